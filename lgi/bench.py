"""Every method on the same frames, in one run: LGI and the baselines of :mod:`lgi.baselines`.

Test sets:

* synthetic: the built-in actor's dataset (47 shapes) and a random performance whose frames are not in
  it; also run with bundle noise (Gaussian, ``noise_mm`` per coordinate) for the jitter measure. LGI
  runs twice: with the actor's jaw rig ("LGI + jaw", shapes unskinned) and without;
* ICT (when the data is there): the dataset is ICT without ``ICT_HELD_OUT`` plus linear combinations
  of the remaining shapes; the test frames are the held-out shapes and mixes of 2-3 shapes that involve
  at least one of them. Errors over the face area (vertices 0-9408).

Columns: vertex error RMS, 95th percentile and max (mm), largest bundle residual (mm), mean normal-angle
error (degrees; how well folds and wrinkles are reproduced), jitter on noisy input (mean squared second
difference, mm^2; the truth's own value is printed beside it), frames/s.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pandas as pd

from .baselines import BlendshapeSolver, LGIMethod, RBFSolver, SmoothSolver
from .evaluate import jitter, normal_angle_errors, vertex_errors

ICT_HELD_OUT = ["mouthFunnel", "mouthSmile_L", "browInnerUp_R", "cheekPuff_R", "noseSneer_L", "jawLeft"]


def _methods(dataset, layout, index, jaw_index=None) -> list:
    lgi_jaw = [] if jaw_index is None else [LGIMethod(jaw_index, temporal_weight=0.02)]
    return [
        *lgi_jaw,
        LGIMethod(index, temporal_weight=0.02),
        RBFSolver(index),
        BlendshapeSolver(dataset, layout),
        BlendshapeSolver(dataset, layout, l2=1e-3),
        SmoothSolver(dataset.neutral, dataset.triangles, layout),
    ]


def _label(m) -> str:
    if isinstance(m, BlendshapeSolver) and m.l2 > 0:
        return f"blendshape (L2 {m.l2:g})"
    if isinstance(m, LGIMethod) and m.solver.rig is not None:
        return "LGI + jaw"
    return {"lgi": "LGI", "rbf": "RBF weights + smooth", "blendshape": "blendshape fit",
            "smooth": "smooth (shell)"}[m.name]


def run_methods(methods: list, truth: np.ndarray, bundles: np.ndarray, triangles: np.ndarray,
                mask: np.ndarray | None = None, noisy: np.ndarray | None = None,
                normal_frames: int = 40) -> tuple[pd.DataFrame, dict[str, np.ndarray]]:
    """Run every method on the same frames.

    Parameters
    ----------
    truth : (F, V, 3) cm; bundles : (F, M, 3) cm
    mask : (V,) bool, optional
        Vertices the errors are measured on.
    noisy : (F, M, 3), optional
        Noisy bundles of the same frames (a sequence) for the jitter column.
    normal_frames : int
        Frames (evenly spread) on which normal angles are measured.

    Returns
    -------
    table : DataFrame, one row per method
    mean_error : dict name -> (V,) mean vertex error over frames, mm (for heat maps)
    """
    rows, maps = [], {}
    sel = np.unique(np.linspace(0, len(truth) - 1, min(normal_frames, len(truth))).astype(int))
    for m in methods:
        t = time.perf_counter()
        recon = m.solve_sequence(bundles)
        dt = time.perf_counter() - t
        resid = max(float(np.nanmax(m.solve_frame(b).residual)) for b in bundles[:: max(1, len(bundles) // 20)])
        err = vertex_errors(recon, truth)
        ang = normal_angle_errors(recon[sel], truth[sel], triangles)
        e = err if mask is None else err[:, mask]
        a = ang if mask is None else ang[:, mask]
        row = {"method": _label(m), "rms_mm": float(np.sqrt(np.mean(e**2))), "p95_mm": float(np.percentile(e, 95)),
               "max_mm": float(e.max()), "bundle_residual_mm": resid * 10, "normal_deg": float(a.mean()),
               "frames_per_s": len(truth) / dt}
        if noisy is not None:
            row["jitter_mm2"] = jitter(m.solve_sequence(noisy), mask)
        rows.append(row)
        maps[_label(m)] = err.mean(0)
    return pd.DataFrame(rows), maps


def synthetic_benchmark(frames: int = 300, noise_mm: float = 0.3, seed: int = 1):
    """The synthetic held-out comparison. Returns (table, heat maps, actor, truth jitter)."""
    from . import synth
    from .index import build_index

    actor = synth.make_actor()
    ds = synth.make_dataset(actor)
    layout, _ = synth.default_layout(actor)
    index, _ = build_index(ds, layout, show_progress=False)
    jaw_index, _ = build_index(ds, layout, show_progress=False, jaw_rig=synth.jaw_rig(actor))
    truth = actor.evaluate_many(synth.random_performance(frames, seed=seed)).astype(np.float64)
    bundles = layout.evaluate(truth)
    rng = np.random.default_rng(seed)
    noisy = bundles + rng.normal(scale=noise_mm / 10, size=bundles.shape)
    table, maps = run_methods(_methods(ds, layout, index, jaw_index), truth, bundles, actor.triangles, noisy=noisy)
    return table, maps, actor, jitter(truth)


def ict_benchmark(ict: Path, n_combinations: int = 400, n_test: int = 60, seed: int = 0):
    """The ICT held-out comparison. Returns (table, heat maps, dataset)."""
    from .augment import linear_combinations
    from .importers import import_obj_folder
    from .index import build_index
    from .markers import read_layout
    from .paths import shipped

    full = import_obj_folder(ict, rigid_vertices="none", show_progress=False)
    layout = read_layout(shipped("markers_ict.csv"), full.triangles)
    keep = [n for n in full.names if n not in ICT_HELD_OUT]
    train = linear_combinations(full.take([full.index(n) for n in keep]), n_combinations, seed=seed)
    mixes = linear_combinations(full, 4000, seed=seed + 7, levels=(0.3, 0.6, 0.9))
    names = [n for n in mixes.names[full.n_shapes:] if any(h + "*" in n for h in ICT_HELD_OUT)][:n_test]
    test = mixes.take([mixes.index(n) for n in names])
    truth = np.concatenate([full.neutral[None] + np.asarray(full.deltas[[full.index(h) for h in ICT_HELD_OUT]],
                                                                      np.float64),
                            full.neutral[None] + np.asarray(test.deltas, np.float64)])
    index, _ = build_index(train, layout, show_progress=False)
    mask = np.zeros(full.n_vertices, bool)
    mask[:9409] = True
    table, maps = run_methods(_methods(train, layout, index), truth, layout.evaluate(truth), full.triangles, mask)
    return table, maps, full


def format_table(table: pd.DataFrame) -> str:
    cols = {"method": "method", "rms_mm": "RMS mm", "p95_mm": "p95 mm", "max_mm": "max mm",
            "bundle_residual_mm": "bundle residual mm", "normal_deg": "normal error deg",
            "jitter_mm2": "jitter mm^2 (noisy)", "frames_per_s": "frames/s"}
    t = table[[c for c in cols if c in table]].rename(columns=cols)
    fmt = {"RMS mm": "{:.3f}", "p95 mm": "{:.3f}", "max mm": "{:.2f}", "bundle residual mm": "{:.1e}",
           "normal error deg": "{:.2f}", "jitter mm^2 (noisy)": "{:.4f}", "frames/s": "{:.0f}"}
    lines = ["| " + " | ".join(t.columns) + " |", "|" + "---|" * len(t.columns)]
    for _, r in t.iterrows():
        lines.append("| " + " | ".join(fmt.get(c, "{}").format(r[c]) for c in t.columns) + " |")
    return "\n".join(lines)
