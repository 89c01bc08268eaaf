"""The accuracy benchmark: LGI and the baselines on the same frames, in one run (``lgi bench``,
``benchmarks/bench_accuracy.py``).

The test sets are built by :mod:`lgi.evaluation.benchsets` (their frames are never dataset shapes): (a) the
synthetic actor's held-out performance, (b) an ICT actor with a rotating jaw, (c) held-out ICT shapes,
(d) ICT with combination shapes and their correctives, each with clean bundles and with tracking noise
(0.3 mm per coordinate, 5 % of marker-frames missing in runs).

Every method gets the same information. Where a set has a jaw rig, LGI indexes unskinned shapes and
estimates each frame's jaw with the shape weights (:class:`~lgi.solve.globalfit.GlobalFit`), and every
baseline gets that rig and that jaw estimate: the blendshape fit solves the same joint problem (it *is*
the jaw estimator), the shell interpolates from the neutral skinned by the jaw, RBF skins its blend.
The plain blendshape fit of the dataset's shapes as they are is shown beside them.

Methods:

* ``LGI (default)``: ``lgi reconstruct``'s defaults (local fits, noise estimated from the shot and,
  when the bundles are noisy, weights smoothed over time);
* ``LGI simplex (paper)``: the paper's choice among containing simplices only (``--method simplex
  --noise 0 --smooth 1``); on noisy sets also ``LGI --smooth 5`` (``--noise 0 --smooth 5``);
* ``blendshape fit``, ``blendshape fit + rig``, ``RBF weights + smooth``, ``smooth (shell)``:
  :mod:`lgi.evaluation.baselines`.

Columns: vertex error RMS / p95 / max over the set's measured vertices (face area), RMS on the lips and
on the frames opened wide, the largest distance of a seen bundle from the surface (mm), frames/s, and
the ratio of each method's RMS and p95 to the best baseline's.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from lgi.evaluation.baselines import BlendshapeSolver, RBFSolver, RiggedBlendshapeSolver, SmoothSolver
from lgi.evaluation.metrics import jitter, normal_angle_errors, vertex_errors
from lgi.units import MM_PER_CM

ICT_HELD_OUT = ["mouthFunnel", "mouthSmile_L", "browInnerUp_R", "cheekPuff_R", "noseSneer_L", "jawLeft"]

# What ``lgi reconstruct`` does by default (kept in one place with the CLI's defaults).
LGI_DEFAULTS = {"temporal_weight": 0.02, "spatial_weight": 1e-3, "max_gap": 0}


@dataclass
class Method:
    """A method of the benchmark: a label, whether it is a baseline, and a function from bundle positions
    (F, M, 3) cm to vertices (F, V, 3)."""

    label: str
    baseline: bool
    run: Callable[[np.ndarray], np.ndarray]


def lgi_method(index, label: str = "LGI (default)", **options) -> Method:
    """LGI through :meth:`LGISolver.solve_sequence` with ``lgi reconstruct``'s defaults, overridden by
    ``options`` (solver and sequence options together)."""
    from lgi.solve.solver import LGISolver

    seq_keys = {"smooth", "jaw_smooth", "max_gap", "noise"}
    opts = {**LGI_DEFAULTS, **options}
    seq = {k: v for k, v in opts.items() if k in seq_keys}
    ctor = {k: v for k, v in opts.items() if k not in seq_keys}

    def run(pos: np.ndarray) -> np.ndarray:
        return LGISolver(index, **ctor).solve_sequence(pos, **seq).vertices

    return Method(label, False, run)


def _sequence(solver) -> Callable[[np.ndarray], np.ndarray]:
    return solver.solve_sequence


def methods_for(bench_set, index, noisy: bool = False) -> list[Method]:
    """The methods compared on a set, given its index (built with the set's rig when it has one)."""
    rig = index.jaw_rig()
    out = [lgi_method(index), lgi_method(index, "LGI simplex (paper)", method="simplex", noise=0, smooth=1)]
    if noisy:
        out.append(lgi_method(index, "LGI --smooth 5 (no noise model)", noise=0, smooth=5))
    ds, layout = bench_set.dataset, bench_set.layout
    out.append(Method("blendshape fit", True, _sequence(BlendshapeSolver(ds, layout))))
    if rig is not None:
        out.append(Method("blendshape fit + rig", True, _sequence(RiggedBlendshapeSolver(index))))
    out.append(Method("RBF weights + smooth", True, _sequence(RBFSolver(index))))
    jaw_fit = RiggedBlendshapeSolver(index).fit if rig is not None else None
    out.append(Method("smooth (shell)" + (" + rig" if rig is not None else ""), True,
                      _sequence(SmoothSolver(ds.neutral, ds.triangles, layout, rig=rig, jaw_fit=jaw_fit))))
    return out


def run_set(bench_set, methods: list[Method], noisy: bool = False, frames: int | None = None,
            normal_frames: int = 0) -> tuple[pd.DataFrame, dict[str, np.ndarray]]:
    """Run every method on one set (clean or noisy bundles).

    Returns
    -------
    table : DataFrame, one row per method (errors in mm)
    mean_error : dict label -> (V,) mean vertex error over frames, mm (for heat maps)
    """
    bs = bench_set
    n = bs.n_frames if frames is None else min(frames, bs.n_frames)
    pos = (bs.noisy if noisy else bs.bundles)[:n]
    truth = bs.truth[:n]
    rows, maps = [], {}
    for m in methods:
        t = time.perf_counter()
        recon = np.asarray(m.run(pos), np.float64)
        dt = time.perf_counter() - t
        err = vertex_errors(recon, truth)
        e = err[:, bs.mask]
        seen = np.all(np.isfinite(pos), axis=2)
        resid = []
        for c in range(3):
            at = np.einsum("fmk,mk->fm", recon[:, bs.layout.vertices, c], bs.layout.weights)
            resid.append(at - np.where(seen, pos[..., c], 0.0))
        resid = np.where(seen, np.linalg.norm(np.stack(resid, -1), axis=-1), np.nan)
        row = {"set": bs.name, "bundles": "noisy" if noisy else "clean", "method": m.label, "baseline": m.baseline,
               "rms_mm": float(np.sqrt(np.mean(e**2))), "p95_mm": float(np.percentile(e, 95)),
               "max_mm": float(e.max()),
               "lips_rms_mm": float(np.sqrt(np.mean(err[:, bs.lips] ** 2))) if bs.lips.any() else np.nan,
               "wide_open_rms_mm": (float(np.sqrt(np.mean(e[bs.wide_open[:n]] ** 2)))
                                    if bs.wide_open[:n].any() else np.nan),
               "bundle_residual_mm": float(np.nanmax(resid)) * MM_PER_CM, "frames_per_s": n / dt}
        if normal_frames:
            sel = np.unique(np.linspace(0, n - 1, min(normal_frames, n)).astype(int))
            row["normal_deg"] = float(normal_angle_errors(recon[sel], truth[sel], bs.triangles)[:, bs.mask].mean())
        if noisy:
            row["jitter_mm2"] = jitter(recon, bs.mask)
        rows.append(row)
        maps[m.label] = err.mean(0)
    table = pd.DataFrame(rows)
    base = table[table.baseline]
    table["rms_vs_best_baseline"] = table.rms_mm / base.rms_mm.min()
    table["p95_vs_best_baseline"] = table.p95_mm / base.p95_mm.min()
    return table, maps


def build_set_index(bench_set, show_progress: bool = False):
    """The LGI index of a set's dataset and layout (with its rig when it has one)."""
    from lgi.index.build import build_index

    index, _ = build_index(bench_set.dataset, bench_set.layout, show_progress=show_progress, jaw_rig=bench_set.rig)
    return index


def accuracy_benchmark(sets: dict, frames: int | None = None, log: Callable[[str], None] = print
                       ) -> tuple[pd.DataFrame, dict[str, dict[str, np.ndarray]]]:
    """Every set, clean and noisy. Returns the long table and the heat-map data per set and bundles kind."""
    tables, maps = [], {}
    for name, bs in sets.items():
        t = time.perf_counter()
        index = build_set_index(bs)
        log(f"{name}: index built in {time.perf_counter() - t:.0f} s")
        for noisy in (False, True):
            table, m = run_set(bs, methods_for(bs, index, noisy), noisy, frames)
            tables.append(table)
            maps[f"{name}_{'noisy' if noisy else 'clean'}"] = m
            log(f"\n{name}, {'noisy' if noisy else 'clean'} bundles: {bs.description}")
            log(format_table(table))
    return pd.concat(tables, ignore_index=True), maps


def format_table(table: pd.DataFrame) -> str:
    cols = {"method": "method", "rms_mm": "RMS mm", "p95_mm": "p95 mm", "max_mm": "max mm",
            "lips_rms_mm": "lips RMS mm", "wide_open_rms_mm": "wide-open RMS mm",
            "bundle_residual_mm": "bundle residual mm", "normal_deg": "normal error deg",
            "jitter_mm2": "jitter mm^2", "rms_vs_best_baseline": "RMS / best baseline",
            "p95_vs_best_baseline": "p95 / best baseline", "frames_per_s": "frames/s"}
    t = table[[c for c in cols if c in table]].rename(columns=cols)
    fmt = {"RMS mm": "{:.3f}", "p95 mm": "{:.3f}", "max mm": "{:.2f}", "lips RMS mm": "{:.3f}",
           "wide-open RMS mm": "{:.3f}", "bundle residual mm": "{:.1e}", "normal error deg": "{:.2f}",
           "jitter mm^2": "{:.4f}", "RMS / best baseline": "{:.2f}", "p95 / best baseline": "{:.2f}",
           "frames/s": "{:.0f}"}
    lines = ["| " + " | ".join(t.columns) + " |", "|" + "---|" * len(t.columns)]
    for _, r in t.iterrows():
        lines.append("| " + " | ".join("-" if isinstance(r[c], float) and np.isnan(r[c]) else
                                       fmt.get(c, "{}").format(r[c]) for c in t.columns) + " |")
    return "\n".join(lines)
