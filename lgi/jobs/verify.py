"""``lgi verify``: every dataset shape reconstructed from its own bundles (paper 7.1); the rebuild-dataset
flow's verify stage calls it with the same :class:`VerifyOptions`."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lgi.errors import InputError
from lgi.jobs.reconstruct.options import ReconstructOptions
from lgi.options import declared, option, same_as

if TYPE_CHECKING:
    import pandas as pd


@declared
@dataclass(frozen=True)
class VerifyOptions:
    """Options of ``lgi verify`` (:mod:`lgi.options`)."""

    tolerance: float = option(0.01, "RMS tolerance over the marked region, mm (default %(default)s)", group="check",
                              metavar="MM", units="mm")
    shapes: str | None = option(None, "only shapes matching these shell patterns (default: all)", group="inputs",
                                metavar="PATTERN")
    spatial_weight: float = same_as(ReconstructOptions, "spatial_weight", group="check")

    def __post_init__(self) -> None:
        for name in ("tolerance", "spatial_weight"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise InputError(f"--{name.replace('_', '-')} must be a finite number of mm >= 0, not {v!r}")

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def verify(index_dir: str | Path, options: VerifyOptions | None = None,
           show_progress: bool = False) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Every selected dataset shape reconstructed from its own bundles: the per-shape table
    (:func:`lgi.evaluation.verify.verify_index`) and a summary whose ``passed`` is the verdict."""
    from lgi.evaluation.verify import verify_index
    from lgi.index.build import LGIIndex
    from lgi.solve.solver import LGISolver

    o = options or VerifyOptions()
    index = LGIIndex.load(index_dir)
    table = verify_index(index, LGISolver(index, spatial_weight=o.spatial_weight), o.shapes,
                         show_progress=show_progress)
    if len(table) == 0:
        raise InputError(f"no shape matches {o.shapes!r}", path=index_dir)
    # A non-finite error fails the check (NaN > tolerance is false, so compare the other way round).
    bad = ~(table.rms_mm <= o.tolerance)
    unseen = table[(table.rms_all_mm > o.tolerance) & ~bad]
    k = int(np.nan_to_num(table.rms_mm.to_numpy(float), nan=np.inf).argmax())  # a NaN is the worst
    summary = {"shapes": len(table), "worst_rms_mm": float(table.rms_mm.max()),
               "worst_shape": str(table["shape"].iloc[k]),
               "worst_max_mm": float(table.max_mm.max()), "worst_rms_all_mm": float(table.rms_all_mm.max()),
               "max_residual_mm": float(table.residual_mm.max()), "tolerance_mm": o.tolerance,
               "failed": int(bad.sum()), "passed": bool(not bad.any()),
               "region_vertices": int(index.arrays["nn_region"].sum()),
               "unseen_outside_region": unseen["shape"].tolist(),
               "non_finite": table["shape"][~np.isfinite(table.rms_mm)].tolist()}
    return table, summary


def verify_report(table: pd.DataFrame, s: dict[str, Any]) -> list[str]:
    lines = [table.to_string(index=False, float_format=lambda v: f"{v:.5f}"),
             f"{s['shapes']} shapes, marked region ({s['region_vertices']} vertices): worst RMS "
             f"{s['worst_rms_mm']:.5f} mm ({s['worst_shape']}), worst max {s['worst_max_mm']:.4f} mm; whole mesh: "
             f"worst RMS {s['worst_rms_all_mm']:.5f} mm; largest bundle residual {s['max_residual_mm']:.2e} mm"]
    if s["unseen_outside_region"]:
        lines.append(f"{len(s['unseen_outside_region'])} shapes move vertices outside the marked region that no marker "
                     f"sees (whole-mesh RMS above tolerance), e.g. {', '.join(s['unseen_outside_region'][:3])}")
    if s["non_finite"]:
        lines.append(f"non-finite errors for {len(s['non_finite'])} shapes (e.g. {', '.join(s['non_finite'][:3])}): "
                     "the index holds non-finite values")
    verdict = f"FAILED for {s['failed']}" if not s["passed"] else "passed"
    lines.append(f"tolerance {s['tolerance_mm']} mm RMS over the marked region: {verdict}")
    return lines
