"""The accuracy benchmark: LGI and the baselines on the same frames, in one run (``lgi bench``,
``benchmarks/bench_accuracy.py``).

The test sets are built by :mod:`lgi.evaluation.benchsets` (their frames are never dataset shapes): (a) the
synthetic actor's held-out performance, (b) an ICT actor with a rotating jaw, (c) held-out ICT shapes,
(d) ICT with combination shapes and their correctives, (e) a capture session: the synthetic actor's shapes
plus 0, 150 or 400 captured poses of another performance (``session_N``), and the frames of (d) against
the ICT actor's shapes plus 150 captured frames of another performance (``ict_session``); each with clean
bundles and with tracking noise (0.3 mm per coordinate, 5 % of marker-frames missing in runs).

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
  :mod:`lgi.evaluation.baselines`;
* on noisy bundles, ``blendshape fit + rig, smoothed bundles`` (``blendshape fit, smoothed bundles``
  without a rig): the same fit of the bundles smoothed exactly as LGI smooths them (noise estimated from
  the shot, each marker's trajectory filtered, :meth:`~lgi.solve.solver.LGISolver.denoise`; missing
  markers stay missing), so that LGI's lead on noisy shots is not only its use of time;
* on the session sets (names starting ``session`` or ``ict_session``) the plain blendshape fit is
  ``blendshape fit (ridge chosen on the truth)``: of four L2 weights (:data:`RIDGE_L2`, cm^2 per unit
  weight^2) the one whose reconstruction has the lowest RMS over the set's measured vertices, chosen
  per run (clean and noisy apart) *by looking at the true surface*, which no method can do in use;
  the chosen weight is in the ``note`` column. **This favours that baseline**: a dataset with hundreds of
  near-duplicate scans is where a ridge helps a least-squares fit, and it gets its best one for free.
  Its frames/s counts all four fits.

Columns: vertex error RMS / p95 / max over the set's measured vertices (face area), RMS on the lips and
on the frames opened wide, RMS and max over the measured vertices farther than 2 cm from every marker
(``rms_far_mm``, ``max_far_mm``: where no bundle constrains the surface; UV-geodesic distance, the
index's natural-neighbour ``nn_distance``), the largest distance of a seen bundle from the surface (mm),
frames/s, and the ratio of each method's RMS and p95 to the best baseline's.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from lgi.evaluation.baselines import BlendshapeSolver, RBFSolver, RiggedBlendshapeSolver, SmoothSolver
from lgi.evaluation.metrics import jitter, normal_angle_errors, vertex_errors
from lgi.index.build import build_index
from lgi.solve.solver import LGISolver
from lgi.units import MM_PER_CM

ICT_HELD_OUT = ["mouthFunnel", "mouthSmile_L", "browInnerUp_R", "cheekPuff_R", "noseSneer_L", "jawLeft"]

#: L2 weights (cm^2 per unit weight^2) tried by the session sets' blendshape fit, the best chosen on the truth.
RIDGE_L2 = (0.0, 1e-5, 1e-4, 1e-3)
#: Vertices farther than this (cm, UV-geodesic) from every marker are "far" (``rms_far_mm``, ``max_far_mm``).
FAR_CM = 2.0
SESSION_PREFIXES = ("session", "ict_session")


@dataclass
class Method:
    """A method of the benchmark: a label, whether it is a baseline, a function from bundle positions
    (F, M, 3) cm to vertices (F, V, 3), and a note the run may leave (shown in the table's ``note``)."""

    label: str
    baseline: bool
    run: Callable[[np.ndarray], np.ndarray]
    note: str = ""


def lgi_method(index, label: str = "LGI (default)", **options) -> Method:
    """LGI through :meth:`LGISolver.solve_sequence` with its defaults (those of ``lgi reconstruct``, which declares
    them from :class:`~lgi.solve.settings.SolverSettings`), overridden by ``options`` (solver and sequence options
    together)."""
    seq_keys = {"smooth", "jaw_smooth", "max_gap", "noise"}
    seq = {k: v for k, v in options.items() if k in seq_keys}
    ctor = {k: v for k, v in options.items() if k not in seq_keys}

    def run(pos: np.ndarray) -> np.ndarray:
        return LGISolver(index, **ctor).solve_sequence(pos, **seq).vertices

    return Method(label, False, run)


def _sequence(solver) -> Callable[[np.ndarray], np.ndarray]:
    return solver.solve_sequence


def smoothed_bundles(index, solver) -> Callable[[np.ndarray], np.ndarray]:
    """``solver.solve_sequence`` of the bundles smoothed exactly as LGI smooths them before its fit.

    The noise is estimated from the shot (``--noise auto``, :meth:`~lgi.solve.solver.LGISolver.resolve_noise`:
    independent poses or clean bundles are left as they are) and each marker's trajectory filtered
    (:meth:`~lgi.solve.solver.LGISolver.denoise`); rows of missing markers stay NaN, which the baselines' fits
    leave out frame by frame.
    """
    def run(pos: np.ndarray) -> np.ndarray:
        s = LGISolver(index)
        return solver.solve_sequence(s.denoise(pos, s.resolve_noise(pos, "auto"))[0])

    return run


def ridge_on_truth(bench_set, l2s: tuple[float, ...] = RIDGE_L2,
                   label: str = "blendshape fit (ridge chosen on the truth)") -> Method:
    """The bounded blendshape fit with the best of several L2 weights, chosen on the set's true surface.

    The method's run fits the bundles with every weight of ``l2s`` (cm^2 per unit weight^2) and returns the
    reconstruction with the lowest RMS error over the set's measured vertices against the truth of the same
    frames (the set's first F frames, as :func:`run_set` passes them), leaving ``l2=...`` in ``note``. No
    method can choose so in use: this favours the baseline.

    Raises
    ------
    ValueError
        No ``l2s``; from the run, when the positions are not the set's first frames (clean or noisy): the
        truth would not be theirs.
    """
    if not l2s:
        raise ValueError("no L2 weight to choose from")
    bs = bench_set
    solvers = [BlendshapeSolver(bs.dataset, bs.layout, l2=l2) for l2 in l2s]

    def run(pos: np.ndarray) -> np.ndarray:
        n = len(pos)
        if not any(np.array_equal(pos, b[:n], equal_nan=True) for b in (bs.bundles, bs.noisy)):
            raise ValueError(f"{label}: the positions are not the first {n} frames of set {bs.name}")
        truth = bs.truth[:n]
        best: tuple[float, float, np.ndarray] | None = None
        for l2, solver in zip(l2s, solvers, strict=True):
            recon = solver.solve_sequence(pos)
            rms = float(np.sqrt(np.mean(vertex_errors(recon, truth)[:, bs.mask] ** 2)))
            if best is None or rms < best[0]:
                best = (rms, l2, recon)
        assert best is not None  # l2s is not empty
        method.note = f"l2={best[1]:g}"
        return best[2]

    method = Method(label, True, run)
    return method


def methods_for(bench_set, index, noisy: bool = False) -> list[Method]:
    """The methods compared on a set, given its index (built with the set's rig when it has one)."""
    rig = index.jaw_rig()
    out = [lgi_method(index), lgi_method(index, "LGI simplex (paper)", method="simplex", noise=0, smooth=1)]
    if noisy:
        out.append(lgi_method(index, "LGI --smooth 5 (no noise model)", noise=0, smooth=5))
    ds, layout = bench_set.dataset, bench_set.layout
    if bench_set.name.startswith(SESSION_PREFIXES):
        out.append(ridge_on_truth(bench_set))
    else:
        out.append(Method("blendshape fit", True, _sequence(BlendshapeSolver(ds, layout))))
    if rig is not None:
        out.append(Method("blendshape fit + rig", True, _sequence(RiggedBlendshapeSolver(index))))
        if noisy:
            out.append(Method("blendshape fit + rig, smoothed bundles", True,
                              smoothed_bundles(index, RiggedBlendshapeSolver(index))))
    elif noisy:
        out.append(Method("blendshape fit, smoothed bundles", True,
                          smoothed_bundles(index, BlendshapeSolver(ds, layout))))
    out.append(Method("RBF weights + smooth", True, _sequence(RBFSolver(index))))
    jaw_fit = RiggedBlendshapeSolver(index).fit if rig is not None else None
    out.append(Method("smooth (shell)" + (" + rig" if rig is not None else ""), True,
                      _sequence(SmoothSolver(ds.neutral, ds.triangles, layout, rig=rig, jaw_fit=jaw_fit))))
    return out


def far_vertices(bench_set, index=None, radius_cm: float = FAR_CM) -> np.ndarray:
    """(V,) bool: the set's measured vertices farther than ``radius_cm`` from every marker.

    The distance is the index's natural-neighbour one (``nn_distance``: UV-geodesic on the welded mesh, cm
    equivalents; a vertex no marker reaches counts as far); without an index (or one without it), the
    straight-line distance on the neutral to the nearest marker's rest position.
    """
    bs = bench_set
    if index is not None and "nn_distance" in index.arrays:
        d = np.asarray(index.arrays["nn_distance"], np.float64)
    else:
        from scipy.spatial import cKDTree

        x0 = np.asarray(bs.dataset.neutral, np.float64)
        d, _ = cKDTree(bs.layout.evaluate(x0)).query(x0)
    return bs.mask & ~(d <= radius_cm)


def run_set(bench_set, methods: list[Method], noisy: bool = False, frames: int | None = None,
            normal_frames: int = 0, index=None) -> tuple[pd.DataFrame, dict[str, np.ndarray]]:
    """Run every method on one set (clean or noisy bundles).

    ``index`` (the set's, optional) gives the natural-neighbour distances of the "far" columns
    (:func:`far_vertices`).

    Returns
    -------
    table : DataFrame, one row per method (errors in mm); a ``note`` column when a method left one
    mean_error : dict label -> (V,) mean vertex error over frames, mm (for heat maps)
    """
    bs = bench_set
    n = bs.n_frames if frames is None else min(frames, bs.n_frames)
    pos = (bs.noisy if noisy else bs.bundles)[:n]
    truth = bs.truth[:n]
    far = far_vertices(bs, index)
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
               "rms_far_mm": float(np.sqrt(np.mean(err[:, far] ** 2))) if far.any() else np.nan,
               "max_far_mm": float(err[:, far].max()) if far.any() else np.nan,
               "bundle_residual_mm": float(np.nanmax(resid)) * MM_PER_CM, "frames_per_s": n / dt,
               "note": m.note}
        if normal_frames:
            sel = np.unique(np.linspace(0, n - 1, min(normal_frames, n)).astype(int))
            row["normal_deg"] = float(normal_angle_errors(recon[sel], truth[sel], bs.triangles)[:, bs.mask].mean())
        if noisy:
            row["jitter_mm2"] = jitter(recon, bs.mask)
        rows.append(row)
        maps[m.label] = err.mean(0)
    table = pd.DataFrame(rows)
    if not table.note.astype(bool).any():
        table = table.drop(columns="note")
    base = table[table.baseline]
    table["rms_vs_best_baseline"] = table.rms_mm / base.rms_mm.min()
    table["p95_vs_best_baseline"] = table.p95_mm / base.p95_mm.min()
    return table, maps


def build_set_index(bench_set, show_progress: bool = False):
    """The LGI index of a set's dataset and layout (with its rig when it has one)."""
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
            table, m = run_set(bs, methods_for(bs, index, noisy), noisy, frames, index=index)
            tables.append(table)
            maps[f"{name}_{'noisy' if noisy else 'clean'}"] = m
            log(f"\n{name}, {'noisy' if noisy else 'clean'} bundles: {bs.description}")
            log(format_table(table))
    return pd.concat(tables, ignore_index=True), maps


def format_table(table: pd.DataFrame) -> str:
    """One set's rows as a Markdown table (a ``note`` column only when some row has one)."""
    cols = {"method": "method", "rms_mm": "RMS mm", "p95_mm": "p95 mm", "max_mm": "max mm",
            "lips_rms_mm": "lips RMS mm", "wide_open_rms_mm": "wide-open RMS mm", "max_far_mm": "far max mm",
            "bundle_residual_mm": "bundle residual mm", "normal_deg": "normal error deg",
            "jitter_mm2": "jitter mm^2", "rms_vs_best_baseline": "RMS / best baseline",
            "p95_vs_best_baseline": "p95 / best baseline", "frames_per_s": "frames/s", "note": "note"}
    keep = [c for c in cols if c in table and (c != "note" or table[c].fillna("").astype(bool).any())]
    t = table[keep].rename(columns=cols)
    fmt = {"RMS mm": "{:.3g}", "p95 mm": "{:.3g}", "max mm": "{:.3g}", "lips RMS mm": "{:.3g}",
           "wide-open RMS mm": "{:.3g}", "far max mm": "{:.2f}", "bundle residual mm": "{:.1e}",
           "normal error deg": "{:.2f}", "jitter mm^2": "{:.4f}", "RMS / best baseline": "{:.2f}",
           "p95 / best baseline": "{:.2f}", "frames/s": "{:.0f}"}
    lines = ["| " + " | ".join(t.columns) + " |", "|" + "---|" * len(t.columns)]
    for _, r in t.iterrows():
        lines.append("| " + " | ".join("-" if isinstance(r[c], float) and np.isnan(r[c]) else
                                       fmt.get(c, "{}").format(r[c]) for c in t.columns) + " |")
    return "\n".join(lines)
