"""Jaw articulation by linear blend skinning (paper section 6).

A :class:`JawRig` is a hinge on the neutral (a pivot) and per-vertex skinning weights. Jaw parameters
are ``(open, yaw, roll)`` in degrees and ``forward`` in cm: rotation ``Ry(yaw) Rz(roll) Rx(open)`` about
the pivot, then a translation along +z. A vertex with weight w moves by ``(1 - w) I + w T(theta)``.

Shapes are stored unskinned: ``s* = T(theta_k)^-1 (x0 + s_k) - x0`` per vertex, with ``theta_k`` fitted to
the vertices that move with the jaw; frames are unskinned with parameters fitted to the bundles that
move with the jaw, indexed, and skinned back.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lgi.dataset.stabilise import rigid_fit
from lgi.errors import InputError
from lgi.io.atomic import atomic_file
from lgi.io.npz import load_npz, save_npz
from lgi.solve._jaw_kernels import jaw_map, jaw_map_derivatives, skin_points
from lgi.units import MM_PER_CM

N_PARAMS = 4
PARAM_NAMES = ["open_deg", "yaw_deg", "roll_deg", "forward_cm"]

# Thresholds of the hinge fit (cm and degrees; the rig's convention: x lateral, y up, z forward).
OPENING_MIN_DEG = 1.0  # a smaller rotation of the jaw vertices is a translation for the hinge fit
OPENING_MIN_AXIS_X = 0.9  # |x| of an opening's rotation axis: within ~26 degrees of the lateral axis
WARN_RESIDUAL_CM = 0.05  # hinge residual of an opening above which the fit is reported as far off
WARN_SLIDE_CM = 1.0  # a jaw slides a few mm along the articular eminence, not centimetres
WARN_PIVOT_DISTANCE_CM = 15.0  # the hinge (the condyles) sits ~5-12 cm from the lower teeth

log = logging.getLogger(__name__)


def jaw_matrix(params: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """(4, 4) rigid jaw motion for ``(open, yaw, roll, forward)`` (deg, deg, deg, cm) about ``pivot`` (3,) cm:
    ``R = R_yaw R_roll R_open`` about the pivot, then the slide along +z (:func:`lgi.solve._jaw_kernels.jaw_map`)."""
    m = np.eye(4)
    jaw_map(np.asarray(params, np.float64).reshape(N_PARAMS), np.asarray(pivot, np.float64).reshape(3), m[:3])
    return m


def jaw_matrix_derivatives(params: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """(4, 3, 4) derivatives of the top rows of :func:`jaw_matrix` in each parameter (per degree for the
    three angles, per cm for the slide)."""
    out = np.empty((N_PARAMS, 3, 4))
    jaw_map_derivatives(np.asarray(params, np.float64).reshape(N_PARAMS), np.asarray(pivot, np.float64).reshape(3),
                          out)
    return out


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
        w = self.weights if w is None else np.asarray(w, np.float64)
        x = np.ascontiguousarray(x, np.float64)
        if x.ndim != 2 or x.shape[1] != 3 or w.shape != (len(x),):
            raise ValueError(f"skin: positions {x.shape} and weights {w.shape} do not match (N, 3) and (N,)")
        out = np.empty_like(x)
        skin_points(x, np.ascontiguousarray(w), np.ascontiguousarray(jaw_matrix(params, self.pivot)[:3]), out)
        return out

    def unskin(self, x: np.ndarray, params: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Inverse of :meth:`skin` point by point (each blended map is an invertible affine map)."""
        m = self.blend_matrices(params, w)
        return np.linalg.solve(m[:, :, :3], (np.asarray(x, np.float64) - m[:, :, 3])[..., None])[..., 0]

    def fit(self, rest: np.ndarray, moved: np.ndarray, w: np.ndarray, init: np.ndarray | None = None) -> np.ndarray:
        """Jaw parameters (4,) best explaining ``moved`` (N, 3) as skinned ``rest`` (N, 3) with weights w.

        Solved by robust (soft-L1) nonlinear least squares, so points that also carry an expression
        (a pucker on the lower lip) weigh less.
        """
        from scipy.optimize import least_squares  # here: scipy.optimize costs every command 0.2 s to import

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

        z = load_npz(path, required=("pivot", "weights"))
        if z["pivot"].size != 3 or z["weights"].ndim != 1:
            raise InputError(f"jaw rig arrays have shapes {z['pivot'].shape} (pivot, 3 expected) and "
                             f"{z['weights'].shape} (weights, one per vertex)", path=path)
        rig = cls(np.asarray(z["pivot"], np.float64).reshape(3), np.asarray(z["weights"], np.float64))
        if not (np.all(np.isfinite(rig.pivot)) and np.all(np.isfinite(rig.weights))):
            raise InputError("jaw rig holds non-finite values", path=path)
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


def hinge_parameters(axis: np.ndarray, point: np.ndarray, angles_deg: np.ndarray, pivot: np.ndarray,
                     tol_cm: float = 1e-3) -> np.ndarray:
    """lgi's jaw parameters (the ``--jaw`` CSV's) of a jaw that turns about a known hinge.

    The hinge is the line through ``point`` along ``axis``; a frame turns the jaw by its angle about it
    (right-handed about ``axis``). lgi's parameters describe the same motion about the rig's ``pivot``:
    ``R = Ry(yaw) Rz(roll) Rx(open)``, then a slide ``forward`` along +z, so the rotation is the hinge's and the
    slide takes up where the hinge crosses the rig's pivot. ``lgi rig`` puts the pivot on the hinge it fits, in
    the jaw's mid-plane, so that a hinge a hair off the x axis gives a tiny yaw and roll and no slide.

    Parameters
    ----------
    axis : (3,) float, the hinge's direction in the index's frame (normalised here)
    point : (3,) float, cm: any point of the hinge
    angles_deg : (F,) float, degrees
    pivot : (3,) float, cm: the rig's pivot (``jaw_rig.npz`` ``pivot``, printed by ``lgi rig``)
    tol_cm : float
        The motion must be a rotation about ``pivot`` and a slide along z to this; a hinge that passes elsewhere
        would move the pivot across, which the rig cannot.

    Returns
    -------
    (F, 4) float64: open, yaw, roll (degrees), forward (cm)
    """
    from scipy.spatial.transform import Rotation

    a = np.asarray(axis, np.float64).reshape(3)
    a = a / np.linalg.norm(a)
    angles = np.atleast_1d(np.asarray(angles_deg, np.float64))
    rot = Rotation.from_rotvec(np.radians(angles)[:, None] * a).as_matrix()
    off = np.asarray(point, np.float64).reshape(3) - np.asarray(pivot, np.float64).reshape(3)
    slide = off - rot @ off  # (F, 3): the motion's translation about the pivot
    worst = float(np.abs(slide[:, :2]).max(initial=0.0))
    if worst > tol_cm:
        raise InputError(f"the hinge passes {np.linalg.norm(off - (off @ a) * a):.3g} cm from the rig's pivot: "
                         f"its motion moves the pivot by up to {worst:.3g} cm across z, which the rig's parameters "
                         "cannot give")
    return np.array([[*_euler(r), t[2]] for r, t in zip(rot, slide, strict=True)])


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


@dataclass
class RigFitReport:
    """How :func:`fit_rig` placed the hinge.

    Attributes
    ----------
    used : list of str
        The opening shapes the pivot was fitted from, in input order.
    skipped : dict of str to str
        The other shapes, each with why it was not taken as an opening.
    angles_deg : dict of str to float
        Each used opening's opening angle (degrees, the ``open`` parameter).
    slides : dict of str to float
        Each used opening's slide along +z (cm).
    residual_rms : dict of str to float
        Each used opening's RMS distance (cm) of the jaw vertices from the hinge model (its rotation
        about the fitted pivot, then its slide along z).
    pivot : (3,) float64, cm
    centroid : (3,) float64, cm
        The jaw vertices' centroid on the neutral.
    widest : str
        The opening whose displacements gave the skinning weights.
    joint_slides : bool
        Whether the slides were solved jointly with the pivot (openings of different sizes about one
        axis) rather than the pivot taken as the rotations' fixed point.
    warnings : list of str
        What looked far off (also logged as warnings).
    """

    used: list[str]
    skipped: dict[str, str]
    angles_deg: dict[str, float]
    slides: dict[str, float]
    residual_rms: dict[str, float]
    pivot: np.ndarray
    centroid: np.ndarray
    widest: str
    joint_slides: bool
    warnings: list[str] = field(default_factory=list)


def _axis_angle(r: np.ndarray) -> tuple[np.ndarray, float]:
    """Unit axis (3,) and angle (degrees, in [0, 180]) of a rotation matrix (3, 3)."""
    angle = float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))
    ax = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    n = np.linalg.norm(ax)
    if n < 1e-9 and angle > 90:
        # At 180 degrees the antisymmetric part vanishes; the axis is R's eigenvector of eigenvalue 1.
        vals, vecs = np.linalg.eigh((r + r.T) / 2)
        return vecs[:, int(np.argmax(vals))], angle
    return (ax / n if n > 0 else np.zeros(3)), angle


def _opening_or_reason(r: np.ndarray, t_mean: np.ndarray) -> str | None:
    """None when a shape's jaw motion is an opening, else why not (for the report).

    ``r`` (3, 3) is the rigid rotation of the jaw vertices, ``t_mean`` (3,) cm their mean displacement.
    """
    axis, angle = _axis_angle(r)
    if angle <= OPENING_MIN_DEG:
        return (f"rotates the jaw vertices by {angle:.2f} deg (<= {OPENING_MIN_DEG:g}): mostly a translation "
                f"of {np.linalg.norm(t_mean) * MM_PER_CM:.1f} mm, no hinge in it")
    if abs(axis[0]) <= OPENING_MIN_AXIS_X:
        ax = ", ".join(f"{v:.2f}" for v in axis)
        return (f"rotates {angle:.1f} deg about axis ({ax}), not the lateral x axis (|x| {abs(axis[0]):.2f} <= "
                f"{OPENING_MIN_AXIS_X:g}): a sideways or twisting motion, not an opening")
    return None


#: Smallest singular value (cm of opening motion per cm of pivot or slide) of a direction the openings observe
#: (:func:`_solve_pivot`).
PIVOT_OBSERVABLE = 1e-3


def _solve_pivot(rotations: list[np.ndarray], translations: list[np.ndarray], centroid: np.ndarray,
                 joint: bool) -> np.ndarray:
    """Hinge (3,) cm from openings ``x' = R_k x + t_k``: least squares of ``(I - R_k) p + f_k z = t_k``.

    With ``joint`` every opening's slide ``f_k`` is an unknown too (separable from the pivot only with
    openings of different sizes about one axis); otherwise the pivot is the rotations' fixed point. The
    component along the hinge axis is not observable from rotations about it: solving for the offset
    from the jaw vertices' centroid with the minimum-norm solution puts the pivot in their mid-plane.

    Openings about axes a hair apart (any real hinge, or a hair of noise on the shapes) make that component
    barely observable instead of not at all: an exact least-squares solution then slides the pivot metres
    along the axis to explain micrometres (ICT with 0.1 um of noise on its openings: 23 cm; 1 um: 1 m). So
    directions whose singular value is below :data:`PIVOT_OBSERVABLE` (1 cm of pivot moving the openings by
    under 10 um) are taken as unobservable, like the exact axis.
    """
    n = len(rotations)
    a = np.zeros((3 * n, 3 + n))
    b = np.empty(3 * n)
    for k, (r, t) in enumerate(zip(rotations, translations, strict=True)):
        a[3 * k:3 * k + 3, :3] = np.eye(3) - r
        a[3 * k + 2, 3 + k] = 1.0
        b[3 * k:3 * k + 3] = t - (np.eye(3) - r) @ centroid
    cols = a if joint else a[:, :3]
    u, sv, vt = np.linalg.svd(cols, full_matrices=False)
    keep = sv > PIVOT_OBSERVABLE
    return centroid + (vt[keep].T @ ((u[:, keep].T @ b) / sv[keep]))[:3]


def _hinge_rms(rest: np.ndarray, moved: np.ndarray, params: np.ndarray, pivot: np.ndarray) -> float:
    """RMS distance (cm) of ``moved`` (N, 3) from ``rest`` (N, 3) moved rigidly by ``jaw_matrix(params, pivot)``."""
    m = jaw_matrix(params, pivot)
    return float(np.sqrt(np.mean(np.sum((rest @ m[:3, :3].T + m[:3, 3] - moved) ** 2, axis=1))))


def _fit_warnings(report: RigFitReport) -> list[str]:
    """What makes the fitted hinge implausible, one sentence each (mm in the text, cm in the report)."""
    out = []
    for name, rms in report.residual_rms.items():
        if rms > WARN_RESIDUAL_CM:
            out.append(f"{name}: the jaw vertices are {rms * MM_PER_CM:.2f} mm RMS from the hinge model (> "
                       f"{WARN_RESIDUAL_CM * MM_PER_CM:g} mm): they do not move as a rotation about the fitted "
                       f"pivot plus a slide; check the jaw vertices and the opening shapes")
    for name, f in report.slides.items():
        if abs(f) > WARN_SLIDE_CM:
            out.append(f"{name}: the hinge needs a slide of {f * MM_PER_CM:.1f} mm along z "
                       f"(> {WARN_SLIDE_CM * MM_PER_CM:g} mm): the pivot is probably misplaced")
    off = report.pivot - report.centroid
    dist = float(np.linalg.norm(off))
    where = []
    if dist > WARN_PIVOT_DISTANCE_CM:
        where.append(f"{dist * MM_PER_CM:.0f} mm from the jaw vertices' centroid "
                     f"(> {WARN_PIVOT_DISTANCE_CM * MM_PER_CM:g} mm)")
    if off[2] > 0:
        where.append(f"{off[2] * MM_PER_CM:.0f} mm in front of the jaw vertices (a hinge is behind them)")
    if off[1] < 0:
        where.append(f"{-off[1] * MM_PER_CM:.0f} mm below the jaw vertices (a hinge is above them)")
    if where:
        p = ", ".join(f"{v:.2f}" for v in report.pivot)
        out.append(f"the pivot ({p}) cm is " + " and ".join(where) + ": implausible for a jaw hinge")
    return out


def fit_rig(neutral: np.ndarray, deltas: np.ndarray, jaw_vertices: np.ndarray, triangles: np.ndarray,
            smoothing: int = 10, names: list[str] | None = None) -> tuple[JawRig, np.ndarray]:
    """Fit a jaw rig from shapes in which a set of vertices moves rigidly with the jaw.

    The hinge is fitted from the *opening* shapes only: those whose jaw vertices mainly rotate about an
    axis close to the mesh's lateral x axis (by more than ``OPENING_MIN_DEG``, axis ``|x| >
    OPENING_MIN_AXIS_X``). Sideways and forward shapes (ICT's jawLeft/jawRight/jawForward are linear
    approximations, mostly translations) would pull the pivot far off: with them, two openings put it
    11 cm from the hinge with a 4.9 cm slide.

    Parameters
    ----------
    neutral : (V, 3) float, cm
    deltas : (S, V, 3) float, cm
        The jaw shapes (e.g. ICT's jawOpen, jawLeft, jawRight, jawForward).
    jaw_vertices : (K,) int
        Vertices that move rigidly with the jaw (ICT: the lower teeth, 19247-21450).
    triangles : (T, 3) int
        For smoothing the weights over the mesh.
    smoothing : int
        Averaging passes of the weights over mesh neighbours (the jaw vertices stay at 1).
    names : list of S str, optional
        Shape names for the report and messages (default ``shape 0``, ``shape 1``, ...).

    Returns
    -------
    rig : JawRig
        Pivot: the hinge, solved by least squares from the openings jointly with each opening's forward
        slide (``(I - R_k) p + f_k z = t_k``) when openings of different sizes make that well posed, as a
        pure rotation's fixed point otherwise; along the hinge axis it is the jaw vertices' mid-plane.
        Weights: how much of each vertex's displacement in the widest opening follows the jaw's motion, in
        [0, 1], smoothed. ``rig.fit_report`` is the :class:`RigFitReport` of the fit.
    params : (S, 4)
        Every shape's jaw parameters (Euler angles of its rotation, degrees; forward = the translation
        left along z about the pivot, cm), openings or not.

    Raises
    ------
    InputError
        When no shape is an opening (the hinge cannot be placed).

    Notes
    -----
    Logs a warning (``logging.getLogger("lgi.solve.jaw")``) when the fit looks far off: an opening more than
    ``WARN_RESIDUAL_CM`` RMS from the hinge model, a slide over ``WARN_SLIDE_CM``, or a pivot more than
    ``WARN_PIVOT_DISTANCE_CM`` from the jaw vertices' centroid or not behind and above them.
    """
    x0 = np.asarray(neutral, np.float64)
    jv = np.asarray(jaw_vertices)
    names = [f"shape {k}" for k in range(len(deltas))] if names is None else [str(n) for n in names]
    if len(names) != len(deltas):
        raise ValueError(f"{len(names)} names for {len(deltas)} shapes")
    rest = x0[jv]
    moved = [rest + np.asarray(d, np.float64)[jv] for d in deltas]
    fits = [rigid_fit(rest, m) for m in moved]
    rot = [f.rotation for f in fits]
    angles = np.array([_axis_angle(r)[1] for r in rot])
    skipped: dict[str, str] = {}
    use = []
    for k, (r, m) in enumerate(zip(rot, moved, strict=True)):
        reason = _opening_or_reason(r, (m - rest).mean(0))
        if reason is None:
            use.append(k)
        else:
            skipped[names[k]] = reason
    if not use:
        why = "; ".join(f"{n}: {r}" for n, r in skipped.items()) or "no shapes given"
        plural = "" if len(deltas) == 1 else "s"
        raise InputError(f"no jaw opening among the {len(deltas)} jaw shape{plural} (an opening rotates the jaw "
                         f"vertices by more than {OPENING_MIN_DEG:g} deg about an axis with |x| > "
                         f"{OPENING_MIN_AXIS_X:g}): cannot place the hinge ({why})")
    centroid = rest.mean(0)
    joint = _two_sizes_about_one_axis([rot[k] for k in use], angles[use])
    pivot = _solve_pivot([rot[k] for k in use], [fits[k].translation for k in use], centroid, joint)
    params = np.zeros((len(deltas), 4))
    for k, f in enumerate(fits):
        op, yaw, roll = _euler(f.rotation)
        left = f.translation - (pivot - f.rotation @ pivot)
        params[k] = [op, yaw, roll, left[2]]
    widest = use[int(np.argmax(angles[use]))]
    report = RigFitReport(
        used=[names[k] for k in use], skipped=skipped,
        angles_deg={names[k]: float(params[k, 0]) for k in use},
        slides={names[k]: float(params[k, 3]) for k in use},
        residual_rms={names[k]: _hinge_rms(rest, moved[k], params[k], pivot) for k in use},
        pivot=pivot.copy(), centroid=centroid, widest=names[widest], joint_slides=bool(joint))
    report.warnings = _fit_warnings(report)
    for msg in report.warnings:
        log.warning("jaw rig: %s", msg)
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
    # An attribute, not a third return value, so that existing ``rig, params = fit_rig(...)`` callers hold.
    rig.fit_report = report  # type: ignore[attr-defined]
    return rig, params
