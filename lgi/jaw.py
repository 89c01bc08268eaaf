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
from .npz import save_npz

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
            save_npz(tmp, pivot=self.pivot, weights=self.weights)

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


def _euler(r: np.ndarray) -> tuple[float, float, float]:
    """(open, yaw, roll) degrees of ``r = Ry(yaw) Rz(roll) Rx(open)``."""
    roll = np.arcsin(np.clip(r[1, 0], -1, 1))
    yaw = np.arctan2(-r[2, 0], r[0, 0])
    op = np.arctan2(-r[1, 2], r[1, 1])
    return float(np.degrees(op)), float(np.degrees(yaw)), float(np.degrees(roll))


def _two_sizes_about_one_axis(rotations: list[np.ndarray], angles: np.ndarray) -> bool:
    """Whether two rotations share an axis (within ~8 degrees) but differ in angle by more than 10 %."""
    axes = []
    for r in rotations:
        ax = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
        axes.append(ax / max(np.linalg.norm(ax), 1e-12))
    for i in range(len(axes)):
        for j in range(i + 1, len(axes)):
            same_axis = abs(axes[i] @ axes[j]) > 0.99
            if same_axis and abs(angles[i] - angles[j]) > 0.1 * max(angles[i], angles[j]):
                return True
    return False


def fit_rig(neutral: np.ndarray, deltas: np.ndarray, jaw_vertices: np.ndarray, triangles: np.ndarray,
            smoothing: int = 10) -> tuple[JawRig, np.ndarray]:
    """Fit a jaw rig from shapes in which a set of vertices moves rigidly with the jaw.

    Parameters
    ----------
    neutral : (V, 3) cm
    deltas : (S, V, 3)
        The jaw shapes (e.g. ICT's jawOpen, jawLeft, jawRight, jawForward).
    jaw_vertices : (K,) int
        Vertices that move rigidly with the jaw (ICT: the lower teeth, 19247-21450).
    triangles : (T, 3) int
        For smoothing the weights over the mesh.
    smoothing : int
        Averaging passes of the weights over mesh neighbours (the jaw vertices stay at 1).

    Returns
    -------
    rig : JawRig
        Pivot: the hinge, solved by least squares jointly with each rotating shape's forward slide
        (``(I - R_k) p + f_k z = t_k``) when openings of different sizes make that well posed, as a pure
        rotation's fixed point otherwise. Weights: how much of each
        vertex's displacement in the widest-opening shape follows the jaw's motion, in [0, 1], smoothed.
    params : (S, 4)
        Each shape's jaw parameters (Euler angles of its rotation; forward = the translation left along z).
    """
    from .stabilize import rigid_fit

    x0 = np.asarray(neutral, np.float64)
    jv = np.asarray(jaw_vertices)
    fits = [rigid_fit(x0[jv], x0[jv] + np.asarray(d, np.float64)[jv]) for d in deltas]
    rot = [f.rotation for f in fits]
    angles = np.array([np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))) for r in rot])
    use = np.flatnonzero(angles > 1.0)
    if use.size == 0:
        raise InputError("no jaw shape rotates the jaw vertices by more than 1 degree: cannot place the hinge")
    # A rotation about p followed by a forward slide f along z: (I - R) p + f z = t. Solved jointly for
    # p and every rotating shape's f (openings of different sizes separate the slide from the pivot).
    # The slides are only separable from the pivot with several openings of different sizes; with
    # one (ICT has a single jawOpen) they trade off exactly, and a pure rotation is fitted instead.
    a = np.zeros((3 * len(use), 3 + len(use)))
    for r, k in enumerate(use):
        a[3 * r:3 * r + 3, :3] = np.eye(3) - rot[k]
        a[3 * r + 2, 3 + r] = 1.0
    b = np.concatenate([fits[k].translation for k in use])
    if _two_sizes_about_one_axis([rot[k] for k in use], angles[use]):
        pivot = np.linalg.lstsq(a, b, rcond=None)[0][:3]
    else:
        pivot = np.linalg.lstsq(a[:, :3], b, rcond=None)[0]
    params = np.zeros((len(deltas), 4))
    for k, f in enumerate(fits):
        op, yaw, roll = _euler(f.rotation)
        rest = f.translation - (pivot - f.rotation @ pivot)
        params[k] = [op, yaw, roll, rest[2]]
    widest = int(np.argmax(angles))
    rig = JawRig(pivot, np.zeros(len(x0)))
    move = rig.skin(x0, params[widest], np.ones(len(x0))) - x0
    d = np.asarray(deltas[widest], np.float64)
    norm2 = np.sum(move**2, axis=1)
    w = np.where(norm2 > 1e-8, np.sum(d * move, axis=1) / np.maximum(norm2, 1e-12), 0.0)
    w = np.clip(w, 0.0, 1.0)
    w[jv] = 1.0
    import scipy.sparse as sp

    t = np.asarray(triangles)
    n = len(x0)
    adj = sp.coo_matrix((np.ones(6 * len(t)), (t[:, [0, 1, 2, 1, 2, 0]].ravel(), t[:, [1, 2, 0, 0, 1, 2]].ravel())),
                        shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    deg = np.maximum(np.asarray(adj.sum(1)).ravel(), 1)
    for _ in range(smoothing):
        w = 0.5 * w + 0.5 * (adj @ w) / deg
        w[jv] = 1.0
    rig.weights = np.clip(w, 0.0, 1.0)
    return rig, params
