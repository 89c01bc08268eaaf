"""Rigid stabilisation of captured shapes: remove head motion, keep the expression.

A captured shape is ``y = R (x0 + d) + t``: the expression displacement ``d`` seen through a rigid
head motion ``(R, t)``. On vertices that move with the skull ``d`` is zero, so ``(R, t)`` is found by a
rigid (rotation and translation, no scale) Procrustes fit of those vertices of the neutral onto the
shape. The fit is weighted and made robust with iteratively reweighted least squares (Tukey's
biweight on the residuals, scale from their median absolute deviation), so that a few "rigid" vertices
that do move, or a wrong vertex set, do not bias it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lgi.errors import InputError


@dataclass
class RigidFit:
    """Result of :func:`rigid_fit`.

    Attributes
    ----------
    rotation : (3, 3) float64
    translation : (3,) float64
        ``dst ~= src @ rotation.T + translation``.
    weights : (N,) float64
        Final robust weight of each point (0 = rejected as outlier).
    rms : float
        Weighted RMS residual of the inliers, in input units.
    """

    rotation: np.ndarray
    translation: np.ndarray
    weights: np.ndarray
    rms: float

    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous transform mapping ``src`` to ``dst``."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rotation and translation with ``dst ~= src @ R.T + t``.

    Parameters
    ----------
    src, dst : (N, 3) float
    weights : (N,) float, optional
        Non-negative; at least three non-collinear points must have positive weight.

    Returns
    -------
    R : (3, 3) float64, a proper rotation (det +1)
    t : (3,) float64
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    wsum = w.sum()
    if wsum <= 0:
        raise InputError("all weights are zero")
    cs = (w[:, None] * src).sum(0) / wsum
    cd = (w[:, None] * dst).sum(0) / wsum
    h = ((src - cs) * w[:, None]).T @ (dst - cd)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cd - r @ cs


def rigid_fit(
    src: np.ndarray,
    dst: np.ndarray,
    weights: np.ndarray | None = None,
    robust: bool = True,
    iterations: int = 30,
    tukey_c: float = 4.685,
    min_scale: float = 1e-7,
) -> RigidFit:
    """Robust weighted rigid fit of ``src`` onto ``dst`` (no scale).

    Parameters
    ----------
    src, dst : (N, 3) float
        Corresponding points (e.g. rigid vertices of the neutral and of a shape), same units.
    weights : (N,) float, optional
        Prior confidence of each point.
    robust
        Reweight by Tukey's biweight of the residuals; points beyond ``tukey_c`` robust standard
        deviations get zero weight.
    iterations
        IRLS iterations at most (stops earlier when the weights settle).
    min_scale
        Floor of the robust residual scale, in input units, so exact data does not divide by zero.
    """
    prior = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    w = prior.copy()
    r, t = kabsch(src, dst, w)
    for _ in range(iterations if robust else 0):
        res = np.linalg.norm(src @ r.T + t - dst, axis=1)
        active = prior > 0
        scale = max(1.4826 * float(np.median(res[active])), min_scale)
        u = res / (tukey_c * scale)
        w_new = prior * np.where(u < 1, (1 - u**2) ** 2, 0.0)
        if w_new.sum() <= 0:
            break
        r, t = kabsch(src, dst, w_new)
        if np.allclose(w_new, w, atol=1e-9):
            w = w_new
            break
        w = w_new
    res = np.linalg.norm(src @ r.T + t - dst, axis=1)
    rms = float(np.sqrt((w * res**2).sum() / max(w.sum(), 1e-300)))
    return RigidFit(r, t, w, rms)


def find_rigid_vertices(
    neutral: np.ndarray,
    shapes: np.ndarray,
    fraction: float = 0.1,
    sample: int = 20000,
    seed: int = 0,
) -> np.ndarray:
    """Find the vertices that move most rigidly over a set of shapes.

    Each shape is fitted robustly to the neutral using all vertices (most of a head does not move
    in an expression, so the fit locks onto the skull), then each vertex is scored by its largest
    residual over the shapes; the ``fraction`` with the smallest score are returned.

    Parameters
    ----------
    neutral : (V, 3) float
    shapes : (S, V, 3) float
        Full positions of the shapes (not displacements), possibly with head motion.
    fraction
        Share of the vertices to return.
    sample
        The fits use at most this many randomly chosen vertices (speed); scores use all.

    Returns
    -------
    (K,) int64
        Vertex indices, ascending.
    """
    neutral = np.asarray(neutral, np.float64)
    rng = np.random.default_rng(seed)
    v = len(neutral)
    pick = rng.choice(v, size=min(sample, v), replace=False)
    score = np.zeros(v)
    for s in shapes:
        s = np.asarray(s, np.float64)
        fit = rigid_fit(neutral[pick], s[pick])
        res = np.linalg.norm(neutral @ fit.rotation.T + fit.translation - s, axis=1)
        np.maximum(score, res, out=score)
    k = max(3, int(round(fraction * v)))
    return np.sort(np.argsort(score, kind="stable")[:k])


def stabilise(
    neutral: np.ndarray,
    shapes: np.ndarray,
    rigid_vertices: np.ndarray,
    weights: np.ndarray | None = None,
    robust: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Remove each shape's rigid head motion.

    Parameters
    ----------
    neutral : (V, 3) float
    shapes : (S, V, 3) float
        Full captured positions.
    rigid_vertices : (K,) int
        Vertices that move with the skull.
    weights : (K,) float, optional
        Prior weight of each rigid vertex.

    Returns
    -------
    deltas : (S, V, 3) float32
        Stabilised displacements ``R^T (y - t) - x0``.
    transforms : (S, 4, 4) float64
        The removed motion of each shape (stabilised -> captured).
    rms : (S,) float64
        Robust RMS residual of each fit on the rigid vertices, in input units.
    """
    neutral = np.asarray(neutral, np.float64)
    idx = np.asarray(rigid_vertices, np.int64)
    deltas = np.empty((len(shapes), *neutral.shape), np.float32)
    transforms = np.empty((len(shapes), 4, 4))
    rms = np.empty(len(shapes))
    for k, s in enumerate(shapes):
        s = np.asarray(s, np.float64)
        fit = rigid_fit(neutral[idx], s[idx], weights=weights, robust=robust)
        # Inverse motion applied to rows: (y - t) R  ==  R^T (y - t) per point.
        deltas[k] = (s - fit.translation) @ fit.rotation - neutral
        transforms[k] = fit.matrix()
        rms[k] = fit.rms
    return deltas, transforms, rms


def random_rigid(rng: np.random.Generator, max_degrees: float, max_translation: float) -> np.ndarray:
    """(4, 4) random rigid motion: uniform axis, angle up to ``max_degrees``, translation up to
    ``max_translation`` (in a uniformly random direction)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ang = np.deg2rad(rng.uniform(0, max_degrees))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    r = np.eye(3) + np.sin(ang) * k + (1 - np.cos(ang)) * k @ k
    d = rng.normal(size=3)
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = d / np.linalg.norm(d) * rng.uniform(0, max_translation)
    return m
