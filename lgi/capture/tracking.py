"""Labelled dot tracks from stereo footage: labelling, tracking with anchor frames, triangulation.

The world frame is the rig's (camera 0 unless the rig says otherwise), in mm.

1. Labelling: the reference frame's dots are matched across the cameras along epipolar lines and
   triangulated; the neutral marker layout is fitted to them rigidly (trimmed ICP from several starting
   orientations, face towards the cameras); the fitted layout is projected into each camera and each
   projection takes the nearest free detection (one-to-one, gated). A label file can replace this.
2. Tracking: each marker's 3D position is predicted (previous position plus velocity; a marker not seen
   moves with its layout neighbours), projected into both cameras and matched to the detections
   one-to-one within a gate. Matches are checked: a pair whose triangulation reprojects badly
   (epipolar inconsistency) is dropped in both cameras, and so is a marker whose motion disagrees with
   its neighbours'. Unmatched markers are gaps, not guesses.
3. Anchor frames (drift control): frames whose image is close to the reference frame's are matched to
   the reference directly; the clips between anchors are tracked forward from one and backward from
   the next, and per frame and marker the observation closer to its prediction wins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from lgi.capture.camera import StereoRig
from lgi.capture.dots import Dots
from lgi.capture.settings import GATE_PX, PIXEL_NOISE_PX
from lgi.dataset.stabilise import kabsch, rigid_fit
from lgi.errors import InputError


@dataclass
class TrackOptions:
    """Tracking parameters (pixels unless stated)."""

    gate_px: float = GATE_PX
    anchor_gate_px: float = 14.0
    label_gate_px: float = 25.0
    epipolar_px: float = 2.5
    neighbour_mm: float = 4.0
    anchor_similarity: float = 0.985
    anchor_min_spacing: int = 5
    anchor_min_matched: float = 0.95
    anchor_max_median_px: float = 2.0
    neighbours: int = 6
    #: px per image coordinate, one standard deviation: :data:`PIXEL_NOISE_PX`
    pixel_noise_px: float = PIXEL_NOISE_PX


@dataclass
class Tracks:
    """Result of :meth:`Tracker.track`.

    Attributes
    ----------
    uv : (F, M, 2, 2) float64
        Pixel position of each marker in each camera (NaN where not seen).
    X : (F, M, 3) float64
        Triangulated positions, world frame (mm), NaN unless seen by both cameras.
    error : (F, M, 2) float64
        Reprojection error in each camera (px), NaN where not triangulated.
    source : (F, M, 2) int8
        0 not seen, 1 forward track, 2 backward track, 3 anchor or reference match.
    anchors : (A,) int64
        Anchor frames (the reference first).
    rejected : (F, M) int8
        1 epipolar inconsistency, 2 neighbour inconsistency (the observation was dropped).
    """

    uv: np.ndarray
    X: np.ndarray
    error: np.ndarray
    source: np.ndarray
    anchors: np.ndarray
    rejected: np.ndarray


def _assign(pred: np.ndarray, det: np.ndarray, gate: float, pred_area: np.ndarray | None = None,
            det_area: np.ndarray | None = None, max_area_ratio: float = 2.2, min_area_ratio: float = 1 / 3
            ) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching of predictions (M, 2) to detections (N, 2) within ``gate``.

    With areas (the marker's blob area in the reference frame, and each detection's), a detection whose
    area differs from the marker's by more than ``max_area_ratio`` cannot take it (an eye corner or a
    brow end is not the dot beside it); a dot may shrink more (occluded in part, foreshortened) down to
    ``min_area_ratio``.

    Returns the detection index per prediction (-1 if none) and the distance (inf if none).
    """
    m = len(pred)
    idx = np.full(m, -1)
    dist = np.full(m, np.inf)
    ok = np.all(np.isfinite(pred), axis=1)
    if not ok.any() or len(det) == 0:
        return idx, dist
    rows = np.flatnonzero(ok)
    tree = cKDTree(det)
    near = tree.query_ball_point(pred[rows], gate)
    cand = sorted({j for lst in near for j in lst})
    if not cand:
        return idx, dist
    cand = np.asarray(cand)
    d = np.linalg.norm(pred[rows, None, :] - det[None, cand, :], axis=2)
    big = 1e6
    allowed = d <= gate
    if pred_area is not None and det_area is not None:
        ratio = np.log(np.maximum(det_area[None, cand], 1) / np.maximum(pred_area[rows, None], 1))
        allowed &= ~((ratio > np.log(max_area_ratio)) | (ratio < np.log(min_area_ratio)))  # NaN (unknown) allows
    cost = np.where(allowed, d, big)
    r, c = linear_sum_assignment(cost)
    good = cost[r, c] < big
    idx[rows[r[good]]] = cand[c[good]]
    dist[rows[r[good]]] = d[r[good], c[good]]
    return idx, dist


def thumbnail(image: np.ndarray, size: tuple[int, int] = (80, 64)) -> np.ndarray:
    """A small, zero-mean, unit-norm version of an image, for appearance similarity (NCC)."""
    import cv2

    t = cv2.resize(image, size, interpolation=cv2.INTER_AREA).astype(np.float32).ravel()
    t -= t.mean()
    return t / max(float(np.linalg.norm(t)), 1e-6)


class Tracker:
    """Labels and tracks the dots of one shot.

    Parameters
    ----------
    rig : StereoRig (mm)
    layout_mm : (M, 3) neutral marker positions in the head frame, mm
    names : marker names
    """

    def __init__(self, rig: StereoRig, layout_mm: np.ndarray, names: list[str], options: TrackOptions | None = None):
        self.rig = rig
        self.layout = np.asarray(layout_mm, np.float64)
        self.names = list(names)
        self.o = options or TrackOptions()
        k = min(self.o.neighbours + 1, len(self.layout))
        self.nbrs = cKDTree(self.layout).query(self.layout, k)[1][:, 1:]
        self.ref_area = np.full((len(self.layout), 2), np.nan)  # blob area of each marker in the reference
        self.ref_fit: np.ndarray | None = None  # the layout fitted rigidly to the reference frame

    # ------------------------------------------------------------------ labelling
    def _stereo_points(self, d0: np.ndarray, d1: np.ndarray) -> np.ndarray:
        """Unlabelled stereo matches of two detection sets, triangulated: (K, 3) world mm."""
        x0 = self.rig.cameras[0].normalized(d0)
        x1 = self.rig.cameras[1].normalized(d1)
        n0, n1 = len(x0), len(x1)
        ii, jj = np.meshgrid(np.arange(n0), np.arange(n1), indexing="ij")
        epi = self.rig.epipolar_distance_normalized(x0[ii.ravel()], x1[jj.ravel()]).reshape(n0, n1)
        cost = np.where(epi < 3.0, epi, 1e6)
        r, c = linear_sum_assignment(cost)
        good = cost[r, c] < 1e6
        X, err = self.rig.triangulate(d0[r[good]], d1[c[good]])
        z = self.rig.cameras[0].to_camera(X)[:, 2]
        return X[(z > 30) & (z < 1000) & (err.max(axis=1) < 3.0)]

    def fit_layout(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Rigid (R, t, trimmed RMS mm) mapping the layout onto unlabelled 3D points (K, 3)."""

        tree = cKDTree(points)
        src = self.layout
        best = (np.eye(3), np.zeros(3), np.inf)
        face_to_cam = np.diag([1.0, -1.0, -1.0])  # head +z (out of the face) towards the cameras
        keep = max(int(0.7 * min(len(src), len(points))), 3)
        for ang in [(a, b, c) for a in (-30, 0, 30) for b in (-30, 0, 30) for c in (-30, 0, 30)]:
            R = Rotation.from_euler("xyz", ang, degrees=True).as_matrix() @ face_to_cam
            t = points.mean(0) - src.mean(0) @ R.T
            for _ in range(30):
                d, j = tree.query(src @ R.T + t)
                order = np.argsort(d)[:keep]
                R, t = kabsch(src[order], points[j[order]])
            d, _ = tree.query(src @ R.T + t)
            rms = float(np.sqrt(np.mean(np.sort(d)[:keep] ** 2)))
            if rms < best[2]:
                best = (R, t, rms)
        return best

    def label_reference(self, dots: tuple[Dots, Dots]) -> np.ndarray:
        """(M, 2, 2) labelled pixel positions of the reference frame (NaN where not found)."""
        pts = self._stereo_points(dots[0].xy, dots[1].xy)
        if len(pts) < 4:
            raise InputError(f"only {len(pts)} dots could be matched between the cameras in the reference frame")
        R, t, _ = self.fit_layout(pts)
        self.ref_fit = self.layout @ R.T + t
        uv = np.full((len(self.layout), 2, 2), np.nan)
        for _ in range(3):  # label, triangulate the labelled markers, refit, relabel
            X = self.layout @ R.T + t
            for c, cam in enumerate(self.rig.cameras):
                idx, _ = _assign(cam.project(X), dots[c].xy, self.o.label_gate_px)
                uv[:, c] = np.where(idx[:, None] >= 0, dots[c].xy[np.maximum(idx, 0)], np.nan)
                self.ref_area[:, c] = np.where(idx >= 0, dots[c].area[np.maximum(idx, 0)], np.nan)
            both = np.all(np.isfinite(uv[:, :, 0]), axis=1)
            Xt, err = self.rig.triangulate(uv[both, 0], uv[both, 1])
            ok = err.max(axis=1) < self.o.epipolar_px
            R, t = kabsch(self.layout[both][ok], Xt[ok])
            self.ref_fit = self.layout @ R.T + t
        return uv

    # ------------------------------------------------------------------ tracking
    def _neighbour_motion(self, moved: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """(M, 3) median motion of each marker's seen neighbours (zero if none)."""
        mask = seen[self.nbrs]
        nb = np.sort(np.where(mask[..., None], moved[self.nbrs], np.nan), axis=1)  # NaN sort last
        cnt = mask.sum(axis=1)
        lo = np.take_along_axis(nb, np.maximum((cnt - 1) // 2, 0)[:, None, None], axis=1)[:, 0]
        hi = np.take_along_axis(nb, (cnt // 2)[:, None, None].clip(max=nb.shape[1] - 1), axis=1)[:, 0]
        return np.where(cnt[:, None] > 0, 0.5 * (lo + hi), 0.0)

    def _complete(self, X: np.ndarray, ref_X: np.ndarray) -> np.ndarray:
        """Fill markers missing from ``X`` (M, 3) with the reference moved like their seen neighbours."""
        seen = np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(ref_X), axis=1)
        moved = np.where(seen[:, None], X - ref_X, 0.0)
        return np.where(np.isfinite(X), X, ref_X + self._neighbour_motion(moved, seen))

    def _observe(self, X_pred: np.ndarray, dots: tuple[Dots, Dots], gate: float):
        """Match predictions to detections in both cameras; check epipolar and neighbour consistency."""
        M = len(X_pred)
        uv = np.full((M, 2, 2), np.nan)
        cost = np.full((M, 2), np.inf)
        for c, cam in enumerate(self.rig.cameras):
            idx, dist = _assign(cam.project(X_pred), dots[c].xy, gate, self.ref_area[:, c], dots[c].area)
            hit = idx >= 0
            uv[hit, c] = dots[c].xy[idx[hit]]
            cost[hit, c] = dist[hit]
        rejected = np.zeros(M, np.int8)
        X = np.full((M, 3), np.nan)
        both = np.all(np.isfinite(uv[:, :, 0]), axis=1)
        if both.any():
            Xt, err = self.rig.triangulate(uv[both, 0], uv[both, 1])
            X[both] = Xt
            bad = np.flatnonzero(both)[err.max(axis=1) > self.o.epipolar_px]
            rejected[bad] = 1
        # Neighbour consistency: motion relative to the prediction, against the neighbours' median.
        seen = np.all(np.isfinite(X), axis=1) & (rejected == 0)
        dev = np.where(seen[:, None], X - X_pred, 0.0)
        nb = self._neighbour_motion(dev, seen)
        off = seen & (np.linalg.norm(dev - nb, axis=1) > self.o.neighbour_mm)
        rejected[off] = 2
        drop = rejected > 0
        uv[drop] = np.nan
        cost[drop] = np.inf
        X[drop] = np.nan
        return uv, cost, X, rejected

    def _pass(self, order: list[int], dots: list[tuple[Dots, Dots]], start_X: np.ndarray):
        """Track along ``order`` (frames) from a known state at ``order[0]``."""
        F, M = len(order), len(start_X)
        uv = np.full((F, M, 2, 2), np.nan)
        cost = np.full((F, M, 2), np.inf)
        rej = np.zeros((F, M), np.int8)
        est = start_X.copy()  # current estimate of every marker (last seen, moved with neighbours)
        prev_seen = np.all(np.isfinite(start_X), axis=1)
        est[~prev_seen] = np.nan
        vel = np.zeros_like(est)
        for k, f in enumerate(order[1:], start=1):
            known = np.all(np.isfinite(est), axis=1)
            pred = np.where(known[:, None], est + vel, np.nan)
            u, c, X, r = self._observe(pred, dots[f], self.o.gate_px)
            uv[k], cost[k], rej[k] = u, c, r
            seen = np.all(np.isfinite(X), axis=1)
            moved = np.where(seen[:, None] & known[:, None], X - est, 0.0)
            nb = self._neighbour_motion(moved, seen & known)
            new_est = np.where(seen[:, None], X, est + nb)
            vel = np.where((seen & known)[:, None], X - est, nb)
            est = new_est
        return uv, cost, rej

    def anchors(self, thumbs: np.ndarray, reference: int) -> np.ndarray:
        """Anchor frames: image similarity (NCC of thumbnails) to the reference at least the threshold."""
        sim = thumbs @ thumbs[reference]
        cand = np.flatnonzero(sim >= self.o.anchor_similarity)
        out = [reference]
        for f in cand[np.argsort(-sim[cand], kind="stable")]:
            if all(abs(int(f) - a) >= self.o.anchor_min_spacing for a in out):
                out.append(int(f))
        return np.array(sorted(out))

    def track(self, dots: list[tuple[Dots, Dots]], thumbs: np.ndarray, reference: int = 0,
              reference_uv: np.ndarray | None = None) -> Tracks:
        """Label the reference frame and track every frame (see the module docstring).

        Parameters
        ----------
        dots : per frame, the detections of cameras 0 and 1
        thumbs : (F, P) float32 :func:`thumbnail` of each frame's camera-0 image
        reference_uv : (M, 2, 2), optional: the reference labels (else found automatically)
        """
        F, M = len(dots), len(self.layout)
        if reference_uv is None:
            ref_uv = self.label_reference(dots[reference])
        else:
            ref_uv = reference_uv
            for c in range(2):
                for m in np.flatnonzero(np.isfinite(ref_uv[:, c, 0])):
                    k = int(np.argmin(np.linalg.norm(dots[reference][c].xy - ref_uv[m, c], axis=1)))
                    self.ref_area[m, c] = dots[reference][c].area[k]
        ref_X = np.full((M, 3), np.nan)
        both = np.all(np.isfinite(ref_uv[:, :, 0]), axis=1)
        ref_X[both] = self.rig.triangulate(ref_uv[both, 0], ref_uv[both, 1])[0]
        if self.ref_fit is None:
            from lgi.dataset.stabilise import kabsch

            R, t = kabsch(self.layout[both], ref_X[both])
            self.ref_fit = self.layout @ R.T + t
        # Markers not labelled in the reference start from the fitted layout, so they can be picked up later.
        ref_X = np.where(np.isfinite(ref_X), ref_X, self.ref_fit)
        anchors = self.anchors(thumbs, reference)
        uv = np.full((F, M, 2, 2), np.nan)
        cost = np.full((F, M, 2), np.inf)
        source = np.zeros((F, M, 2), np.int8)
        rejected = np.zeros((F, M), np.int8)
        uv[reference], cost[reference] = ref_uv, np.where(np.isfinite(ref_uv[..., 0]), 0.0, np.inf)
        source[reference] = np.where(np.isfinite(ref_uv[..., 0]), 3, 0)
        anchor_X = {reference: ref_X}
        n_ref = int(np.isfinite(ref_uv[..., 0]).sum())
        kept = [reference]
        for a in anchors:
            if a == reference:
                continue
            u, c, X, r = self._observe(ref_X, dots[a], self.o.anchor_gate_px)
            # The head may have moved in the helmet: align the reference rigidly to this first match, then
            # match again from the aligned reference.
            seen = np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(ref_X), axis=1)
            if seen.sum() < 6:
                continue
            fit = rigid_fit(ref_X[seen], X[seen])
            u, c, X, r = self._observe(ref_X @ fit.rotation.T + fit.translation, dots[a], self.o.anchor_gate_px / 2)
            # A candidate is an anchor only if it matches the reference closely almost everywhere.
            ok = np.isfinite(c)
            if ok.sum() < self.o.anchor_min_matched * n_ref or np.median(c[ok]) > self.o.anchor_max_median_px:
                continue
            kept.append(int(a))
            uv[a], cost[a], rejected[a] = u, c, r
            source[a] = np.where(ok, 3, 0)
            anchor_X[a] = self._complete(X, ref_X)
        anchors = np.array(sorted(kept))
        bounds = [0, *anchors.tolist(), F - 1]
        for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
            if hi - lo < 1:
                continue
            runs = []
            if lo in anchor_X:
                runs.append((list(range(lo, hi + 1)), anchor_X[lo], 1))
            if hi in anchor_X:
                runs.append((list(range(hi, lo - 1, -1)), anchor_X[hi], 2))
            for order, start, label in runs:
                u, c, r = self._pass(order, dots, start)
                for k, f in enumerate(order[1:], start=1):
                    if f in anchor_X:
                        continue
                    better = c[k] < cost[f]
                    uv[f][better] = u[k][better]
                    cost[f][better] = c[k][better]
                    source[f][better] = label
                    rejected[f] = np.maximum(rejected[f], r[k])
        # Final triangulation and consistency of the merged observations.
        X = np.full((F, M, 3), np.nan)
        err = np.full((F, M, 2), np.nan)
        for f in range(F):
            b = np.all(np.isfinite(uv[f, :, :, 0]), axis=1)
            if b.any():
                Xt, e = self.rig.triangulate(uv[f, b, 0], uv[f, b, 1])
                bad = e.max(axis=1) > self.o.epipolar_px
                idx = np.flatnonzero(b)
                X[f, idx[~bad]] = Xt[~bad]
                err[f, idx[~bad]] = e[~bad]
                uv[f, idx[bad]] = np.nan
                source[f, idx[bad]] = 0
                rejected[f, idx[bad]] = 1
        return Tracks(uv, X, err, source, anchors, rejected)
