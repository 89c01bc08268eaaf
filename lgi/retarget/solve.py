"""Solving a reconstructed shot onto an actor's blendshape rig: per-frame control weights, then cleaned over time.

The rig (``lgi rig-generate``'s dataset) plays ``x(w) = x0 + sum_k w_k d_k + sum_p (prod_{c in p} w_c) e_p``:
controls ``d_k`` with weights in [0, 1] and correctives ``e_p`` driven by the product of their controls'
weights. Fitting ``w`` to a reconstructed mesh is a small bounded nonlinear least-squares problem (13-60
controls against thousands of coordinates):

* **Per frame** (:meth:`RigSolver.fit_frame`): Gauss-Newton steps, each a box-constrained QP
  (:func:`lgi.solve.qp.box_qp`, so the weights stay in [0, 1] exactly), warm-started from the previous frame,
  on a subsample of the face region (the vertices the rig moves). Robust: the rows are reweighted with Huber
  weights on each vertex's residual distance (threshold ``robust`` times the frame's median), so a few
  bad vertices do not pull the weights.
* **Over time** (:func:`smooth_curves`): the frames' quadratic models (the Gauss-Newton Hessians at the fit)
  plus a second-difference penalty on each control's curve, solved jointly over the shot with the bounds
  (a sparse active-set solve), then relinearised once. The penalty of control ``k`` is
  ``lambda_k = median_f p_fk / (2 sin(pi / T))^4`` for ``--smooth T`` frames (``p_fk`` the control's marginal
  precision, :func:`penalty_weights`): a zero-phase low-pass
  (a Whittaker smoother) that halves a curve's wiggles of period T frames. Zero phase means no lag: a step
  stays centred where it happens, only its corners are rounded over about T/2 frames; a held
  expression's frame-to-frame noise is averaged away.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from lgi.errors import InputError

log = logging.getLogger(__name__)

MOVED_CM = 0.005  # a vertex some rig shape moves by more than this (0.05 mm) belongs to the face region


@dataclass
class BlendRig:
    """A blendshape rig with product-driven correctives.

    Attributes
    ----------
    neutral : (V, 3) float64, cm
    controls : list of str, K names
    deltas : (K + P, V, 3) float32, cm: the K controls' displacements, then the P correctives'
    combinations : P tuples of control indices (each corrective's weight is the product of theirs)
    corrective_names : list of str, P names (``a+b``)
    """

    neutral: np.ndarray
    controls: list[str]
    deltas: np.ndarray
    combinations: list[tuple[int, ...]] = field(default_factory=list)
    corrective_names: list[str] = field(default_factory=list)

    @property
    def n_controls(self) -> int:
        return len(self.controls)

    @property
    def names(self) -> list[str]:
        """Every shape's name, controls first (the order of :attr:`deltas` and of the USD blend shapes)."""
        return [*self.controls, *self.corrective_names]

    @classmethod
    def from_dataset(cls, ds, path=None) -> BlendRig:
        """The rig of a shape dataset whose shapes are tagged ``control`` or ``corrective`` (the corrective's
        metadata ``combination`` names its controls), as ``lgi rig-generate`` writes it."""
        tags = [set(m.tags) for m in ds.shape_meta]
        ctrl = [i for i, t in enumerate(tags) if "control" in t]
        corr = [i for i, t in enumerate(tags) if "corrective" in t]
        if not ctrl:
            raise InputError("the rig dataset has no shape tagged 'control' (make the rig with lgi rig-generate)",
                             path=path)
        other = [ds.names[i] for i, t in enumerate(tags) if not t & {"control", "corrective"}]
        if other:
            raise InputError(f"rig shapes {', '.join(map(repr, other[:5]))} are tagged neither control nor "
                             "corrective", path=path)
        controls = [ds.names[i] for i in ctrl]
        k = {c: j for j, c in enumerate(controls)}
        combos = []
        for i in corr:
            parts = ds.shape_meta[i].extra.get("combination")
            if not isinstance(parts, list) or len(parts) < 2 or any(p not in k for p in parts):
                raise InputError(f"corrective {ds.names[i]!r}: its metadata 'combination' ({parts!r}) does not name "
                                 "two or more of the rig's controls", path=path)
            combos.append(tuple(k[p] for p in parts))
        deltas = np.asarray(ds.deltas)[ctrl + corr].astype(np.float32)
        return cls(np.asarray(ds.neutral, np.float64), controls, deltas, combos, [ds.names[i] for i in corr])

    def all_weights(self, w: np.ndarray) -> np.ndarray:
        """(..., K + P) every shape's weight for control weights ``w`` (..., K): the correctives' products."""
        w = np.asarray(w, np.float64)
        prods = [np.prod(w[..., list(c)], axis=-1) for c in self.combinations]
        return np.concatenate([w, np.stack(prods, -1)], -1) if prods else w.copy()

    def evaluate(self, w: np.ndarray) -> np.ndarray:
        """(V, 3) float64: the rig's playback at control weights ``w`` (K,)."""
        b = self.all_weights(w)
        return self.neutral + np.tensordot(b, np.asarray(self.deltas, np.float64), axes=1)

    def face_region(self, moved_cm: float = MOVED_CM) -> np.ndarray:
        """(V,) bool: the vertices some shape moves by more than ``moved_cm``."""
        return np.linalg.norm(self.deltas, axis=2).max(axis=0) > moved_cm


@dataclass
class FrameFit:
    """One frame's fit: control weights (K,), the reweighted Gauss-Newton Hessian (K, K) and gradient (K,) of the
    robust cost at them (the frame's model in the temporal solve), and the iterations it took."""

    weights: np.ndarray
    hessian: np.ndarray
    gradient: np.ndarray
    iterations: int


class RigSolver:
    """Fits a :class:`BlendRig`'s control weights to meshes over a fixed set of vertices.

    Parameters
    ----------
    rig : BlendRig
    vertices : (S,) int
        The vertices fitted (e.g. a subsample of the face region).
    robust : float
        Huber threshold in multiples of the frame's median vertex residual (0: plain least squares).
    floor_cm : float
        The threshold never goes below this (cm): a well-fitted frame is not reweighted by its rounding.
    """

    def __init__(self, rig: BlendRig, vertices: np.ndarray, robust: float = 3.0, floor_cm: float = 0.01) -> None:
        self.rig = rig
        self.vertices = np.asarray(vertices, np.int64)
        self.robust = float(robust)
        self.floor_cm = float(floor_cm)
        k = rig.n_controls
        d = np.asarray(rig.deltas, np.float64)[:, self.vertices]  # (K + P, S, 3)
        self.x0 = rig.neutral[self.vertices].reshape(-1)
        self.d = np.ascontiguousarray(d.reshape(len(d), -1).T)  # (3S, K + P)
        # The Gram matrix once: an iteration then costs two passes over the sample, and the robust reweighting
        # only subtracts the few down-weighted vertices' rows from it.
        self.gram = self.d.T @ self.d
        self.lo = np.zeros(k)
        self.hi = np.ones(k)
        # A ridge at the rounding level keeps the QP's Cholesky defined for a control that moves no sampled vertex.
        self.ridge = 1e-12 * max(float(np.trace(self.gram[:k, :k])), 1e-30)

    def _chain(self, w: np.ndarray) -> np.ndarray:
        """(K + P, K): derivative of every shape's weight in each control's (identity, then the products')."""
        k = len(w)
        a = np.zeros((k + len(self.rig.combinations), k))
        a[:k] = np.eye(k)
        for p, combo in enumerate(self.rig.combinations):
            for c in combo:
                a[k + p, c] = np.prod([w[o] for o in combo if o != c])
        return a

    def _residual(self, w: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = self.x0 + self.d @ self.rig.all_weights(w) - y
        return r, np.sqrt(np.sum(r.reshape(-1, 3) ** 2, axis=1))

    def threshold(self, dist: np.ndarray) -> float:
        """The Huber threshold (cm) for vertex residual distances ``dist`` (S,); inf when not robust."""
        return max(self.robust * float(np.median(dist)), self.floor_cm) if self.robust > 0 else np.inf

    def cost(self, w: np.ndarray, y: np.ndarray, c: float) -> float:
        """The Huber cost of the sample at ``w`` with threshold ``c`` (cm): ``d^2 / 2`` within, ``c (d - c/2)``
        beyond."""
        d = self._residual(w, y)[1]
        return float(np.sum(np.where(d <= c, 0.5 * d * d, c * (d - 0.5 * c))))

    def linearise(self, w: np.ndarray, y: np.ndarray,
                  c: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Reweighted Gauss-Newton model at ``w`` for sampled positions ``y`` (3S,): Hessian (K, K), gradient (K,)
        (of the Huber cost), the per-vertex robust weights (S,) and the threshold used (``c``, or the frame's)."""
        r, dist = self._residual(w, y)
        c = self.threshold(dist) if c is None else c
        omega = np.ones_like(dist)
        gram = self.gram
        big = np.flatnonzero(dist > c)
        if big.size:
            omega[big] = c / dist[big]
            rows = (3 * big[:, None] + np.arange(3)).ravel()
            db = self.d[rows]
            gram = gram - db.T @ (np.repeat(1.0 - omega[big], 3)[:, None] * db)
        a = self._chain(w)
        h = a.T @ gram @ a + self.ridge * np.eye(len(w))
        grad = a.T @ (self.d.T @ (np.repeat(omega, 3) * r))
        return h, grad, omega, c

    def fit_frame(self, y: np.ndarray, w0: np.ndarray | None = None, max_iter: int = 20,
                  tol: float = 1e-5) -> FrameFit:
        """Control weights (K,) in [0, 1] best explaining sampled positions ``y`` (S, 3) cm, from ``w0``.

        Each iteration reweights (IRLS: the threshold from the current residuals), takes the bounded Newton
        step of that model, and halves it until the Huber cost with that threshold drops (the correctives make
        the model nonlinear). Stops when the weights move less than ``tol`` (IRLS converges linearly once
        vertices are down-weighted: 1e-5 of a weight is under 0.001 mm of motion, and took half the iterations
        of 1e-7 on a reconstructed shot).
        """
        from lgi.solve.qp import box_qp

        y = np.asarray(y, np.float64).reshape(-1)
        k = self.rig.n_controls
        w = np.zeros(k) if w0 is None else np.clip(np.asarray(w0, np.float64), 0.0, 1.0)
        n_it = 0
        while n_it < max_iter:
            n_it += 1
            h, grad, _, c = self.linearise(w, y)
            step = np.zeros(k)
            box_qp(h, -grad, self.lo - w, self.hi - w, step)  # min 0.5 s'Hs + grad's with 0 <= w + s <= 1
            c0 = self.cost(w, y, c)
            t = 1.0
            while True:
                wn = np.clip(w + t * step, 0.0, 1.0)
                if self.cost(wn, y, c) <= c0 * (1 + 1e-12) + 1e-30 or t < 1e-3:
                    break
                t *= 0.5
            moved = float(np.max(np.abs(wn - w)))
            w = wn
            if moved < tol:
                break
        h, grad, _, _ = self.linearise(w, y)
        return FrameFit(w, h, grad, n_it)


def smooth_curves(fits: list[FrameFit], lam: np.ndarray, lo: float = 0.0, hi: float = 1.0,
                  max_iter: int = 50) -> np.ndarray:
    """Curves (F, K) minimising the frames' quadratic models plus a second-difference penalty, within bounds.

    Frame f's model about its fit ``w_f``: ``0.5 (x - w_f)' H_f (x - w_f) + g_f' (x - w_f)``; the penalty is
    ``0.5 sum_k lam_k sum_f (x_{f-1,k} - 2 x_{f,k} + x_{f+1,k})^2``. A sparse system of F*K unknowns, solved
    by an active-set loop (violated bounds fixed, fixed ones whose multiplier points inward released).

    Parameters
    ----------
    fits : F frame fits
    lam : (K,) float, the penalty of each control (in the Hessians' units)
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    n_f, k = len(fits), len(lam)
    if n_f < 3 or not np.any(lam > 0):
        return np.stack([f.weights for f in fits])
    h = sp.block_diag([f.hessian for f in fits], format="csr")
    w = np.concatenate([f.weights for f in fits])
    rhs = h @ w - np.concatenate([f.gradient for f in fits])
    d2 = sp.diags([np.ones(n_f - 2), -2 * np.ones(n_f - 2), np.ones(n_f - 2)], [0, 1, 2], shape=(n_f - 2, n_f))
    a = (h + sp.kron(d2.T @ d2, sp.diags(np.asarray(lam, np.float64)))).tocsc()
    x = np.clip(w, lo, hi)
    # Start from the frames' own active bounds (a control at rest stays at 0): few passes then change the set.
    fixed = (x <= lo) | (x >= hi)
    for _ in range(max_iter):
        free = ~fixed
        sub = a[free][:, free]
        x_new = x.copy()
        x_new[free] = splu(sub.tocsc()).solve(rhs[free] - a[free][:, fixed] @ x[fixed])
        viol = free & ((x_new < lo - 1e-12) | (x_new > hi + 1e-12))
        x_new = np.clip(x_new, lo, hi)
        grad = a @ x_new - rhs  # the multiplier of a fixed variable: negative at lo (or positive at hi) releases it
        release = fixed & (((x_new <= lo) & (grad < -1e-10 * (1 + abs(rhs).max())))
                           | ((x_new >= hi) & (grad > 1e-10 * (1 + abs(rhs).max()))))
        x = x_new
        if not viol.any() and not release.any():
            break
        fixed = (fixed | viol) & ~release
    return x.reshape(n_f, k)


def penalty_weights(fits: list[FrameFit], period_frames: float) -> np.ndarray:
    """(K,) second-difference penalties for a smoother that halves wiggles of ``period_frames`` frames (0: none):
    ``median_f p_fk / (2 sin(pi / T))^4``, the Whittaker smoother's half-power period for a curve whose frames
    weigh ``p_fk``.

    ``p_fk = 1 / (H_f^-1)[k, k]`` is the control's marginal precision: what the frame says about it once the
    other controls are free. Controls whose shapes overlap (the jaw's sideways moves and the opening) are
    less certain than their own ``H[k, k]`` says; penalised by ``H[k, k]`` they were over-smoothed (on the
    noisy benchmark shot the jaw_right curve's correlation with the truth fell from 0.97 to 0.93 at T = 4; by the
    marginal precision it stays at 0.97 and the held frames are as calm).
    """
    k = len(fits[0].weights) if fits else 0
    if period_frames <= 0 or not fits:
        return np.zeros(k)
    t = max(float(period_frames), 2.0)
    prec = np.median(np.stack([1.0 / np.diag(np.linalg.inv(f.hessian)) for f in fits]), axis=0)
    return prec / (2 * np.sin(np.pi / t)) ** 4


def solve_shot(solver: RigSolver, meshes: np.ndarray, smooth_frames: float = 4.0, relinearise: int = 1,
               progress=None) -> tuple[np.ndarray, np.ndarray, list[FrameFit]]:
    """Curves for a shot.

    Parameters
    ----------
    solver : RigSolver
    meshes : (F, V, 3) float, cm: the reconstruction (only ``solver.vertices`` are read)
    smooth_frames : float
        ``--smooth``: the period (frames) whose wiggles the temporal penalty halves; 0: per-frame fits only.
    relinearise : int
        Times the frames' models are rebuilt at the smoothed curves and the shot solved again.

    Returns
    -------
    curves : (F, K) float64 in [0, 1], the smoothed weights
    raw : (F, K) float64, the per-frame fits (no temporal term)
    fits : the per-frame fits
    """
    fits: list[FrameFit] = []
    w = None
    frames = range(len(meshes))
    for f in (progress(frames) if progress else frames):
        fit = solver.fit_frame(np.asarray(meshes[f][solver.vertices], np.float64), w)
        fits.append(fit)
        w = fit.weights
    raw = np.stack([f.weights for f in fits]) if fits else np.zeros((0, solver.rig.n_controls))
    lam = penalty_weights(fits, smooth_frames)
    if not np.any(lam > 0):
        return raw.copy(), raw, fits
    curves = smooth_curves(fits, lam)
    for _ in range(relinearise):
        models = []
        for f, c in enumerate(curves):
            h, g, _, _ = solver.linearise(c, np.asarray(meshes[f][solver.vertices], np.float64).reshape(-1))
            models.append(FrameFit(c, h, g, 0))
        curves = smooth_curves(models, lam)
    return curves, raw, fits


def step_lag(curve: np.ndarray, step_frame: int, before: float, after: float) -> float:
    """Frames by which ``curve`` (F,) crosses halfway between ``before`` and ``after`` later than the step at
    ``step_frame`` (the first frame at the new value); negative when it crosses early."""
    mid = 0.5 * (before + after)
    s = np.sign(after - before)
    above = np.flatnonzero(s * (np.asarray(curve) - mid) >= 0)
    above = above[above >= max(step_frame - 20, 0)]
    if above.size == 0:
        return float("inf")
    i = int(above[0])
    if i == 0:
        return float(-step_frame)
    # linear interpolation between the two frames around the crossing; the true crossing is at step_frame - 0.5
    c0, c1 = curve[i - 1], curve[i]
    frac = (mid - c0) / (c1 - c0) if c1 != c0 else 1.0
    return float(i - 1 + frac - (step_frame - 0.5))
