"""The head pose solved with the face: per frame, the rigid head pose, the jaw and the shape weights together.

The stable-marker stabilisation (:mod:`lgi.capture.headstab`) assumes that some markers move rigidly with the
skull. None does exactly: a smile lifts the under-eye markers and the fit takes the lift for head motion. The
actor's dataset says where every marker is in every expression, so the pose need not assume any marker rigid:
per frame, the head-frame bundles ``x_h = R^T (x_w - t)`` are modelled by the global fit's model (the jaw and the
bounded shape weights, :class:`~lgi.solve.globalfit.GlobalFit`), and ``R, t`` are chosen so that the model fits
them best.

The solve alternates a bounded fit of the face to the current head-frame bundles with a Gauss-Newton step of
the pose in which the face's free parameters (the jaw and the weights strictly inside their bounds) move too:
the step minimises ``|| r + J_pose d_pose - B d_face ||`` over both, so a pose change that an expression would
explain as well is not taken for head motion. Markers the model cannot explain (a mistracked dot; the residual
far above the frame's robust spread) are left out of the frame's fit. Each frame starts from the stable-marker
pose of that frame and the face of the previous one, and no pose is smoothed over time: a helmet that jolts is
followed within the frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lgi.units import MM_PER_CM

log = logging.getLogger(__name__)

#: Fewest seen markers for the joint fit of a frame (6 pose parameters, the jaw and the weights). Below this,
#: the frame keeps the stable-marker pose, and says so.
MIN_MARKERS = 12
#: Convergence: the pose step's rotation (rad) and translation (cm) below which a frame is done.
STEP_RAD = 1e-8
STEP_CM = 1e-7
MAX_ITERATIONS = 40
#: A marker is left out of its frame's fit when its residual exceeds this many robust spreads (1.4826 MAD) of the
#: frame's residuals, and this floor (mm): model error on the lips is a few tenths of a millimetre.
OUTLIER_SPREADS = 5.0
OUTLIER_FLOOR_MM = 0.5
#: How each frame's pose was found (the ``head_pose`` column of the tracks table).
JOINT, STABLE, NONE = "joint", "stable markers", "none"


@dataclass
class HeadPoses:
    """The joint fit's result for a shot.

    Attributes
    ----------
    R : (F, 3, 3) float64, t : (F, 3) float64, mm
        Head -> world per frame (NaN where no pose could be found).
    source : (F,) object
        :data:`JOINT`, :data:`STABLE` (too few markers or a failed fit: the stable-marker pose kept) or :data:`NONE`.
    rms_mm : (F,) float64
        RMS distance of the frame's inlier markers from the fitted face, mm.
    outliers : (F, M) bool
        Markers left out of their frame's fit.
    iterations : (F,) int
    """

    R: np.ndarray
    t: np.ndarray
    source: np.ndarray
    rms_mm: np.ndarray
    outliers: np.ndarray
    iterations: np.ndarray


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3) vectors to (N, 3, 3) cross-product matrices: ``_skew(a) @ b == a x b``."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1), np.stack([v[:, 2], z, -v[:, 0]], -1),
                     np.stack([-v[:, 1], v[:, 0], z], -1)], 1)


def _rotation(w: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation by the rotation vector ``w`` (rad)."""
    a = float(np.linalg.norm(w))
    if a < 1e-12:
        return np.eye(3) + _skew(w[None])[0]
    k = _skew((w / a)[None])[0]
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


class HeadPoseSolver:
    """Joint head pose and face per frame (see the module docstring).

    Parameters
    ----------
    table : (S + 1, M, 3) float, cm, head frame
        The markers on the neutral (row 0) and on every shape: an index's ``ptab`` (unskinned with a rig).
    rig : JawRig, optional, and bundle_weights : (M,) float
        The index's jaw rig and each marker's skinning weight.
    """

    def __init__(self, table: np.ndarray, rig=None, bundle_weights: np.ndarray | None = None) -> None:
        from lgi.solve.globalfit import GlobalFit

        self.fit = GlobalFit(table, rig, bundle_weights)
        self.n_markers = self.fit.n_markers

    @classmethod
    def from_index(cls, index) -> HeadPoseSolver:
        """The solver of an :class:`~lgi.index.build.LGIIndex`'s markers, shapes and jaw rig."""
        rig = index.jaw_rig()
        bw = None if rig is None else index.layout().evaluate(rig.weights[:, None])[:, 0]
        return cls(index.arrays["ptab"], rig, bw)

    # ------------------------------------------------------------------ the face's free directions
    def _face_columns(self, res, x_h: np.ndarray) -> np.ndarray:
        """(3M, n) columns of the face model's free parameters at the fit ``res``: the shapes whose weights
        are strictly inside [0, 1] and the jaw's four parameters (when estimated), cm per unit."""
        fit = self.fit
        free = np.flatnonzero((res.weights > 1e-9) & (res.weights < 1 - 1e-9))
        if fit.rig is None:
            cols = fit.basis[free].reshape(len(free), 3 * self.n_markers).T
        else:
            maps = fit._maps(res.jaw)
            cols = np.einsum("mij,kmj->mik", maps[:, :, :3], fit.basis[free]).reshape(-1, len(free))
        parts = [cols]
        if fit.rig is not None and fit.jaw_observable and res.jaw is not None:
            base = fit.predict(res.weights, res.jaw)
            h = np.array([1e-4, 1e-4, 1e-4, 1e-5])  # deg, deg, deg, cm: central differences would gain little
            jac = np.empty((3 * self.n_markers, 4))
            for k in range(4):
                th = res.jaw.copy()
                th[k] += h[k]
                jac[:, k] = ((fit.predict(res.weights, th) - base) / h[k]).ravel()
            parts.append(jac)
        return np.concatenate(parts, axis=1)

    # ------------------------------------------------------------------ one frame
    def solve_frame(self, x_w: np.ndarray, R0: np.ndarray, t0: np.ndarray, init=None,
                    info: np.ndarray | None = None):
        """Fit one frame.

        Parameters
        ----------
        x_w : (M, 3) float, mm, world frame (NaN rows: not seen)
        R0, t0 : (3, 3), (3,) mm: the starting pose, head -> world
        init : GlobalFitResult, optional: the previous frame's face

        Returns
        -------
        R, t (mm), the face fit (head frame), the RMS of the inliers (mm), the outlier mask (M,) and the
        iterations taken.
        """
        seen = np.all(np.isfinite(x_w), axis=1)
        x_cm = np.where(seen[:, None], x_w, 0.0) / MM_PER_CM
        R, t = np.array(R0, np.float64), np.asarray(t0, np.float64) / MM_PER_CM
        use = seen.copy()
        res = init
        it = 0
        while it < MAX_ITERATIONS:
            it += 1
            x_h = (x_cm - t) @ R
            res = self.fit.solve(np.where(use[:, None], x_h, np.nan), init=res)
            r = x_h - self.fit.predict(res.weights, res.jaw)  # cm
            d = np.linalg.norm(r, axis=1)
            spread = 1.4826 * np.median(d[use]) if use.any() else 0.0
            keep = seen & (d * MM_PER_CM <= max(OUTLIER_SPREADS * spread * MM_PER_CM, OUTLIER_FLOOR_MM))
            if keep.sum() >= MIN_MARKERS:
                use = keep
            # Pose perturbation in the head frame: x_h' = exp(-[w]) (x_h - u) ~ x_h + x_h x w - u.
            rows = np.repeat(use, 3)
            # r = x_h - model: d r / d w = [x_h]x, d r / d u = -I, d r / d face = -B.
            j_pose = np.concatenate([_skew(x_h).reshape(-1, 3), -np.tile(np.eye(3), (self.n_markers, 1))], axis=1)
            j_face = -self._face_columns(res, x_h)
            A = np.concatenate([j_pose, j_face], axis=1)
            b = -r.ravel()
            if info is not None:
                # Each marker's rows whitened by its triangulation's information, carried into the head frame.
                S = np.linalg.cholesky(np.einsum("ji,mjk,kl->mil", R, info, R)).transpose(0, 2, 1)
                A = np.einsum("mij,mjk->mik", S, A.reshape(self.n_markers, 3, -1)).reshape(A.shape)
                b = np.einsum("mij,mj->mi", S, b.reshape(-1, 3)).ravel()
            step = np.linalg.lstsq(A[rows], b[rows], rcond=1e-10)[0]
            w, u = step[:3], step[3:6]
            # x_w = R x_h + t; with x_h' = exp(-[w]) (x_h - u): R' = R exp([w]), t' = t + R u.
            t = t + R @ u
            R = R @ _rotation(w)
            if np.linalg.norm(w) < STEP_RAD and np.linalg.norm(u) < STEP_CM:
                break
        x_h = (x_cm - t) @ R
        res = self.fit.solve(np.where(use[:, None], x_h, np.nan), init=res)
        d = np.linalg.norm(x_h - self.fit.predict(res.weights, res.jaw), axis=1)
        rms = float(np.sqrt(np.mean(d[use] ** 2))) * MM_PER_CM
        return R, t * MM_PER_CM, res, rms, seen & ~use, it

    # ------------------------------------------------------------------ a shot
    def solve(self, X: np.ndarray, R0: np.ndarray, t0: np.ndarray, info: np.ndarray | None = None) -> HeadPoses:
        """Every frame of a shot.

        Parameters
        ----------
        X : (F, M, 3) float, mm, world frame, in the solver's marker order (NaN: not seen)
        R0, t0 : (F, 3, 3), (F, 3) mm: the stable-marker poses (:func:`lgi.capture.headstab.stabilise_bundles`),
            where each frame starts (NaN rows: none)
        info : (F, M, 3, 3) float, 1/mm^2, world frame, optional
            Each bundle's information (inverse covariance: :func:`triangulation_information`): a stereo pair
            places a dot several times less precisely along its viewing direction than across it, and the pose
            should trust each bundle where it is precise. Without it, every bundle counts the same in every
            direction.
        """
        F, M = X.shape[:2]
        if M != self.n_markers:
            raise ValueError(f"{M} markers given, the model has {self.n_markers}")
        R = np.full((F, 3, 3), np.nan)
        t = np.full((F, 3), np.nan)
        source = np.full(F, NONE, dtype=object)
        rms = np.full(F, np.nan)
        outliers = np.zeros((F, M), bool)
        iters = np.zeros(F, np.int64)
        prev = None
        for f in range(F):
            has_start = bool(np.all(np.isfinite(R0[f])) and np.all(np.isfinite(t0[f])))
            if has_start:
                R[f], t[f], source[f] = R0[f], t0[f], STABLE
            n_seen = int(np.all(np.isfinite(X[f]), axis=1).sum())
            if not has_start or n_seen < MIN_MARKERS:
                continue
            Rf, tf, res, r, out, it = self.solve_frame(X[f], R0[f], t0[f], prev, None if info is None else info[f])
            if not (np.all(np.isfinite(Rf)) and np.all(np.isfinite(tf))):
                continue
            R[f], t[f], source[f], rms[f], outliers[f], iters[f] = Rf, tf, JOINT, r, out, it
            prev = res
        n_stable, n_none = int((source == STABLE).sum()), int((source == NONE).sum())
        if n_stable or n_none:
            log.warning("head pose: %d of %d frames could not be solved with the face (fewer than %d markers seen, "
                        "or no starting pose)%s; %d kept the stable-marker pose and %d have none (head_pose in the "
                        "tracks table)", n_stable + n_none, F, MIN_MARKERS, "", n_stable, n_none)
        return HeadPoses(R, t, source, rms, outliers, iters)


def triangulation_information(X: np.ndarray, cameras, px: float = 1.0, floor: float = 1e-6) -> np.ndarray:
    """The information (inverse covariance) of triangulated points, from the cameras that see them.

    Each camera pins a point across its viewing ray to ``px`` pixels: ``(f / Z)^2 (I - d d^T) / px^2`` with
    ``f`` the focal length (px), ``Z`` the distance and ``d`` the unit ray; the pair's information is the sum.

    Parameters
    ----------
    X : (F, M, 3) float, mm, world frame (NaN: not seen)
    cameras : the rig's cameras (``K``, ``center``), world frame, mm

    Returns
    -------
    (F, M, 3, 3) float64, 1/mm^2 (the identity times ``floor`` added, so that it is invertible; NaN rows: the
    identity).
    """
    seen = np.all(np.isfinite(X), axis=-1)
    x = np.where(seen[..., None], X, 0.0)
    info = np.zeros((*X.shape, 3))
    eye = np.eye(3)
    for cam in cameras:
        v = x - cam.center
        z = np.linalg.norm(v, axis=-1, keepdims=True)
        d = v / np.maximum(z, 1e-9)
        f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        info += ((f / np.maximum(z, 1e-9)) ** 2 / px**2)[..., None] * (eye - d[..., :, None] * d[..., None, :])
    info += floor * eye
    info[~seen] = eye
    return info


def pose_error(R: np.ndarray, t: np.ndarray, R_true: np.ndarray, t_true: np.ndarray, centre_mm: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's head-pose error against a known pose.

    Parameters
    ----------
    R, R_true : (F, 3, 3); t, t_true : (F, 3) mm: head -> world
    centre_mm : (3,) head frame, mm: where the translation error is measured (the markers' centroid: the face)

    Returns
    -------
    deg : (F,) the angle of ``R^T R_true``; mm : (F,) how far ``centre_mm`` lands from where the true pose puts
    it (NaN where there is no pose).
    """
    rel = np.einsum("fji,fjk->fik", R, R_true)
    deg = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    mm = np.linalg.norm(np.einsum("fij,j->fi", R - R_true, np.asarray(centre_mm, float)) + t - t_true, axis=1)
    return deg, mm
