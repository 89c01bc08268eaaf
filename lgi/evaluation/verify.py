"""The paper's verification (section 7.1): every dataset shape reconstructed from its own bundles."""

from __future__ import annotations

import fnmatch

import numpy as np
import pandas as pd

from lgi.index.build import LGIIndex
from lgi.progress import progress
from lgi.solve.solver import LGISolver
from lgi.units import MM_PER_CM


def verify_index(index: LGIIndex, solver: LGISolver | None = None, shapes: str | None = None,
                 show_progress: bool = False) -> pd.DataFrame:
    """Reconstruct each dataset shape from its bundle positions and measure the error.

    Parameters
    ----------
    index
        A built index (it holds every shape's bundle positions and displacements; with a jaw rig, the
        shapes are skinned back with their fitted jaw, given to the solver as a tracked jaw).
    solver
        The solver to use (default: single-frame settings).
    shapes
        Shell patterns (comma-separated) selecting shapes; default all.

    Returns
    -------
    DataFrame
        One row per shape: ``rms_mm`` and ``max_mm``, the vertex error over the marked region (vertices
        within the natural-neighbour region radius of a bundle: what the markers constrain);
        ``rms_all_mm`` and ``max_all_mm`` over the whole mesh (eyeballs, teeth and the back of the head
        move only through the shapes chosen at the face, so a shape that moves only them, such as a
        pupil dilation, cannot be seen by face markers); ``residual_mm`` (largest bundle residual);
        ``projected`` (bundles outside their cloud).
    """
    solver = solver or LGISolver(index)
    names = index.manifest["shapes"]
    pats = [p.strip() for p in (shapes or "").split(",") if p.strip()]
    pick = [k for k, n in enumerate(names) if not pats or any(fnmatch.fnmatchcase(n, p) for p in pats)]
    x0 = np.asarray(index.arrays["neutral"], np.float64)
    region = np.asarray(index.arrays["nn_region"], bool)
    rows = []
    rig = index.jaw_rig()
    layout = solver.layout
    for k in progress(pick, "verifying", disable=not show_progress):
        truth = x0 + np.asarray(index.deltas[k + 1], np.float64)
        if rig is None:
            r = solver.solve_frame(index.arrays["ptab"][k + 1])
        else:
            # The index holds unskinned shapes: skin each with its fitted jaw and solve from its bundles
            # with that jaw given, as for a shot whose jaw was tracked (paper 7.2). Estimating the jaw
            # from the bundles is measured by benchmarks/bench_jaw.py.
            theta = index.arrays["jaw_shape_params"][k]
            truth = rig.skin(truth, theta)
            r = solver.solve_frame(layout.evaluate(truth), jaw=theta)
        err = np.linalg.norm(r.vertices.astype(np.float64) - truth, axis=1) * MM_PER_CM
        er = err[region]
        rows.append((names[k], float(np.sqrt(np.mean(er**2))), float(er.max()), float(np.sqrt(np.mean(err**2))),
                     float(err.max()), _finite_max(r.residual) * MM_PER_CM, int((r.status == 1).sum())))
    return pd.DataFrame(rows, columns=["shape", "rms_mm", "max_mm", "rms_all_mm", "max_all_mm", "residual_mm",
                                       "projected"])


def _finite_max(a: np.ndarray) -> float:
    """Largest finite value of ``a``, NaN when it has none (a non-finite shape's residuals: the row then fails
    the check on its error, without numpy's all-NaN warning)."""
    a = np.asarray(a, np.float64)
    a = a[np.isfinite(a)]
    return float(a.max()) if a.size else float("nan")
