"""Lip occlusion contours as a post-process on the reconstructed surface (LGI 7.4, after Bhat et al. 2013).

A rotoscoped (or traced) contour is a 2D polyline per frame and camera where the upper or the lower lip's
inner edge is seen. The mesh's counterpart is the lip's inner edge: the chains of the mouth opening's boundary
loop, split at the mouth corners into the upper lip's (its faces above it) and the lower lip's. Per frame,
:meth:`LipContours.fit` alternates, as an ICP on the image:

1. project each chain vertex into each camera that traced its curve and take the closest point of the curve
   (within ``gate_px``, and not past either end of the traced stretch);
2. the vertex should lie on the viewing ray through that point: its target is the ray's closest point;
3. move the lip region (the vertices within ``region_cm`` of the chains on the neutral) by the smoothest
   displacement (least squares on its graph Laplacian, i.e. a thin-plate-like bending energy) that takes the
   chain vertices to their targets (weighted), and keeps the region's rim and every marker's triangle where
   they are: the bundles keep their surface points and the surface stays continuous.

Only the boundary of the mouth opening is a contour here: a mesh whose lips roll inward (occluding contours
that slide over the lip) is not handled; a mesh without a mouth opening is refused.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lgi.errors import InputError
from lgi.units import MM_PER_CM

log = logging.getLogger(__name__)

CURVES = ("upper_inner", "lower_inner")


@dataclass
class ContourView:
    """One traced curve in one camera of one frame."""

    camera: object  # lgi.capture.camera.Camera
    R: np.ndarray  # (3, 3) head -> rig frame
    t: np.ndarray  # (3,) mm
    curve: str
    points: np.ndarray  # (P, 2) px, in order along the curve


def boundary_loops(triangles: np.ndarray) -> list[np.ndarray]:
    """The mesh's boundary loops, each an ordered (n,) array of vertex ids."""
    e = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    edges = uniq[count == 1]
    nxt: dict[int, list[int]] = {}
    for a, b in edges:
        nxt.setdefault(int(a), []).append(int(b))
        nxt.setdefault(int(b), []).append(int(a))
    loops, done = [], set()
    for start in nxt:
        if start in done:
            continue
        loop, prev, cur = [start], None, start
        done.add(start)
        while True:
            step = [v for v in nxt[cur] if v != prev and (v not in done or v == start)]
            if not step or step[0] == start:
                break
            prev, cur = cur, step[0]
            loop.append(cur)
            done.add(cur)
        loops.append(np.array(loop))
    return loops


class LipContours:
    """The lip edges of an index's mesh and the lip region's deformation, precomputed once per shot.

    Parameters
    ----------
    neutral : (V, 3) float, cm
    triangles : (T, 3) int
    marker_vertices : (M, 3) int; marker_weights : (M, 3) float
        Each marker's triangle and barycentric weights: the deformation keeps every marker's surface point
        where it is (a hard constraint; the triangle's vertices may still move).
    region_cm : float
        Vertices within this distance of the lip edges (on the neutral) may move.
    """

    def __init__(self, neutral: np.ndarray, triangles: np.ndarray, marker_vertices: np.ndarray,
                 marker_weights: np.ndarray, region_cm: float = 1.0, gate_px: float = 10.0,
                 weight: float = 100.0) -> None:
        import scipy.sparse as sp
        from scipy.spatial import cKDTree

        self.gate_px, self.weight = gate_px, weight
        loops = boundary_loops(triangles)
        extent = [np.ptp(neutral[lp], axis=0).sum() for lp in loops]
        inner = [lp for k, lp in enumerate(loops) if k != int(np.argmax(extent)) and len(lp) >= 4]
        if not inner:
            raise InputError("lip contours need a mouth opening in the mesh (a boundary loop inside the face): "
                             "this index's mesh has none")
        # The mouth: the interior loop nearest the markers' centre below the eyes is not known in general; take
        # the longest interior loop (eyes are usually closed surfaces or shorter loops).
        mouth = max(inner, key=len)
        x = neutral[mouth, 0]
        a, b = int(np.argmin(x)), int(np.argmax(x))
        if a > b:
            a, b = b, a
        one = mouth[a:b + 1]
        two = np.concatenate([mouth[b:], mouth[:a + 1]])[::-1]
        side = {}
        tri_of: dict[tuple[int, int], int] = {}
        for k, tr in enumerate(triangles):
            for i in range(3):
                tri_of[tuple(sorted((int(tr[i]), int(tr[(i + 1) % 3]))))] = k
        for chain in (one, two):
            up = []
            for p, q in zip(chain[:-1], chain[1:], strict=True):
                k = tri_of.get(tuple(sorted((int(p), int(q)))))
                if k is not None:
                    up.append(neutral[triangles[k], 1].mean() - 0.5 * (neutral[p, 1] + neutral[q, 1]))
            side[id(chain)] = float(np.mean(up)) if up else 0.0
        upper, lower = (one, two) if side[id(one)] > side[id(two)] else (two, one)
        self.chains = {"upper_inner": upper, "lower_inner": lower}
        edge_ids = np.unique(np.concatenate([upper, lower]))
        near = cKDTree(neutral[edge_ids]).query(neutral)[0] <= region_cm
        # Graph of the mesh: its edges, for the Laplacian and the rim.
        e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
        e = np.unique(np.sort(e, axis=1), axis=0)
        rim = np.zeros(len(neutral), bool)
        cross = near[e[:, 0]] != near[e[:, 1]]
        rim[e[cross].ravel()] = True
        fixed = ~near | rim
        self.free = np.flatnonzero(near & ~fixed)
        col = np.full(len(neutral), -1)
        col[self.free] = np.arange(len(self.free))
        # The bundles keep their surface points: sum_k b_k d(v_k) = 0 over each marker's triangle.
        mv, mw = np.asarray(marker_vertices), np.asarray(marker_weights, np.float64)
        touched = np.flatnonzero((col[mv] >= 0).any(axis=1))
        r, c, w = [], [], []
        for k, m in enumerate(touched):
            for v, b in zip(mv[m], mw[m], strict=True):
                if col[v] >= 0 and b != 0:
                    r.append(k)
                    c.append(col[v])
                    w.append(b)
        self.keep = sp.csr_matrix((w, (r, c)), shape=(len(touched), len(self.free)))
        n = len(neutral)
        adj = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                            shape=(n, n)).tocsr()
        deg = np.asarray(adj.sum(axis=1)).ravel()
        lap = sp.diags(deg) - adj  # uniform graph Laplacian of the whole mesh
        rows = np.flatnonzero(near)
        self.lap = lap[rows][:, self.free].tocsc()  # fixed vertices do not move: their columns drop out
        self.bending = (self.lap.T @ self.lap).tocsc()
        self.col = col
        self.n_free = len(self.free)

    def fit_frames(self, vertices: np.ndarray, curves: list, cameras: list, head_r: np.ndarray, head_t: np.ndarray
                   ) -> tuple[np.ndarray, list[int], list[int]]:
        """Fit frames of surfaces ``vertices`` (F, V, 3), cm, head frame, in place, onto their traced curves:
        ``curves`` (F,), each frame's list of ``(camera index, curve name, (P, 2) px)`` (empty or None: nothing
        traced), seen by ``cameras`` from the head poses ``head_r`` (F, 3, 3) and ``head_t`` (F, 3) mm (NaN:
        unknown).

        Returns the RMS pixel distance of the lip edges from the curves before and after (2, F) (NaN where nothing
        was fitted), and the frames (positions) whose curves could not be used: those without a head pose, and
        those where no lip edge vertex came within ``gate_px`` of the curves."""
        px = np.full((2, len(vertices)), np.nan)
        no_pose, unmatched = [], []
        for f, frame_curves in enumerate(curves):
            if not frame_curves:
                continue
            if not np.all(np.isfinite(head_r[f])):
                no_pose.append(f)
                continue
            views = [ContourView(cameras[c], head_r[f], head_t[f], name, pts) for c, name, pts in frame_curves]
            x, px[0, f], px[1, f] = self.fit(vertices[f], views)
            if not np.isfinite(px[0, f]):
                unmatched.append(f)
            vertices[f] = x
        return px, no_pose, unmatched

    def fit(self, x: np.ndarray, views: list[ContourView], iterations: int = 8) -> tuple[np.ndarray, float, float]:
        """Move the lip region of surface ``x`` (V, 3) float, cm, head frame, onto the traced curves.

        Returns the corrected surface (float64) and the RMS pixel distance of the chain vertices that found their
        curve from it, before and after (NaN when none did)."""
        import scipy.sparse as sp
        from scipy.sparse.linalg import spsolve

        x = np.asarray(x, np.float64).copy()
        before = after = float("nan")
        for it in range(iterations + 1):
            rows, targets, errs = [], [], []
            for v in views:
                chain = self.chains[v.curve]
                world = x[chain] * MM_PER_CM @ v.R.T + v.t
                uv = v.camera.project(world)
                foot, dist, inside = _closest_on_polyline(v.points, uv)
                ok = inside & (dist <= self.gate_px) & np.isfinite(dist)
                errs.append(dist[ok])
                if it == iterations or not ok.any():
                    continue
                cam = v.camera
                d_world = cam.rays(foot[ok]) @ cam.R
                o = v.R.T @ (cam.center - v.t) / MM_PER_CM
                d = d_world @ v.R  # R^T d, row-wise
                d /= np.linalg.norm(d, axis=1, keepdims=True)
                p = x[chain[ok]]
                along = np.einsum("ij,ij->i", p - o, d)
                rows.append(chain[ok])
                targets.append(o + along[:, None] * d - p)
            e = np.concatenate(errs) if errs else np.zeros(0)
            rms = float(np.sqrt(np.mean(e**2))) if e.size else float("nan")
            if it == 0:
                before = rms
            after = rms
            if it == iterations or not rows:
                break
            ids = np.concatenate(rows)
            delta = np.concatenate(targets)
            c = self.col[ids]
            use = c >= 0
            if not use.any():
                break
            # Several cameras (or both curves at a corner) may ask for one vertex: their mean.
            cnt = np.bincount(c[use], minlength=self.n_free)
            acc = np.zeros((self.n_free, 3))
            np.add.at(acc, c[use], delta[use])
            has = cnt > 0
            acc[has] /= cnt[has, None]
            w = sp.diags(np.where(has, self.weight, 0.0))
            kkt = sp.bmat([[self.bending + w, self.keep.T], [self.keep, None]]).tocsc()
            rhs = np.zeros((kkt.shape[0], 3))
            rhs[:self.n_free] = self.weight * acc * has[:, None]
            disp = spsolve(kkt, rhs)[:self.n_free]
            x[self.free] += disp
        return x, before, after


def _closest_on_polyline(poly: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For points q (N, 2): the closest point on polyline ``poly`` (P, 2), its distance, and whether it falls
    within the polyline (not at an end beyond which the point lies)."""
    if len(poly) < 2:
        n = len(q)
        return np.full((n, 2), np.nan), np.full(n, np.inf), np.zeros(n, bool)
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.einsum("nsk,sk->ns", q[:, None] - a[None], ab) / np.maximum(np.einsum("sk,sk->s", ab, ab), 1e-12)
    tc = np.clip(t, 0.0, 1.0)
    foot = a[None] + tc[..., None] * ab[None]
    dist = np.linalg.norm(q[:, None] - foot, axis=2)
    dist = np.where(np.isfinite(dist), dist, np.inf)
    k = np.argmin(dist, axis=1)
    r = np.arange(len(q))
    past = ((k == 0) & (t[r, k] < -1e-6)) | ((k == len(ab) - 1) & (t[r, k] > 1 + 1e-6))
    return foot[r, k], dist[r, k], ~past
