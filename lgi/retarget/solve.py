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
  plus a second-difference penalty on each control's curve, solved jointly with the bounds (a sparse active-set
  solve; a long take in overlapping windows, :func:`smooth_shot`), then relinearised once. The frames' models
  wait in a scratch file (:class:`ShotFits`), so a take's memory is a window's. The penalty of control ``k`` is
  ``lambda_k = median_f p_fk / (2 sin(pi / T))^4`` for ``--smooth T`` frames (``p_fk`` the control's marginal
  precision, :func:`penalty_weights`): a zero-phase low-pass
  (a Whittaker smoother) that halves a curve's wiggles of period T frames. Zero phase means no lag: a step
  stays centred where it happens, only its corners are rounded over about T/2 frames; a held
  expression's frame-to-frame noise is averaged away.

**The jaw joint.** A rig generated from a jaw-rigged index (:attr:`BlendRig.jaw`) plays
``x(w, theta) = LBS_theta(x0 + sum_k w_k d_k + ...)``: its shapes are unskinned (the jaw closed) and the jaw
parameters ``theta = (open, yaw, roll, forward)`` (degrees, cm) skin them with the jaw rig's weights
(:class:`lgi.solve.jaw.JawRig`). The four parameters are unknowns of each frame beside the weights (unbounded,
started from the reconstruction's own jaw), in the same Gauss-Newton steps and the same temporal solve; with
``fix_jaw`` they are held at the given values.

**Jaw controls are driven by the joint.** The jaw controls' shapes (jaw_open, jaw_left, ...) hold only what the
rotation does not do, often almost nothing; left free, their weights would be set by whatever their small
shapes and their correctives (a smile with the jaw open) happen to fit, and would not say how far the jaw is
open (on the benchmark shot their correlation with the true activations was -0.19 to 0.10). As in a production
rig, where the jaw control turns the jaw bone and its corrective shapes with it, their weights are the jaw pose
split onto the controls' own poses (:func:`jaw_control_weights`, from each control's ``jaw`` metadata): bounded
least squares, held during the fit, so that jaw_open reads as the opening and its correctives fire with it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property
from itertools import product
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.optimize import lsq_linear
from scipy.sparse.linalg import splu

from lgi.dataset.shapes import ShapeDataset
from lgi.errors import InputError
from lgi.io.stored import ScratchArray
from lgi.solve.streamed import frame_blocks
from lgi.threads import one_blas_thread

log = logging.getLogger(__name__)

MOVED_CM = 0.005  # a vertex some rig shape moves by more than this (0.05 mm) belongs to the face region
# How the jaw parameters weigh against each other when a pose is split onto the jaw controls: a degree
# against a millimetre of slide (a vertex 6 cm from the hinge moves 1 mm per degree).
JAW_POSE_SCALE = np.array([1.0, 1.0, 1.0, 10.0])
DRIVEN_PASSES = 3  # refits of the shot with the jaw controls following the fitted jaw
DRIVEN_TOL = 1e-5  # ... until they move less than this (a weight)
# The temporal solve: a shot of up to SMOOTH_WHOLE frames in one sparse solve, a longer one in windows of
# SMOOTH_WINDOW frames with SMOOTH_MARGIN of context each side, fewer frames in all than the whole solve of the
# longest one-solve shot, so that a long take's peak stays below a short one's (a solve costs about 0.35 MB a
# frame for 61 unknowns: at windows of 1,152 frames a 9,000-frame ICT take peaked 1.11x above 1,000 frames).
# On a 1,000-frame ICT shot (61 curves, --smooth 4) windows of 100 frames gave the whole solve's curves within
# 5e-6 to 2e-5 of a weight at margins of 8 to 128 frames, no closer with more: the smoother's kernel is gone
# within 8 frames, and what is left is the active-set solve's own tolerance. The margins are solved twice, so
# they cost time: on the noisy 1,000-frame shot's fits, windows of 768 frames with margins of 64 took 1.2x the
# whole solve, with margins of 16 as long as it, and came within 2e-9 of its curves (960 and 16: 4e-7).
SMOOTH_WHOLE = 1024
SMOOTH_WINDOW = 960
SMOOTH_MARGIN = 16


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
    jaw : JawRig or None
        The jaw joint: the deltas are unskinned and a pose skins them with its jaw parameters (None: a rig
        without a jaw joint, its jaw baked into the jaw controls' shapes).
    jaw_poses : (K, 4) float64 or None
        Each control's own jaw pose (its metadata ``jaw``), which tells the jaw controls the joint drives
        (:attr:`jaw_controls`); None when a control has none (every weight is then free).
    """

    neutral: np.ndarray
    controls: list[str]
    deltas: np.ndarray
    combinations: list[tuple[int, ...]] = field(default_factory=list)
    corrective_names: list[str] = field(default_factory=list)
    jaw: object | None = None
    jaw_poses: np.ndarray | None = None

    @cached_property
    def jaw_controls(self) -> np.ndarray:
        """(J,) int: the controls the jaw joint drives, those whose own jaw pose (:attr:`jaw_poses`, (K, 4)) moves
        the face more than their shape does (and by more than ``MOVED_CM``): jaw_open, not a cheek puff whose jaw
        slides half a millimetre. Empty without a joint or without the controls' poses."""
        if self.jaw is None or self.jaw_poses is None:
            return np.zeros(0, np.int64)
        x0 = self.neutral
        out = []
        for k, pose in enumerate(self.jaw_poses):
            by_pose = float(np.linalg.norm(self.jaw.skin(x0, pose) - x0, axis=1).max())
            by_shape = float(np.linalg.norm(self.deltas[k], axis=1).max())
            if by_pose > max(by_shape, MOVED_CM):
                out.append(k)
        return np.asarray(out, np.int64)

    @property
    def n_jaw(self) -> int:
        """Jaw parameters per frame: 4 with a jaw joint, else 0."""
        return 0 if self.jaw is None else 4

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
        jaw = None
        if getattr(ds, "jaw_pivot", None) is not None:
            from lgi.solve.jaw import JawRig

            jaw = JawRig(np.asarray(ds.jaw_pivot, np.float64), np.asarray(ds.jaw_weights, np.float64))
        poses = [ds.shape_meta[i].extra.get("jaw") for i in ctrl]
        if jaw is not None and all(isinstance(p, list) and len(p) == 4 for p in poses):
            poses_arr = np.asarray(poses, np.float64)
        else:
            poses_arr = None  # without every control's pose nothing is driven: all weights are free
        return cls(np.asarray(ds.neutral, np.float64), controls, deltas, combos, [ds.names[i] for i in corr], jaw,
                   poses_arr)

    def all_weights(self, w: np.ndarray) -> np.ndarray:
        """(..., K + P) every shape's weight for control weights ``w`` (..., K): the correctives' products."""
        w = np.asarray(w, np.float64)
        prods = [np.prod(w[..., list(c)], axis=-1) for c in self.combinations]
        return np.concatenate([w, np.stack(prods, -1)], -1) if prods else w.copy()

    def evaluate(self, w: np.ndarray, jaw: np.ndarray | None = None) -> np.ndarray:
        """(V, 3) float64: the rig's playback at control weights ``w`` (K,) and, with a jaw joint, jaw parameters
        ``jaw`` (4,) (open, yaw, roll deg, forward cm; default closed)."""
        b = self.all_weights(w)
        x = self.neutral + np.tensordot(b, np.asarray(self.deltas, np.float64), axes=1)
        if self.jaw is None or jaw is None:
            return x
        return self.jaw.skin(x, np.asarray(jaw, np.float64))

    def face_region(self, moved_cm: float = MOVED_CM) -> np.ndarray:
        """(V,) bool: the vertices some shape moves by more than ``moved_cm``."""
        return np.linalg.norm(self.deltas, axis=2).max(axis=0) > moved_cm


def jaw_control_weights(rig: BlendRig, jaw: np.ndarray) -> np.ndarray:
    """(F, J) float64 in [0, 1]: the jaw controls' weights (:attr:`BlendRig.jaw_controls`) for jaw parameters
    ``jaw`` (F, 4): the weights whose sum of the controls' poses is nearest the jaw pose (bounded least squares,
    the slide weighed by :data:`JAW_POSE_SCALE`). Of two opposite controls (jaw_left and jaw_right: poses at more
    than 150 degrees) only one moves, the one that fits better: together they would cancel, and fitted poses are
    never exactly opposite, so both were driven to 1 on a centred jaw. A jaw half open gives jaw_open about 0.5,
    a jaw turned left jaw_left and not jaw_right."""

    jc = rig.jaw_controls
    jaw = np.asarray(jaw, np.float64).reshape(-1, 4)
    if jc.size == 0 or len(jaw) == 0:
        return np.zeros((len(jaw), jc.size))
    a = (rig.jaw_poses[jc] * JAW_POSE_SCALE).T  # (4, J)
    unit = a / np.maximum(np.linalg.norm(a, axis=0), 1e-12)
    cos = unit.T @ unit
    pairs = [(i, j) for i in range(jc.size) for j in range(i + 1, jc.size) if cos[i, j] < np.cos(np.radians(150))]
    # A ridge at the rounding level keeps each subproblem's solution unique.
    eps = 1e-6 * float(np.sqrt(np.sum(a**2)))
    choices = []
    for drop in product(*pairs):
        keep = np.setdiff1d(np.arange(jc.size), drop)
        choices.append((keep, np.vstack([a[:, keep], eps * np.eye(keep.size)])))
    out = np.zeros((len(jaw), jc.size))
    for f, th in enumerate(jaw):
        target = th * JAW_POSE_SCALE
        best = np.inf
        for keep, ak in choices:
            r = lsq_linear(ak, np.r_[target, np.zeros(keep.size)], bounds=(0.0, 1.0), method="bvls")
            if r.cost < best - 1e-12:
                best = r.cost
                out[f] = 0.0
                out[f, keep] = r.x
    return out


@dataclass
class FrameFit:
    """One frame's fit: its unknowns (N,) (the K control weights, then the rig's 4 jaw parameters when it has a
    jaw joint), the reweighted Gauss-Newton Hessian (N, N) and gradient (N,) of the robust cost at them (the
    frame's model in the temporal solve), and the iterations it took."""

    weights: np.ndarray
    hessian: np.ndarray
    gradient: np.ndarray
    iterations: int


class RigSolver:
    """Fits a :class:`BlendRig`'s control weights (and jaw parameters) to meshes over a fixed set of vertices.

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

    # Convergence of the jaw parameters: 1e-4 degree moves a vertex 10 cm from the hinge by 1.7e-5 cm, and 1e-5 cm
    # of slide as much; the weights' 1e-5 is about 1e-5 cm of motion too.
    JAW_TOL = np.array([1e-4, 1e-4, 1e-4, 1e-5])

    def __init__(self, rig: BlendRig, vertices: np.ndarray, robust: float = 3.0, floor_cm: float = 0.01) -> None:
        self.rig = rig
        self.vertices = np.asarray(vertices, np.int64)
        self.robust = float(robust)
        self.floor_cm = float(floor_cm)
        k = rig.n_controls
        self.n = k + rig.n_jaw
        d = np.asarray(rig.deltas, np.float64)[:, self.vertices]  # (K + P, S, 3)
        self.x0 = rig.neutral[self.vertices].reshape(-1)
        self.d = np.ascontiguousarray(d.reshape(len(d), -1).T)  # (3S, K + P)
        self.lo = np.r_[np.zeros(k), np.full(rig.n_jaw, -np.inf)]
        self.hi = np.r_[np.ones(k), np.full(rig.n_jaw, np.inf)]
        if rig.jaw is not None:
            w = np.asarray(rig.jaw.weights, np.float64)[self.vertices]
            self.jaw_w = w
            # Only the vertices the jaw moves change their rows with the jaw; the others' Gram is computed once.
            self.moving = np.flatnonzero(w > 0)
            still = np.flatnonzero(w <= 0)
            rows = (3 * still[:, None] + np.arange(3)).ravel()
            self.gram = self.d[rows].T @ self.d[rows]
            self.d_moving = self.d.reshape(-1, 3, len(d))[self.moving]  # (M, 3, K + P)
            self._moving_grams = self._skinned_grams(w[self.moving], self.d_moving)
        else:
            # The Gram matrix once: an iteration then costs two passes over the sample, and the robust reweighting
            # only subtracts the few down-weighted vertices' rows from it.
            self.gram = self.d.T @ self.d
        # A ridge at the rounding level keeps the QP's Cholesky defined for a control that moves no sampled vertex.
        self.ridge = 1e-12 * max(float(np.sum(self.d[:, :k] ** 2)), 1e-30)

    def _chain(self, w: np.ndarray) -> np.ndarray:
        """(K + P, K): derivative of every shape's weight in each control's (identity, then the products')."""
        k = len(w)
        a = np.zeros((k + len(self.rig.combinations), k))
        a[:k] = np.eye(k)
        for p, combo in enumerate(self.rig.combinations):
            for c in combo:
                a[k + p, c] = np.prod([w[o] for o in combo if o != c])
        return a

    def _split(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        k = self.rig.n_controls
        return z[:k], (z[k:] if self.rig.jaw is not None else None)

    def _unskinned(self, z: np.ndarray) -> np.ndarray:
        """(3S,): the sampled positions of unknowns ``z`` before the jaw's skinning."""
        return self.x0 + self.d @ self.rig.all_weights(self._split(z)[0])

    def _residual(self, z: np.ndarray, y: np.ndarray,
                  x: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (3S,) and each vertex's distance (S,) at unknowns ``z`` for positions ``y`` (3S,); ``x``:
        :meth:`_unskinned` of ``z`` when known."""
        theta = self._split(z)[1]
        x = self._unskinned(z) if x is None else x
        if theta is not None:
            x = self._skin(x.reshape(-1, 3), theta).reshape(-1)
        r = x - y
        return r, np.sqrt(np.sum(r.reshape(-1, 3) ** 2, axis=1))

    def _skin(self, x: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """(S, 3): the sampled unskinned positions ``x`` (S, 3) skinned with jaw parameters ``theta`` (4,)."""
        from lgi.solve.jaw import jaw_matrix

        m = jaw_matrix(theta, self.rig.jaw.pivot)
        w = self.jaw_w[:, None]
        return (1.0 - w) * x + w * (x @ m[:3, :3].T + m[:3, 3])

    def threshold(self, dist: np.ndarray) -> float:
        """The Huber threshold (cm) for vertex residual distances ``dist`` (S,); inf when not robust."""
        return max(self.robust * float(np.median(dist)), self.floor_cm) if self.robust > 0 else np.inf

    def cost(self, w: np.ndarray, y: np.ndarray, c: float) -> float:
        """The Huber cost of the sample at unknowns ``w`` with threshold ``c`` (cm): ``d^2 / 2`` within,
        ``c (d - c/2)`` beyond."""
        d = self._residual(w, y)[1]
        return float(np.sum(np.where(d <= c, 0.5 * d * d, c * (d - 0.5 * c))))

    @staticmethod
    def _skinned_grams(o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(3, 3, 3, B, B): ``sum_m c_m D_m[i]' D_m[j]`` over the jaw-moved vertices for the three weights ``c`` of
        a skinned row's Gram, ``(1 - o)^2``, ``o (1 - o)`` and ``o^2`` (jaw weights ``o`` (M,), shape rows ``d``
        (M, 3, B)).

        A moved vertex's rows in the shapes' weights are ``A D`` with ``A = (1 - o) I + o R``, so its Gram is
        ``D' ((1 - o)^2 I + o (1 - o) (R + R') + o^2 R'R) D``: with these sums, the jaw's rotation enters every
        Gram as nine numbers instead of a pass over the sample (the cost of a Gauss-Newton step was that pass)."""
        out = np.empty((3, 3, 3, d.shape[2], d.shape[2]))
        for k, c in enumerate(((1.0 - o) ** 2, o * (1.0 - o), o**2)):
            for i in range(3):
                ci = c[:, None] * d[:, i]
                for j in range(3):
                    out[k, i, j] = ci.T @ d[:, j]
        return out

    def _moving_model(self, z: np.ndarray, u: np.ndarray, omega: np.ndarray,
                      wr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The jaw-moved vertices' part of the reweighted Gauss-Newton model at unknowns ``z``: the Gram (B + 4,
        B + 4) and gradient (B + 4,) of their rows in the shapes' weights (B = K + P) and the jaw parameters, for
        their unskinned positions ``u`` (M, 3), robust weights ``omega`` (M,) and weighted residuals ``wr``
        (M, 3)."""
        from lgi.solve.jaw import jaw_matrix, jaw_matrix_derivatives

        theta = self._split(z)[1]
        pivot = self.rig.jaw.pivot
        r = jaw_matrix(theta, pivot)[:3, :3]
        dm = jaw_matrix_derivatives(theta, pivot)  # (4, 3, 4)
        o = self.jaw_w[self.moving]
        dmv = self.d_moving
        nb = dmv.shape[2]
        # (M, 3, 4): column p is o (dT_p/dp [u; 1]); one product for the four parameters' rotations
        jt = (u @ dm[:, :, :3].reshape(12, 3).T).reshape(-1, 4, 3).transpose(0, 2, 1) + dm[:, :, 3].T[None]
        jt *= o[:, None, None]
        full = np.empty((nb + 4, nb + 4))
        g = self._moving_grams
        coef = np.stack([np.eye(3), r + r.T, r.T @ r])  # A'A = (1-o)^2 I + o(1-o)(R + R') + o^2 R'R
        full[:nb, :nb] = np.tensordot(coef, g, axes=3)
        low = np.flatnonzero(omega < 1.0)
        if low.size:
            # Down-weighted vertices: their skinned rows, taken out by what their weight lacks.
            a = (1.0 - o[low])[:, None, None] * np.eye(3) + o[low][:, None, None] * r
            jb = np.matmul(a, dmv[low]).reshape(-1, nb)
            full[:nb, :nb] -= jb.T @ (np.repeat(1.0 - omega[low], 3)[:, None] * jb)

        def at(v: np.ndarray) -> np.ndarray:
            """A' v for each vertex's 3-vectors v (M, 3, P): (1 - o) v + o R' v."""
            rv = (np.ascontiguousarray(v.transpose(0, 2, 1)).reshape(-1, 3) @ r).reshape(len(v), -1, 3)
            return (1.0 - o)[:, None, None] * v + o[:, None, None] * rv.transpose(0, 2, 1)

        wjt = omega[:, None, None] * jt
        # The cross block and the gradient in one pass over the shapes' rows (the pass is the cost).
        both = dmv.reshape(-1, nb).T @ at(np.concatenate([wjt, wr[:, :, None]], axis=2)).reshape(-1, 5)
        full[:nb, nb:] = both[:, :4]
        full[nb:, :nb] = both[:, :4].T
        full[nb:, nb:] = wjt.reshape(-1, 4).T @ jt.reshape(-1, 4)
        grad = np.empty(nb + 4)
        grad[:nb] = both[:, 4]
        grad[nb:] = jt.reshape(-1, 4).T @ wr.reshape(-1)
        return full, grad

    def linearise(self, w: np.ndarray, y: np.ndarray,
                  c: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Reweighted Gauss-Newton model at unknowns ``w`` (N,) for sampled positions ``y`` (3S,): Hessian (N, N),
        gradient (N,) (of the Huber cost), the per-vertex robust weights (S,) and the threshold used (``c``, or
        the frame's)."""
        x = self._unskinned(w)
        r, dist = self._residual(w, y, x)
        c = self.threshold(dist) if c is None else c
        omega = np.ones_like(dist)
        big = np.flatnonzero(dist > c)
        omega[big] = c / dist[big]
        k = self.rig.n_controls
        a = self._chain(w[:k])
        wr = np.repeat(omega, 3) * r
        if self.rig.jaw is None:
            gram = self.gram
            if big.size:
                rows = (3 * big[:, None] + np.arange(3)).ravel()
                db = self.d[rows]
                gram = gram - db.T @ (np.repeat(1.0 - omega[big], 3)[:, None] * db)
            h = a.T @ gram @ a + self.ridge * np.eye(k)
            grad = a.T @ (self.d.T @ wr)
            return h, grad, omega, c
        wr3 = wr.reshape(-1, 3)
        full, g_full = self._moving_model(w, x.reshape(-1, 3)[self.moving], omega[self.moving], wr3[self.moving])
        nb = full.shape[0] - 4
        full[:nb, :nb] += self.gram
        still_big = big[self.jaw_w[big] <= 0]
        if still_big.size:
            rows = (3 * still_big[:, None] + np.arange(3)).ravel()
            db = self.d[rows]
            full[:nb, :nb] -= db.T @ (np.repeat(1.0 - omega[still_big], 3)[:, None] * db)
        # r's rows of the still vertices meet the plain shapes
        mov = np.zeros(len(dist), bool)
        mov[self.moving] = True
        g_full[:nb] += self.d.reshape(-1, 3, nb)[~mov].reshape(-1, nb).T @ wr3[~mov].ravel()
        t = np.zeros((nb + 4, k + 4))
        t[:nb, :k] = a
        t[nb:, k:] = np.eye(4)
        h = t.T @ full @ t + self.ridge * np.eye(k + 4)
        return h, t.T @ g_full, omega, c

    def fit_frame(self, y: np.ndarray, w0: np.ndarray | None = None, max_iter: int = 20,
                  tol: float = 1e-5, jaw: np.ndarray | None = None, fix_jaw: bool = False,
                  held: dict[int, float] | None = None) -> FrameFit:
        """Unknowns (N,) best explaining sampled positions ``y`` (S, 3) cm, from ``w0`` (N,): the control weights in
        [0, 1], then (with a jaw joint) the jaw parameters, started from ``jaw`` (4,) when given (else ``w0``'s, else
        closed) and held there with ``fix_jaw``. ``held``: controls held at given weights (the jaw controls the
        joint drives).

        Each iteration reweights (IRLS: the threshold from the current residuals), takes the bounded Newton
        step of that model, and halves it until the Huber cost with that threshold drops (the correctives and the
        jaw's rotation make the model nonlinear). Stops when the weights move less than ``tol`` and the jaw less
        than :attr:`JAW_TOL` (IRLS converges linearly once vertices are down-weighted: 1e-5 of a weight is under
        0.001 mm of motion, and took half the iterations of 1e-7 on a reconstructed shot).
        """
        from lgi.solve.qp import box_qp

        y = np.asarray(y, np.float64).reshape(-1)
        k, n = self.rig.n_controls, self.n
        z = np.zeros(n)
        if w0 is not None:
            z[:len(w0)] = np.asarray(w0, np.float64)[:n]
        z[:k] = np.clip(z[:k], 0.0, 1.0)
        lo, hi = self.lo.copy(), self.hi.copy()
        if self.rig.jaw is not None:
            if jaw is not None:
                z[k:] = np.asarray(jaw, np.float64)
            if fix_jaw:
                lo[k:] = hi[k:] = z[k:]
        elif fix_jaw or jaw is not None:
            raise InputError("jaw parameters given for a rig without a jaw joint")
        for c, v in (held or {}).items():
            z[c] = lo[c] = hi[c] = v
        tols = np.r_[np.full(k, tol), self.JAW_TOL[:n - k]]
        n_it = 0
        while n_it < max_iter:
            n_it += 1
            h, grad, _, c = self.linearise(z, y)
            step = np.zeros(n)
            box_qp(h, -grad, lo - z, hi - z, step)  # min 0.5 s'Hs + grad's with lo <= z + s <= hi
            c0 = self.cost(z, y, c)
            t = 1.0
            while True:
                zn = np.clip(z + t * step, lo, hi)
                if self.cost(zn, y, c) <= c0 * (1 + 1e-12) + 1e-30 or t < 1e-3:
                    break
                t *= 0.5
            moved = np.abs(zn - z)
            z = zn
            if np.all(moved < tols):
                break
        h, grad, _, _ = self.linearise(z, y)
        return FrameFit(z, h, grad, n_it)


def smooth_curves(fits: list[FrameFit], lam: np.ndarray, lo: float | np.ndarray = 0.0,
                  hi: float | np.ndarray = 1.0, max_iter: int = 50) -> np.ndarray:
    """Curves (F, K) minimising the frames' quadratic models plus a second-difference penalty, within bounds.

    Frame f's model about its fit ``w_f``: ``0.5 (x - w_f)' H_f (x - w_f) + g_f' (x - w_f)``; the penalty is
    ``0.5 sum_k lam_k sum_f (x_{f-1,k} - 2 x_{f,k} + x_{f+1,k})^2``. A sparse system of F*K unknowns, solved
    by an active-set loop (violated bounds fixed, fixed ones whose multiplier points inward released).

    Parameters
    ----------
    fits : F frame fits
    lam : (K,) float, the penalty of each control (in the Hessians' units)
    lo, hi : float or array broadcastable to (F, K)
        The bounds (per unknown and frame: the jaw's are infinite, or equal where it is held).
    """
    n_f, k = len(fits), len(lam)
    if n_f < 3 or not np.any(lam > 0):
        return np.stack([f.weights for f in fits])
    h = sp.block_diag([f.hessian for f in fits], format="csr")
    w = np.concatenate([f.weights for f in fits])
    rhs = h @ w - np.concatenate([f.gradient for f in fits])
    d2 = sp.diags([np.ones(n_f - 2), -2 * np.ones(n_f - 2), np.ones(n_f - 2)], [0, 1, 2], shape=(n_f - 2, n_f))
    a = (h + sp.kron(d2.T @ d2, sp.diags(np.asarray(lam, np.float64)))).tocsc()
    lo = np.broadcast_to(np.asarray(lo, np.float64), (n_f, k)).ravel()
    hi = np.broadcast_to(np.asarray(hi, np.float64), (n_f, k)).ravel()
    held = lo >= hi  # a held unknown (the given jaw) is never released
    x = np.clip(w, lo, hi)
    # Start from the frames' own active bounds (a control at rest stays at 0): few passes then change the set.
    fixed = (x <= lo) | (x >= hi)
    for _ in range(max_iter):
        free = ~fixed
        sub = a[free][:, free]
        x_new = x.copy()
        if free.any():
            # The system is symmetric positive definite and banded (frames in order, 2K wide): the natural order
            # without pivoting fills in least (a third of the time of the default's).
            lu = splu(sub.tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
            x_new[free] = lu.solve(rhs[free] - a[free][:, fixed] @ x[fixed])
        viol = free & ((x_new < lo - 1e-12) | (x_new > hi + 1e-12))
        x_new = np.clip(x_new, lo, hi)
        grad = a @ x_new - rhs  # the multiplier of a fixed variable: negative at lo (or positive at hi) releases it
        release = fixed & ~held & (((x_new <= lo) & (grad < -1e-10 * (1 + abs(rhs).max())))
                                   | ((x_new >= hi) & (grad > 1e-10 * (1 + abs(rhs).max()))))
        x = x_new
        if not viol.any() and not release.any():
            break
        fixed = (fixed | viol) & ~release
    return x.reshape(n_f, k)


def penalty_weights(fits: ShotFits, period_frames: float) -> np.ndarray:
    """(K,) second-difference penalties for a smoother that halves wiggles of ``period_frames`` frames (0: none):
    ``median_f p_fk / (2 sin(pi / T))^4``, the Whittaker smoother's half-power period for a curve whose frames
    weigh ``p_fk``.

    ``p_fk = 1 / (H_f^-1)[k, k]`` is the control's marginal precision: what the frame says about it once the
    other controls are free. Controls whose shapes overlap (the jaw's sideways moves and the opening) are
    less certain than their own ``H[k, k]`` says; penalised by ``H[k, k]`` they were over-smoothed (on the
    noisy benchmark shot the jaw_right curve's correlation with the truth fell from 0.97 to 0.93 at T = 4; by the
    marginal precision it stays at 0.97 and the held frames are as calm).
    """
    if period_frames <= 0 or not len(fits):
        return np.zeros(fits.n)
    t = max(float(period_frames), 2.0)
    return np.median(fits.precision(), axis=0) / (2 * np.sin(np.pi / t)) ** 4


def _precision(hessian: np.ndarray) -> np.ndarray:
    """(N,) the unknowns' marginal precisions ``1 / diag(H^-1)`` of a frame's Hessian (N, N)."""
    return 1.0 / np.diag(np.linalg.inv(hessian))


class ShotFits:
    """A shot's F per-frame fits (:class:`FrameFit`), kept so that a long take costs a window of them: each frame's
    model (Hessian and gradient), weights and marginal precisions (:func:`penalty_weights`), (N, N + 3) float64
    (31 kB a frame for 61 unknowns), in a scratch file (:class:`~lgi.io.stored.ScratchArray`), read back by frame
    range; only the iterations are in memory.

    Parameters
    ----------
    n_frames : int
    n : int, the unknowns per frame
    """

    def __init__(self, n_frames: int, n: int) -> None:
        self.n = n
        self.iterations = np.zeros(n_frames, np.int64)
        # Per frame: the Hessian's N columns, then the gradient, the weights and the precisions.
        self._rows = ScratchArray((n_frames, n, n + 3), np.float64)

    def __len__(self) -> int:
        return len(self.iterations)

    def put(self, f: int, fit: FrameFit) -> None:
        """Keep frame ``f``'s fit."""
        self.iterations[f] = fit.iterations
        self._rows.write(f, np.concatenate([fit.hessian, fit.gradient[:, None], fit.weights[:, None],
                                            _precision(fit.hessian)[:, None]], axis=1)[None])

    def block(self, lo: int, hi: int) -> list[FrameFit]:
        """The fits of frames ``lo .. hi``."""
        n = self.n
        return [FrameFit(m[:, n + 1].copy(), m[:, :n], m[:, n], int(self.iterations[f]))
                for f, m in zip(range(lo, hi), self._rows.rows(lo, hi), strict=True)]

    def weights(self, lo: int = 0, hi: int | None = None, columns: slice = slice(None)) -> np.ndarray:
        """(hi - lo, C) float64: frames lo .. hi's fitted unknowns (``columns`` of them)."""
        return self._column(self.n + 1, lo, len(self) if hi is None else hi, columns)

    def precision(self) -> np.ndarray:
        """(F, N) float64: every frame's marginal precisions."""
        return self._column(self.n + 2, 0, len(self), slice(None))

    def _column(self, c: int, lo: int, hi: int, columns: slice) -> np.ndarray:
        out = np.empty((hi - lo, len(range(self.n)[columns])))
        for a, b in frame_blocks(hi - lo):
            out[a:b] = self._rows.rows(lo + a, lo + b)[:, columns, c]
        return out


def smooth_shot(fits: ShotFits, lam: np.ndarray, bounds, window: int | None = None,
                margin: int | None = None) -> np.ndarray:
    """:func:`smooth_curves` of a whole shot, solved in windows of ``window`` frames with ``margin`` frames of
    context each side (a shot of at most :data:`SMOOTH_WHOLE` or ``window + 2 margin`` frames in one solve).

    The smoother couples a frame to its neighbours through a kernel that decays within a few periods ``T``
    (:func:`penalty_weights`), so a window's curves a margin away from its ends are the whole shot's to within
    the active-set solve's tolerance (:data:`SMOOTH_MARGIN`), and the solve's memory is a window's, not the
    shot's.

    Parameters
    ----------
    fits : ShotFits, F frames
    lam : (K,) float, the penalties
    window, margin : int, default :data:`SMOOTH_WINDOW`, :data:`SMOOTH_MARGIN`
    bounds : callable ``(lo, hi) -> (lower, upper)``, each (hi - lo, N): the bounds of frames lo .. hi

    Returns
    -------
    (F, N) float64
    """
    window = window or SMOOTH_WINDOW
    margin = SMOOTH_MARGIN if margin is None else margin
    n_f = len(fits)
    out = np.empty((n_f, fits.n))
    if n_f <= max(SMOOTH_WHOLE, window + 2 * margin):
        window = max(n_f, 1)
    for a in range(0, n_f, window):
        b = min(a + window, n_f)
        s, e = (a, b) if window >= n_f else (max(0, a - margin), min(n_f, b + margin))
        out[a:b] = smooth_curves(fits.block(s, e), lam, *bounds(s, e))[a - s:b - s]
    return out


@one_blas_thread  # small dense products: BLAS threads only fight a busy node's other work
def solve_shot(solver: RigSolver, meshes: np.ndarray, smooth_frames: float = 4.0, relinearise: int = 1,
               progress=None, jaw: np.ndarray | None = None,
               fix_jaw: bool = False) -> tuple[np.ndarray, ShotFits]:
    """Curves for a shot.

    Parameters
    ----------
    solver : RigSolver
    meshes : (F, V, 3) float, cm: the reconstruction (only ``solver.vertices`` are read)
    smooth_frames : float
        ``--smooth``: the period (frames) whose wiggles the temporal penalty halves; 0: per-frame fits only.
    relinearise : int
        Times the frames' models are rebuilt at the smoothed curves and the shot solved again.
    jaw : (F, 4) float, optional
        With a jaw joint: each frame's starting jaw parameters (the reconstruction's; default the previous
        frame's solution, closed for the first).
    fix_jaw : bool
        Hold the jaw at ``jaw`` instead of fitting it.

    The jaw controls (:attr:`BlendRig.jaw_controls`) are held at :func:`jaw_control_weights` of the jaw: of
    ``jaw`` (of a first pass with every weight free when it is not given), then, when the jaw is fitted, of the
    fitted jaw, refitting (warm) until those weights move less than ``tol`` (at most ``DRIVEN_PASSES`` times).

    Returns
    -------
    curves : (F, N) float64: the smoothed weights in [0, 1] (K), then the jaw parameters (4, with a jaw joint)
    fits : ShotFits, the per-frame fits (no temporal term: ``fits.weights()``)
    """
    k = solver.rig.n_controls
    if fix_jaw and jaw is None:
        raise InputError("fix_jaw needs the jaw parameters")
    jc = solver.rig.jaw_controls
    driven = None
    if jc.size and jaw is None:
        jaw = _per_frame(solver, meshes, None, False, None, None).weights(columns=slice(k, None))
    if jc.size:
        driven = jaw_control_weights(solver.rig, jaw)
    fits = _per_frame(solver, meshes, jaw, fix_jaw, driven, progress)
    for _ in range(DRIVEN_PASSES if jc.size and not fix_jaw else 0):
        # The fitted jaw moved from the start: the jaw controls follow it, and the frames are refitted from
        # their own fits (a pass or two of one or two iterations each).
        fitted = fits.weights(columns=slice(k, None))
        new = jaw_control_weights(solver.rig, fitted)
        if np.abs(new - driven).max(initial=0.0) < DRIVEN_TOL:
            break
        driven = new
        fits = _per_frame(solver, meshes, fitted, False, driven, None, fits)
    lam = penalty_weights(fits, smooth_frames)
    if not np.any(lam > 0):
        return fits.weights(), fits

    def bounds(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        lower = np.broadcast_to(solver.lo, (hi - lo, solver.n)).copy()
        upper = np.broadcast_to(solver.hi, (hi - lo, solver.n)).copy()
        if fix_jaw and solver.rig.jaw is not None:
            lower[:, k:] = upper[:, k:] = fits.weights(lo, hi, slice(k, None))
        if driven is not None:
            lower[:, jc] = upper[:, jc] = driven[lo:hi]
        return lower, upper

    curves = smooth_shot(fits, lam, bounds)
    for _ in range(relinearise):
        models = ShotFits(len(curves), solver.n)
        for f, c in enumerate(curves):
            h, g, _, _ = solver.linearise(c, np.asarray(meshes[f][solver.vertices], np.float64).reshape(-1))
            models.put(f, FrameFit(c, h, g, 0))
        curves = smooth_shot(models, lam, bounds)
    return curves, fits


def _per_frame(solver: RigSolver, meshes: np.ndarray, jaw: np.ndarray | None, fix_jaw: bool,
               driven: np.ndarray | None, progress, starts: ShotFits | None = None) -> ShotFits:
    """Each frame fitted on its own, warm-started from the previous one (or from its fit in ``starts``);
    ``driven`` (F, J): the jaw controls' weights, held."""
    jc = solver.rig.jaw_controls
    fits = ShotFits(len(meshes), solver.n)
    w = None
    frames = range(len(meshes))
    for f in (progress(frames) if progress else frames):
        fit = solver.fit_frame(np.asarray(meshes[f][solver.vertices], np.float64),
                               w if starts is None else starts.weights(f, f + 1)[0],
                               jaw=None if jaw is None else jaw[f], fix_jaw=fix_jaw,
                               held=None if driven is None else dict(zip(jc.tolist(), driven[f], strict=True)))
        fits.put(f, fit)
        w = fit.weights
    return fits


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


# The jaw joint's curves, in the order of lgi.solve.jaw.PARAM_NAMES (degrees; the slide in cm).
JAW_CURVES = ("jaw_open_deg", "jaw_yaw_deg", "jaw_roll_deg", "jaw_forward_cm")


def load_rig(rig_dir: str | Path):
    """The :class:`~lgi.retarget.solve.BlendRig` of a rig dataset, and the dataset."""
    if not Path(rig_dir).is_dir():
        raise InputError("rig dataset folder not found (make it with lgi rig-generate)", path=rig_dir)
    ds = ShapeDataset.load(rig_dir)
    return BlendRig.from_dataset(ds, path=Path(rig_dir) / "manifest.json"), ds


def playback(rig, curves: np.ndarray, vertices: np.ndarray | None = None, chunk: int = 64) -> np.ndarray:
    """(F, N, 3) float32 cm: the rig's playback of ``curves`` at ``vertices`` (default all).

    ``curves`` is (F, K) control weights or, for a rig with a jaw joint, (F, K + 4): the weights, then the jaw
    parameters (open, yaw, roll deg, forward cm) that skin the shapes (the closed jaw when they are left out).
    """
    from lgi.solve.jaw import jaw_matrix

    curves = np.asarray(curves, np.float64)
    k = rig.n_controls
    d = np.asarray(rig.deltas, np.float64)
    x0 = rig.neutral
    jw = None if rig.jaw is None else np.asarray(rig.jaw.weights, np.float64)
    if vertices is not None:
        d, x0 = d[:, vertices], x0[vertices]
        jw = None if jw is None else jw[vertices]
    flat = d.reshape(len(d), -1)
    out = np.empty((len(curves), *x0.shape), np.float32)
    skin = jw is not None and curves.shape[1] > k
    for s in range(0, len(curves), chunk):
        b = rig.all_weights(curves[s:s + chunk, :k])
        x = (x0.reshape(-1) + b @ flat).reshape(len(b), *x0.shape)
        if skin:
            for i, th in enumerate(curves[s:s + chunk, k:k + 4]):
                m = jaw_matrix(th, rig.jaw.pivot)
                x[i] = (1.0 - jw[:, None]) * x[i] + jw[:, None] * (x[i] @ m[:3, :3].T + m[:3, 3])
        out[s:s + chunk] = x
    return out
