"""Error measures for reconstructions against a ground truth."""

from __future__ import annotations

import numpy as np

from lgi.dataset.mesh import vertex_normals
from lgi.units import MM_PER_CM


def vertex_errors(recon: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(F, V) float64 distances in mm between reconstructed and true vertices (both cm)."""
    return np.linalg.norm(np.asarray(recon, np.float64) - np.asarray(truth, np.float64), axis=-1) * MM_PER_CM


def normal_angle_errors(recon: np.ndarray, truth: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(F, V) float64 angle in degrees between reconstructed and true vertex normals: how well the
    local shape (folds, wrinkles) is reproduced, independent of position."""
    out = np.empty(np.asarray(recon).shape[:2])
    for f, (r, t) in enumerate(zip(recon, truth, strict=True)):
        nr = vertex_normals(np.asarray(r, np.float64), triangles)
        nt = vertex_normals(np.asarray(t, np.float64), triangles)
        out[f] = np.degrees(np.arccos(np.clip(np.sum(nr * nt, axis=1), -1, 1)))
    return out


def jitter(vertices: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean squared second difference of vertex positions over time, mm^2 per frame^2.

    Parameters
    ----------
    vertices : (F, V, 3) cm, F >= 3
    mask : (V,) bool, optional
        Vertices to measure.
    """
    v = np.asarray(vertices, np.float64) * MM_PER_CM
    if mask is not None:
        v = v[:, mask]
    if len(v) < 3 or v.shape[1] == 0:
        return float("nan")  # undefined (the benchmark table shows NaN), without numpy's empty-mean warning
    acc = v[2:] - 2 * v[1:-1] + v[:-2]
    return float(np.mean(np.sum(acc**2, axis=-1)))
