"""The synthetic-actor jobs: ``lgi synth`` (dataset, markers, performance, truth, optional HMC footage) and
``lgi demo`` (the main job end to end on it)."""

from __future__ import annotations

import logging
import math
import os
import re
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from lgi.errors import InputError
from lgi.options import declared, option, same_as
from lgi.units import MM_PER_CM

#: What ``lgi synth`` writes into its output directory (an earlier run's ``hmc/`` goes when --hmc is not given).
SYNTH_OUTPUTS = ("dataset", "markers.csv", "bundles.csv", "jaw_rig.npz", "truth.npz", "hmc", "template")
#: What the output folders hold (anything else there is someone else's: the run refuses to replace it).
SYNTH_CONTENTS = {"dataset": ("manifest.json", "mesh.npz", "deltas.npy"),
                  "template": ("manifest.json", "mesh.npz", "deltas.npy"),
                  "hmc": ("cam0", "cam1", "calib", "*.json", "*.csv", "*.npz")}


def _physical_memory() -> int | None:
    """This machine's memory in bytes (None where the OS does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None


def parse_size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` (each 64 to 8192) as integers."""
    m = re.fullmatch(r"(\d+)x(\d+)", str(text).strip())
    if not m or not (64 <= int(m[1]) <= 8192 and 64 <= int(m[2]) <= 8192):
        raise InputError(f"--image-size {text!r}: expected WIDTHxHEIGHT, each side 64 to 8192 pixels")
    return int(m[1]), int(m[2])


_HMC_ONLY = ("lens", "image_size", "dot_noise", "board_views", "rig_flex", "contour_noise", "slip")


@declared
@dataclass(frozen=True)
class SynthOptions:
    """Options of ``lgi synth`` (:mod:`lgi.options`)."""

    vertices: int = option(20000, "at least this many mesh vertices (default %(default)s)",
                           group="actor and performance", metavar="N")
    frames: int = option(240, "performance length, frames (default %(default)s)", group="actor and performance",
                         metavar="F", units="frames")
    seed: int = option(0, "performance seed (default %(default)s)", group="actor and performance", metavar="S")
    hmc: bool = option(
        False, "also render head-mounted camera footage into DIR/hmc (frames, board views, true cameras, "
        "lip_contours.csv)", group="head-mounted camera footage")
    lens: str = option("fisheye", "with --hmc: lens model (default %(default)s)", group="head-mounted camera footage",
                       choices=("fisheye", "pinhole"))
    image_size: str = option("1280x1024", "with --hmc: image size, px (default %(default)s)",
                             group="head-mounted camera footage", metavar="WxH")
    dot_noise: float = option(
        0.3, "with --hmc: random offset of each painted dot per camera and frame, px (default %(default)s)",
        group="head-mounted camera footage", metavar="PX", units="px")
    board_views: int = option(15, "with --hmc: calibration board views (default %(default)s)",
                              group="head-mounted camera footage", metavar="N")
    rig_flex: float = option(
        0.0, "with --hmc: turn camera 1 by this angle during the shot, after calibration, deg (default %(default)s; "
        "see lgi track --helmet)", group="head-mounted camera footage", metavar="DEG", units="deg")
    contour_noise: float = option(
        0.0, "with --hmc: Gaussian noise of the true lip contours in DIR/hmc/lip_contours.csv, px (default "
        "%(default)s)", group="head-mounted camera footage", metavar="PX", units="px")
    actor: int = option(
        0, "another actor: proportions and expression details drawn from SEED, same mesh topology (default "
        "%(default)s: the default actor)", group="actor and performance", metavar="SEED")
    slip: str = option(
        "smooth", "with --hmc: how the helmet moves on the head during the shot: smooth (a slow drift of up to 1 deg "
        "and 1.5 mm) or jolts (that drift plus sudden shifts of 0.5-1.5 deg and 1-3 mm over 1-3 frames, each then "
        "held, and a vibration of about 0.02 deg / 0.03 mm) (default %(default)s)",
        group="head-mounted camera footage", choices=("smooth", "jolts"))
    template: bool = option(
        False, "also write DIR/template: a template rig for lgi rig-generate on this mesh, the default actor's 13 "
        "named controls and its combination shapes (a+b, the pairs that are not the sum of their parts: up to 24)",
        group="actor and performance")

    def __post_init__(self) -> None:
        for name, least, most in (("vertices", 1, 2_000_000), ("frames", 1, 1_000_000), ("seed", 0, 2**32 - 1),
                                  ("board_views", 3, 500), ("actor", 0, 2**31 - 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not least <= v <= most:
                raise InputError(f"--{name.replace('_', '-')} must be a whole number in [{least}, {most}], not {v!r}")
        # The true meshes of the whole performance are held in memory (float32) and written to truth.npz.
        need = 4 * 3 * self.vertices * self.frames * 2
        have = _physical_memory()
        if have and need > have // 2:
            raise InputError(f"--vertices {self.vertices} x --frames {self.frames}: the true meshes need about "
                             f"{need / 2**30:.1f} GiB of memory, more than half of this machine's "
                             f"{have / 2**30:.1f} GiB; use fewer vertices or frames")
        from lgi.synthetic.hmc import SLIPS

        if self.slip not in SLIPS:
            raise InputError(f"--slip takes {' or '.join(SLIPS)}, not {self.slip!r}")
        if self.lens not in ("fisheye", "pinhole"):
            raise InputError(f"--lens takes fisheye or pinhole, not {self.lens!r}")
        for name in ("dot_noise", "rig_flex", "contour_noise"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or (name != "rig_flex" and v < 0):
                raise InputError(f"--{name.replace('_', '-')}: {v!r} is not a valid value")
        parse_size(self.image_size)
        if not self.hmc:
            given = [f"--{f.name.replace('_', '-')}" for f in fields(self) if f.name in _HMC_ONLY
                     and getattr(self, f.name) != f.default]
            if given:
                # Warned, not refused: releases before the check ignored them, and scripts may still pass them.
                logging.getLogger(__name__).warning(
                    f"{', '.join(given)} shape{'s' if len(given) == 1 else ''} the camera footage, which only --hmc "
                    "renders: ignored (add --hmc)")

    def footage(self):
        """The settings of :func:`lgi.synthetic.hmc.write_footage`
        (:class:`~lgi.synthetic.hmc.FootageSettings`), or None without ``hmc``."""
        if not self.hmc:
            return None
        from lgi.synthetic.hmc import FootageSettings

        return FootageSettings(model=self.lens, size=parse_size(self.image_size), seed=self.seed,
                               dot_noise_px=self.dot_noise, board_views=self.board_views, flex_deg=self.rig_flex,
                               contour_noise_px=self.contour_noise, slip=self.slip)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def write_synthetic(out: str | Path, options: SynthOptions, show_progress: bool = False) -> dict[str, Any]:
    """``lgi synth``: the synthetic actor's dataset, markers, performance bundles, jaw rig and truth in ``out``
    (:data:`SYNTH_OUTPUTS`).

    With ``hmc``, also HMC footage in ``out/hmc``; the performance then starts from the neutral face (a 15-frame
    ramp), as a shot does. Returns the actor, dataset, layout, activations and truth (for the demo and tests)
    and ``outputs``, the paths written.
    """
    from lgi.capture.bundles import Bundles, write_bundles
    from lgi.dataset.markers import write_layout
    from lgi.io.atomic import check_contents, check_output, job_outputs
    from lgi.io.npz import save_npz
    from lgi.synthetic import actor as synth

    o = options
    check_output(out, "dir")
    check_contents(out, SYNTH_CONTENTS, SYNTH_OUTPUTS)
    hmc = o.footage()
    actor = synth.make_actor(o.vertices, synth.ActorVariant.draw(o.actor))
    ds = synth.make_dataset(actor)
    layout, dist = synth.default_layout(actor)
    acts = synth.random_performance(o.frames, seed=o.seed)
    if hmc is not None:
        acts = acts * np.clip(np.arange(o.frames) / 15.0, 0.0, 1.0)[:, None]
    truth = actor.evaluate_many(acts)
    bundles = Bundles(frames=np.arange(o.frames), markers=layout.names,
                      positions=layout.evaluate(truth.astype(np.float64)))
    with job_outputs(out, SYNTH_OUTPUTS, SYNTH_CONTENTS) as stage:
        ds.save(stage / "dataset")
        write_layout(stage / "markers.csv", layout, neutral=actor.neutral)
        write_bundles(stage / "bundles.csv", bundles)
        synth.jaw_rig(actor).save(stage / "jaw_rig.npz")
        save_npz(stage / "truth.npz", vertices=truth, activations=acts.astype(np.float32),
                 controls=np.asarray(synth.CONTROLS), jaw=actor.jaw_parameters(acts).astype(np.float32),
                 frames=np.arange(o.frames))
        if o.template:
            synth.template_dataset(o.vertices).save(stage / "template")
        if hmc is not None:
            from lgi.synthetic.hmc import write_footage

            footage = write_footage(stage / "hmc", actor, layout, acts, hmc, show_progress)
    names = ["dataset", "markers.csv", "bundles.csv", "truth.npz", "jaw_rig.npz", *(["template"] if o.template else [])]
    if hmc:
        names += ["hmc/cam0", "hmc/cam1", "hmc/calib", "hmc/cameras_true.json", "hmc/helmet.csv", "hmc/truth.npz",
                  "hmc/lip_contours.csv"]
    return {"actor": actor, "dataset": ds, "layout": layout, "activations": acts, "truth": truth,
            "marker_snap_cm": float(dist.max()), "outputs": [str(Path(out) / n) for n in names],
            "lip_contour_visible": footage["lip_contour_visible"] if hmc else None}


def synth_report(r: dict[str, Any], options: SynthOptions) -> list[str]:
    who = f"synthetic actor {options.actor}" if options.actor else "synthetic actor"
    return [f"{who}: {r['actor'].n_vertices} vertices, {r['dataset'].n_shapes} shapes, "
            f"{len(r['layout'])} markers, {options.frames} frames (seed {options.seed})",
            *(f"  {p}" for p in r["outputs"]),
            *([] if not r.get("lip_contour_visible") else [
                "lip contours (hmc/lip_contours.csv): share of the inner edges' points each camera sees, "
                + ", ".join(f"{k} {100 * v:.1f} %" for k, v in r["lip_contour_visible"].items())])]


@declared
@dataclass(frozen=True)
class DemoOptions:
    """Options of ``lgi demo`` (:mod:`lgi.options`): those of ``lgi synth``'s actor and performance."""

    vertices: int = same_as(SynthOptions, "vertices")
    frames: int = same_as(SynthOptions, "frames")
    seed: int = same_as(SynthOptions, "seed")

    def __post_init__(self) -> None:
        SynthOptions(vertices=self.vertices, frames=self.frames, seed=self.seed)


def demo(out: str | Path, options: DemoOptions | None = None, show_progress: bool = False,
         log=print) -> dict[str, Any]:
    """``lgi demo``: the synthetic actor written, its index built with the jaw rig, its performance reconstructed
    (the reconstruct job's defaults) and compared with the truth; each step reported through ``log`` as it
    ends. Returns the figures."""
    from lgi.index.build import build_index
    from lgi.jobs.reconstruct import ReconstructOptions, Shot, write_reconstruction
    from lgi.synthetic import actor as synth

    o = options or DemoOptions()
    out = Path(out)
    t0 = time.perf_counter()
    r = write_synthetic(out, SynthOptions(vertices=o.vertices, frames=o.frames, seed=o.seed), show_progress)
    actor = r["actor"]
    log(f"[1/4] synthetic actor: {actor.n_vertices} vertices, {r['dataset'].n_shapes} dataset shapes, "
        f"{len(r['layout'])} markers, {o.frames}-frame performance ({time.perf_counter() - t0:.1f} s)")
    nl = synth.nonlinearity(actor, r["activations"])
    log("[2/4] how far the truth is from a linear blend of the extreme shapes (mm), over the performance:")
    log(f"      RMS per frame: median {np.median(nl[:, 0]):.2f}, 95th pct {np.percentile(nl[:, 0], 95):.2f}; "
        f"max per frame: median {np.median(nl[:, 1]):.2f}, 95th pct {np.percentile(nl[:, 1], 95):.2f}, "
        f"worst {nl[:, 1].max():.2f}")
    t = time.perf_counter()
    index, reports = build_index(r["dataset"], r["layout"], show_progress=show_progress,
                                 jaw_rig=synth.jaw_rig(actor))
    index.save(out / "index", reports)
    log(f"[3/4] LGI index (jaw rig, unskinned shapes): {index.manifest['counts']['simplices']} simplices over "
        f"{len(r['layout'])} bundles ({time.perf_counter() - t:.1f} s)")
    opts = ReconstructOptions()
    shot = Shot(out / "index", out / "bundles.csv", opts)
    # A few frames first: the compiled kernels are built (first run) or loaded from their cache, so the
    # timed run below is the steady state.
    t = time.perf_counter()
    shot.finish(shot.choose(0, 3), 0, 3)
    warm = time.perf_counter() - t
    t = time.perf_counter()
    res = shot.run(show_progress)
    dt = time.perf_counter() - t
    write_reconstruction(out, res, index.arrays, opts, noise_estimate=shot.noise.estimate)
    err = np.linalg.norm(res.vertices - r["truth"], axis=2) * MM_PER_CM
    s = {"frames_per_second": o.frames / dt, "warm_up_s": warm, "rms_mm": float(np.sqrt(np.mean(err**2))),
         "p95_mm": float(np.percentile(err, 95)), "max_mm": float(err.max()),
         "max_residual_mm": float(np.nanmax(res.diagnostics.residual_mm))}
    log(f"[4/4] reconstructed the {o.frames}-frame performance (frames not in the dataset) at "
        f"{s['frames_per_second']:.0f} frames/s steady state (kernel compilation or cache load and 3 warm-up "
        f"frames: {warm:.1f} s); error against the truth: RMS {s['rms_mm']:.3f} mm, 95th pct {s['p95_mm']:.3f} mm, "
        f"max {s['max_mm']:.2f} mm; max bundle residual {s['max_residual_mm']:.1e} mm")
    log(f"outputs in {out.resolve()}: dataset/, markers.csv, bundles.csv, truth.npz, index/, meshes.npz, "
        f"diagnostics.csv, per_frame.csv, run.json, review/")
    from lgi.jobs.reconstruct import summarise
    from lgi.jobs.review import ReviewOptions, review_beside

    page = review_beside(out, out / "index", {**summarise(res, shot, out, {"load": 0.0, "solve": dt}),
                                              "options": opts.to_json()},
                         ReviewOptions(truth=str(out / "truth.npz")))
    s["review"] = page["page"]
    log(f"review page (open it in a browser; no server needed): {page['page']}")
    return s
