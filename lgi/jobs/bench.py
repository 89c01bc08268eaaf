"""The bench job: LGI against the baselines on the same frames (``lgi bench``)."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from lgi.errors import InputError
from lgi.options import declared, option
from lgi.units import MM_PER_CM


@declared
@dataclass(frozen=True)
class BenchOptions:
    """Options of ``lgi bench``: the synthetic set's performance length ``frames`` (the capture-session sets keep
    their own, :func:`lgi.evaluation.benchsets.session_set`), bundle ``noise`` (mm per coordinate) of the noisy
    sets, the ICT FaceKit folder ``ict`` (default: the shared data) or ``no_ict``."""

    frames: int = option(300, "synthetic performance length, frames (default %(default)s)", metavar="F",
                         units="frames")
    noise: float = option(
        0.3, "bundle noise of the noisy sets per coordinate, mm; 5 %% of marker-frames are also missing (default "
        "%(default)s)", metavar="MM", units="mm")
    ict: str | None = option(None, "ICT FaceKit folder (default: ../shared/data/ict-facekit)", metavar="DIR")
    no_ict: bool = option(False, "synthetic sets only (the performance and its sessions)")

    def __post_init__(self) -> None:
        if isinstance(self.frames, bool) or not isinstance(self.frames, int) or not 1 <= self.frames <= 100_000:
            raise InputError(f"--frames must be a whole number in [1, 100000], not {self.frames!r}")
        if not isinstance(self.noise, (int, float)) or not math.isfinite(self.noise) or self.noise < 0:
            raise InputError(f"--noise must be a number of mm >= 0, not {self.noise}")

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def _panels(maps: dict[str, Any]) -> dict[str, Any]:
    """Heat-map panels with long method names broken before their parenthesis, so titles do not overlap."""
    return {(k.replace(" (", "\n(", 1) if len(k) > 24 else k): v for k, v in maps.items()}


def bench(out: str | Path, options: BenchOptions | None = None, log=print) -> dict[str, Any]:
    """``lgi bench``: the accuracy tables (``accuracy.csv``) and heat maps in ``out``; progress and tables
    through ``log``.

    Sets: the synthetic actor's performance and its capture sessions (``session_0``, ``session_150``,
    ``session_400``) always; with the ICT data also ``ict_jaw``, ``ict_heldout``, ``ict_combination`` and
    ``ict_session``."""
    from lgi.evaluation import benchsets
    from lgi.evaluation.accuracy import accuracy_benchmark
    from lgi.evaluation.render import heatmap_row
    from lgi.io.atomic import atomic_file
    from lgi.paths import shared_data

    o = options or BenchOptions()
    from lgi.io.atomic import check_output

    out = Path(out)
    check_output(out, "dir", inputs=[o.ict])
    t0 = time.perf_counter()
    names = ["synthetic", *(f"session_{n}{r}" for r in ("", "_norig") for n in benchsets.SESSION_SCANS)]
    ict = Path(o.ict) if o.ict else shared_data("ict-facekit")
    skipped = None
    if o.no_ict:
        skipped = "--no-ict"
    elif not (ict / "generic_neutral_mesh.obj").is_file():
        if o.ict:  # asked for by name: not finding it is an error, not a reason to skip
            raise InputError("not an ICT FaceKit folder (no generic_neutral_mesh.obj in it)", path=ict)
        skipped = f"ICT FaceKit not found at {ict}"
        log(f"{skipped}: the ICT sets are skipped")
    else:
        names += ["ict_jaw", "ict_heldout", "ict_combination", "ict_session"]
    out.mkdir(parents=True, exist_ok=True)
    sets = {}
    for name in names:
        bs = (benchsets.synthetic_set(frames=o.frames) if name == "synthetic"
              else benchsets.load_sets([name], ict)[name])
        if o.noise != benchsets.NOISE_CM * MM_PER_CM:
            bs = dataclasses.replace(bs, noisy=benchsets.tracking_noise(bs.bundles, bs.info.get("seed", 0),
                                                                       noise_cm=o.noise / MM_PER_CM))
        sets[name] = bs
    table, maps = accuracy_benchmark(sets, log=log)
    with atomic_file(out / "accuracy.csv") as tmp:
        table.to_csv(tmp, index=False, float_format="%.6g")
    pictures = []
    for name, bs in sets.items():
        if name == "synthetic":
            pictures.append(heatmap_row(out / "heatmaps_synthetic.png", bs.dataset.neutral, bs.triangles,
                                        _panels(maps["synthetic_clean"]),
                                        title=f"synthetic held-out performance ({bs.n_frames} frames, clean "
                                              "bundles): mean vertex error"))
        elif not benchsets.needs_ict(name):
            pictures.append(heatmap_row(out / f"heatmaps_{name}.png", bs.dataset.neutral, bs.triangles,
                                        _panels(maps[f"{name}_clean"]),
                                        title=f"{name}: synthetic actor, {bs.dataset.n_shapes} shapes "
                                              f"({bs.n_frames} frames, clean bundles): mean vertex error"))
        else:  # ICT pictures derive from ICT data: written only on request of the ICT sets
            pictures.append(heatmap_row(out / f"heatmaps_{name}.png", bs.dataset.neutral, bs.triangles,
                                        _panels(maps[f"{name}_clean"]), mask=bs.mask,
                                        title=f"{name} (clean bundles): mean vertex error"))
    log(f"heat maps: {', '.join(str(p) for p in pictures)}")
    log(f"({time.perf_counter() - t0:.0f} s; tables and pictures in {out.resolve()})")
    return {"sets": names, "ict_skipped": skipped, "table": str((out / "accuracy.csv").resolve()),
            "pictures": [str(p) for p in pictures]}
