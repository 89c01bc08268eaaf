"""Jaw articulation by linear blend skinning (paper section 6).

A :class:`JawRig` is a hinge on the neutral (a pivot) and per-vertex skinning weights. Jaw parameters
are ``(open, yaw, roll)`` in degrees and ``forward`` in cm: rotation ``Ry(yaw) Rz(roll) Rx(open)`` about
the pivot, then a translation along +z. A vertex with weight w moves by ``(1 - w) I + w T(theta)``.

Shapes are stored unskinned: ``s* = T(theta_k)^-1 (x0 + s_k) - x0`` per vertex, with ``theta_k`` fitted to
the vertices that move with the jaw; frames are unskinned with parameters fitted to the bundles that
move with the jaw, indexed, and skinned back.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from .atomic import atomic_file
from .errors import InputError

N_PARAMS = 4
PARAM_NAMES = ["open_deg", "yaw_deg", "roll_deg", "forward_cm"]


def jaw_matrix(params: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """(4, 4) rigid jaw motion for ``(open, yaw, roll, forward)`` about ``pivot`` (cm)."""
    op, yaw, roll, fwd = (float(v) for v in params)
    ca, sa = np.cos(np.deg2rad(op)), np.sin(np.deg2rad(op))
    rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    cy, sy = np.cos(np.deg2rad(yaw)), np.sin(np.deg2rad(yaw))
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    cz, sz = np.cos(np.deg2rad(roll)), np.sin(np.deg2rad(roll))
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    r = ry @ rz @ rx
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = pivot - r @ pivot + np.array([0.0, 0.0, fwd])
    return m


@dataclass
class JawRig:
    """Pivot (3,) cm and skinning weights (V,) in [0, 1] on the neutral."""

    pivot: np.ndarray
    weights: np.ndarray

    def blend_matrices(self, params: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """(N, 3, 4) per-point affine maps ``(1 - w) [I|0] + w T(params)`` for weights ``w`` (N,)."""
        w = self.weights if w is None else np.asarray(w, np.float64)
        t = jaw_matrix(params, self.pivot)[:3]
        ident = np.eye(4)[:3]
        return (1 - w)[:, None, None] * ident + w[:, None, None] * t

    def skin(self, x: np.ndarray, params: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Skinned positions (N, 3) of unskinned positions ``x`` (N, 3) (vertex weights by default)."""
        m = self.blend_matrices(params, w)
        return np.einsum("nij,nj->ni", m[:, :, :3], x) + m[:, :, 3]

    def unskin(self, x: np.ndarray, params: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Inverse of :meth:`skin` point by point (each blended map is an invertible affine map)."""
        m = self.blend_matrices(params, w)
        return np.linalg.solve(m[:, :, :3], (np.asarray(x, np.float64) - m[:, :, 3])[..., None])[..., 0]

    def fit(self, rest: np.ndarray, moved: np.ndarray, w: np.ndarray, init: np.ndarray | None = None) -> np.ndarray:
        """Jaw parameters (4,) best explaining ``moved`` (N, 3) as skinned ``rest`` (N, 3) with weights w.

        Solved by robust (soft-L1) nonlinear least squares, so points that also carry an expression
        (a pucker on the lower lip) weigh less.
        """
        rest = np.asarray(rest, np.float64)
        moved = np.asarray(moved, np.float64)

        def resid(th: np.ndarray) -> np.ndarray:
            return (self.skin(rest, th, w) - moved).ravel()

        x0 = np.zeros(N_PARAMS) if init is None else np.asarray(init, np.float64)
        return least_squares(resid, x0, loss="soft_l1", f_scale=0.05, x_scale=[5.0, 2.0, 2.0, 0.2]).x

    def save(self, path: str | os.PathLike[str]) -> None:
        with atomic_file(path, suffix=".npz") as tmp:
            np.savez(tmp, pivot=self.pivot, weights=self.weights)

    @classmethod
    def load(cls, path: str | os.PathLike[str], n_vertices: int | None = None) -> JawRig:
        path = Path(path)
        if not path.is_file():
            raise InputError("jaw rig file not found", path=path)
        with np.load(path) as z:
            if "pivot" not in z or "weights" not in z:
                raise InputError(f"jaw rig needs arrays 'pivot' and 'weights', has {list(z.keys())}", path=path)
            rig = cls(np.asarray(z["pivot"], np.float64).reshape(3), np.asarray(z["weights"], np.float64))
        if n_vertices is not None and rig.weights.shape != (n_vertices,):
            raise InputError(f"jaw rig has {rig.weights.shape[0]} weights, the mesh {n_vertices} vertices", path=path)
        return rig


def fit_shape_parameters(rig: JawRig, neutral: np.ndarray, deltas: np.ndarray, min_weight: float = 0.95) -> np.ndarray:
    """(S, 4) jaw parameters of every shape, fitted to the vertices moving fully with the jaw."""
    idx = np.flatnonzero(rig.weights >= min_weight)
    if idx.size < 3:
        raise InputError(f"the jaw rig has {idx.size} vertices with weight >= {min_weight}: too few to fit")
    rng = np.random.default_rng(0)
    idx = idx if idx.size <= 400 else np.sort(rng.choice(idx, 400, replace=False))
    rest = neutral[idx]
    w = rig.weights[idx]
    return np.stack([rig.fit(rest, rest + np.asarray(d[idx], np.float64), w) for d in deltas])


def unskin_deltas(rig: JawRig, neutral: np.ndarray, deltas: np.ndarray, params: np.ndarray) -> np.ndarray:
    """(S, V, 3) float32 unskinned displacements ``T(theta_k)^-1 (x0 + s_k) - x0``."""
    out = np.empty(np.shape(deltas), np.float32)
    for k, (d, th) in enumerate(zip(deltas, params, strict=True)):
        out[k] = rig.unskin(neutral + np.asarray(d, np.float64), th) - neutral
    return out


def smooth_parameters(params: np.ndarray, window: int) -> np.ndarray:
    """(F, 4) jaw parameters smoothed by a central moving average of ``window`` frames (odd; edges
    use the frames available)."""
    if window <= 1:
        return np.asarray(params, np.float64)
    p = np.asarray(params, np.float64)
    h = window // 2
    out = np.empty_like(p)
    for f in range(len(p)):
        out[f] = p[max(0, f - h): f + h + 1].mean(0)
    return out
