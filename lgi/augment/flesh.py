"""A volumetric flesh model for physically based in-betweens.

Linear blends of face shapes lose volume and let the lips pass through each other. Here the skin of the
moving part of the face is given a flesh layer: the skin and an inner surface offset along the inward
normal by ``thickness``, tetrahedralised by splitting each prism between a skin triangle and its inner
copy into three tetrahedra (with the vertex-order rule that makes neighbouring prisms conform; the layer
is thin and the skin mesh already good, so this is exact where a general tetrahedraliser would have to
close and re-mesh the surface). The inner side is the skull where the flesh barely moves in the dataset
(held at rest, or carried by the jaw rig), and free where it moves (cheeks and lips over the mouth).

An in-between is solved quasi-statically by projective dynamics (Bouaziz et al. 2014): per tetrahedron
an as-rigid-as-possible term ``||F - R||^2`` and a volume term ``||F - P||^2`` (``P = F / det(F)^(1/3)``,
the deformation gradient rescaled to determinant 1), each weighted by the rest volume; the skin is pulled softly
towards the target (a blend of dataset shapes); the system matrix is factorised once per model and each
iteration is a batch of 3x3 SVDs plus three back-substitutions. After each step, lower-lip skin that has
passed above the upper lip (along ``up``) is pushed back to the contact (a simple collision response).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit, prange
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from lgi.dataset.mesh import triangle_areas, vertex_normals
from lgi.errors import InputError

G0 = np.array([[-1.0, 1, 0, 0], [-1, 0, 1, 0], [-1, 0, 0, 1]])


@dataclass
class FleshOptions:
    """Flesh model parameters (lengths in the dataset's units, cm for ICT and the synthetic actor)."""

    thickness: float = 0.8
    motion_threshold: float = 0.02
    rings: int = 2
    soft_fraction: float = 0.2
    strain_weight: float = 1.0
    volume_weight: float = 300.0
    target_weight: float = 1.0
    iterations: int = 60
    lip_radius: float = 0.3


@dataclass
class FleshResult:
    """One simulated in-between.

    Attributes
    ----------
    positions : (V, 3) float64, the whole mesh (the target outside the simulated region)
    volume_change : float, relative change of the soft (mouth and cheek) flesh volume from the neutral
    target_distance : float, RMS distance of the simulated skin from the target
    contacts : int, lip vertex pairs pushed apart in the last iteration
    model : (2n, 3) float64, the flesh model's skin and inner vertices
    """

    positions: np.ndarray
    volume_change: float
    target_distance: float
    contacts: int
    model: np.ndarray


def _adjacency(n: int, triangles: np.ndarray) -> sp.csr_matrix:
    i = triangles[:, [0, 1, 2, 1, 2, 0]].ravel()
    j = triangles[:, [1, 2, 0, 0, 1, 2]].ravel()
    return sp.csr_matrix((np.ones(len(i), bool), (i, j)), shape=(n, n))


def _moving_region(triangles: np.ndarray, motion: np.ndarray, threshold: float, rings: int) -> np.ndarray:
    """(V,) bool: vertices moving more than ``threshold`` on the component that moves most, grown by
    ``rings`` rings of neighbours."""
    adj = _adjacency(len(motion), triangles)
    _, comp = connected_components(adj, directed=False)
    moving = motion > threshold
    if not moving.any():
        raise InputError("no vertex moves more than the motion threshold: nothing to simulate")
    main = comp == np.bincount(comp[moving]).argmax()
    region = moving & main
    for _ in range(rings):
        region = (region | ((adj @ region.astype(np.int64)) > 0)) & main
    return region


def _cut_vertices(triangles: np.ndarray, sub: np.ndarray) -> np.ndarray:
    """Vertices on edges that border the sub-mesh ``sub`` but are inside the full mesh (shared by two of its
    triangles there): where the simulated region is cut out of the face."""
    def edges(t: np.ndarray) -> np.ndarray:
        return np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)

    full_e, full_n = np.unique(edges(triangles), axis=0, return_counts=True)
    sub_e, sub_n = np.unique(edges(sub), axis=0, return_counts=True)
    once = sub_e[sub_n == 1]
    inner_full = full_e[full_n > 1]
    base = int(triangles.max()) + 1

    def key(e: np.ndarray) -> np.ndarray:
        return e[:, 0] * base + e[:, 1]

    cut = once[np.isin(key(once), key(inner_full))]
    return np.unique(cut)


def prism_tets(triangles: np.ndarray, n_outer: int) -> np.ndarray:
    """(3T, 4) tetrahedra filling the prisms between triangles (T, 3) and their inner copies (index + n).

    Each triangle's vertices are sorted by index, so every quad side is split along the diagonal from the
    lower index's inner vertex to the higher index's outer vertex, the same from both neighbouring prisms.
    """
    a, b, c = np.sort(triangles, axis=1).T
    ai, bi, ci = a + n_outer, b + n_outer, c + n_outer
    return np.concatenate([np.stack([a, b, c, ai], 1), np.stack([b, c, ai, bi], 1), np.stack([c, ai, bi, ci], 1)])


@njit(cache=True, parallel=True)
def _local_step(x: np.ndarray, tets: np.ndarray, K: np.ndarray, ws: np.ndarray, wv: np.ndarray) -> np.ndarray:
    """Right-hand side of the global step: per tetrahedron the rotation (polar decomposition by scaled
    Newton iterations; SVD for inverted elements) and the determinant-1 rescaling of its deformation
    gradient, weighted, per tetrahedron vertex. Returns (N, 4, 3), to be summed into the vertices."""
    out = np.zeros((tets.shape[0], 4, 3))
    for t in prange(tets.shape[0]):
        F = np.empty((3, 3))
        for d in range(3):
            for e in range(3):
                acc = 0.0
                for k in range(4):
                    acc += x[tets[t, k], d] * K[t, k, e]
                F[d, e] = acc
        det = (F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]) - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
               + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]))
        if det > 1e-12:
            R = F.copy()
            for _ in range(20):
                # Inverse transpose of R via the cofactor matrix.
                c00 = R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]
                c01 = R[1, 2] * R[2, 0] - R[1, 0] * R[2, 2]
                c02 = R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0]
                c10 = R[0, 2] * R[2, 1] - R[0, 1] * R[2, 2]
                c11 = R[0, 0] * R[2, 2] - R[0, 2] * R[2, 0]
                c12 = R[0, 1] * R[2, 0] - R[0, 0] * R[2, 1]
                c20 = R[0, 1] * R[1, 2] - R[0, 2] * R[1, 1]
                c21 = R[0, 2] * R[1, 0] - R[0, 0] * R[1, 2]
                c22 = R[0, 0] * R[1, 1] - R[0, 1] * R[1, 0]
                dr = R[0, 0] * c00 + R[0, 1] * c01 + R[0, 2] * c02
                # Scaling (Higham) speeds up convergence for stretched elements.
                nr = 0.0
                ni = 0.0
                for i in range(3):
                    for j in range(3):
                        nr += R[i, j] * R[i, j]
                cs = (c00, c01, c02, c10, c11, c12, c20, c21, c22)
                for v in cs:
                    ni += v * v
                ni /= dr * dr
                g = (ni / nr) ** 0.25
                change = 0.0
                inv_t = np.array([[c00, c01, c02], [c10, c11, c12], [c20, c21, c22]]) / dr
                for i in range(3):
                    for j in range(3):
                        nv = 0.5 * (g * R[i, j] + inv_t[i, j] / g)
                        change += abs(nv - R[i, j])
                        R[i, j] = nv
                if change < 1e-10:
                    break
            scale = det ** (-1.0 / 3.0)
            for i in range(3):
                for j in range(3):
                    F[i, j] = ws[t] * R[i, j] + wv[t] * scale * F[i, j]
        else:
            U, S, Vt = np.linalg.svd(F)
            if np.linalg.det(U) * np.linalg.det(Vt) < 0:
                U[:, 2] = -U[:, 2]
            R = U @ Vt
            for i in range(3):
                for j in range(3):
                    F[i, j] = (ws[t] + wv[t]) * R[i, j]
        for k in range(4):
            for d in range(3):
                acc = 0.0
                for e in range(3):
                    acc += K[t, k, e] * F[d, e]
                out[t, k, d] = acc
    return out


class FleshModel:
    """The flesh layer of a dataset's moving region, factorised for repeated solves.

    Parameters
    ----------
    neutral : (V, 3) float
    triangles : (T, 3) int
    deltas : (S, V, 3) float
        The dataset's shapes: which vertices move (the simulated region) and how much without the jaw
        (soft inner side or skull).
    rig : :class:`lgi.solve.jaw.JawRig`, optional
        Carries the jaw-side inner surface; its weights also split the lips for contact.
    up : (3,) the face's up direction (lower lip below upper lip)
    """

    def __init__(self, neutral: np.ndarray, triangles: np.ndarray, deltas: np.ndarray, rig=None,
                 up: tuple[float, float, float] = (0.0, 1.0, 0.0), options: FleshOptions | None = None,
                 shape_jaw: np.ndarray | None = None) -> None:
        o = self.options = options or FleshOptions()
        neutral = np.asarray(neutral, np.float64)
        triangles = np.asarray(triangles, np.int64)
        V = len(neutral)
        self.n_vertices = V
        self.rig = rig
        self.up = np.asarray(up, np.float64) / np.linalg.norm(up)
        motion = np.zeros(V)
        for d in deltas:
            motion = np.maximum(motion, np.linalg.norm(np.asarray(d, np.float64), axis=1))
        soft_motion = motion
        if rig is not None:
            from lgi.solve.jaw import fit_shape_parameters, unskin_deltas

            params = fit_shape_parameters(rig, neutral, deltas) if shape_jaw is None else shape_jaw
            soft_motion = np.zeros(V)
            for d in unskin_deltas(rig, neutral, deltas, params):
                soft_motion = np.maximum(soft_motion, np.linalg.norm(d, axis=1))
        region = _moving_region(triangles, motion, o.motion_threshold, o.rings)
        tri = triangles[np.all(region[triangles], axis=1)]
        verts = np.unique(tri)
        local = np.full(V, -1)
        local[verts] = np.arange(len(verts))
        self.verts = verts
        n = len(verts)
        self.n_outer = n
        tri_l = local[tri]
        self.tri_local = tri_l
        pinned_outer = np.zeros(n, bool)
        pinned_outer[local[_cut_vertices(triangles, tri)]] = True
        outer = neutral[verts]
        normals = vertex_normals(neutral, triangles)[verts]
        inner = outer - o.thickness * normals
        self.rest = np.vstack([outer, inner])
        tets = prism_tets(tri_l, n)
        X = self.rest[tets]  # (N, 4, 3)
        Dm = np.transpose(X[:, 1:] - X[:, :1], (0, 2, 1))
        det = np.linalg.det(Dm)
        flip = det < 0
        tets[flip] = tets[flip][:, [0, 2, 1, 3]]
        X = self.rest[tets]
        Dm = np.transpose(X[:, 1:] - X[:, :1], (0, 2, 1))
        vol = np.linalg.det(Dm) / 6.0
        keep = vol > 1e-9 * o.thickness**3
        tets, Dm, vol = tets[keep], Dm[keep], vol[keep]
        self.tets, self.vol = tets, vol
        self._scatter = tets.ravel()
        self.K = np.einsum("ij,njk->nik", G0.T, np.linalg.inv(Dm))  # (N, 4, 3): F[d, :] = x_d @ K
        # Soft inner side where the flesh moves by itself (not only with the jaw).
        soft = soft_motion[verts] >= o.soft_fraction * soft_motion[verts].max()
        if rig is not None:
            # Where the jaw weight is partial the flesh spans the joint (masseter, cheek): not bone either.
            jw = np.asarray(rig.weights, np.float64)[verts]
            soft |= (jw > 0.05) & (jw < 0.95)
        self.soft_outer = soft
        self.soft_tets = np.any(np.concatenate([soft, soft])[tets], axis=1)
        pinned = np.concatenate([pinned_outer, pinned_outer | ~soft])
        self.pinned = pinned
        self.free = np.flatnonzero(~pinned)
        area = np.zeros(n)
        a = triangle_areas(outer, tri_l)
        for c in range(3):
            np.add.at(area, tri_l[:, c], a / 3)
        self.w_target = np.concatenate([o.target_weight * area / o.thickness, np.zeros(n)])
        w = (o.strain_weight + o.volume_weight) * vol
        rows = np.repeat(tets, 4, axis=1).ravel()
        cols = np.tile(tets, (1, 4)).ravel()
        KK = np.einsum("nik,njk->nij", self.K, self.K) * w[:, None, None]
        L = sp.csr_matrix((KK.ravel(), (rows, cols)), shape=(2 * n, 2 * n))
        self._L = L
        self._lu_cache: dict[bool, tuple] = {}
        # Lip contact pairs (rest): lower-lip skin vertices and their nearest upper-lip skin vertex.
        self.lip_pairs = np.zeros((0, 2), np.int64)
        if rig is not None:
            from scipy.spatial import cKDTree

            jw = np.asarray(rig.weights, np.float64)[verts]
            lower, upper = np.flatnonzero(jw >= 0.5), np.flatnonzero(jw < 0.5)
            if len(lower) and len(upper):
                # Contact zone: lower-lip skin within lip_radius of the upper lip at rest (where they meet).
                d, j = cKDTree(outer[upper]).query(outer[lower])
                close = d < o.lip_radius
                self.lip_pairs = np.column_stack([lower[close], upper[j[close]]])

    def _factor(self, hard_skin: bool):
        if hard_skin not in self._lu_cache:
            fixed = self.pinned.copy()
            if hard_skin:
                fixed[: self.n_outer] = True
            free = np.flatnonzero(~fixed)
            L = self._L + sp.diags(np.zeros(len(self.w_target)) if hard_skin else self.w_target)
            L = L.tocsc()
            self._lu_cache[hard_skin] = (free, np.flatnonzero(fixed), splu(L[free][:, free].tocsc()),
                                         L[free][:, np.flatnonzero(fixed)])
        return self._lu_cache[hard_skin]

    def boundary(self, target: np.ndarray, jaw: np.ndarray | None = None) -> np.ndarray:
        """(2n, 3) positions of the pinned vertices for a target skin (V, 3): skin at the target, inner
        side at rest or carried by the jaw; the free inner vertices start under their skin."""
        n = self.n_outer
        x = np.empty_like(self.rest)
        x[:n] = target[self.verts]
        inner = self.rest[n:].copy()
        if self.rig is not None and jaw is not None:
            inner = self.rig.skin(inner, jaw, np.asarray(self.rig.weights, np.float64)[self.verts])
        # Free inner vertices start under their skin at the flesh's thickness (no inverted elements).
        start = x[:n] - self.options.thickness * vertex_normals(x[:n], self.tri_local)
        x[n:] = np.where(self.soft_outer[:, None], start, inner)
        return x

    def volumes(self, x: np.ndarray) -> np.ndarray:
        """(N,) signed tetrahedron volumes of model positions ``x`` (2n, 3)."""
        P = x[self.tets]
        return np.linalg.det(np.transpose(P[:, 1:] - P[:, :1], (0, 2, 1))) / 6.0

    def soft_volume_change(self, x: np.ndarray) -> float:
        """Relative change of the soft-region flesh volume of ``x`` (2n, 3) from rest."""
        m = self.soft_tets
        return float(self.volumes(x)[m].sum() / self.vol[m].sum() - 1.0)

    def _contact(self, x: np.ndarray) -> int:
        if not len(self.lip_pairs):
            return 0
        lo, hi = self.lip_pairs[:, 0], self.lip_pairs[:, 1]
        pen = (x[lo] - x[hi]) @ self.up  # > 0: the lower lip is above the upper lip
        bad = pen > 0
        if bad.any():
            shift = 0.5 * pen[bad, None] * self.up
            np.subtract.at(x, lo[bad], shift)
            np.add.at(x, hi[bad], shift)
        return int(bad.sum())

    def solve(self, target: np.ndarray, jaw: np.ndarray | None = None, hard_skin: bool = False) -> FleshResult:
        """Simulate the in-between whose skin target is ``target`` (V, 3).

        ``jaw`` (4,) places the jaw side of the inner surface (with a rig). ``hard_skin`` holds the skin
        exactly at the target (the linear blend with the flesh relaxed behind it, for comparison).
        """
        o = self.options
        target = np.asarray(target, np.float64)
        x = self.boundary(target, jaw)
        free, fixed, lu, L_fc = self._factor(hard_skin)
        tgt = np.zeros_like(x)
        tgt[: self.n_outer] = target[self.verts]
        const = -(L_fc @ x[fixed])
        if not hard_skin:
            const += (self.w_target[:, None] * tgt)[free]
        ws, wv = o.strain_weight * self.vol, o.volume_weight * self.vol
        contacts = 0
        for _ in range(o.iterations):
            contrib = _local_step(x, self.tets, self.K, ws, wv).reshape(-1, 3)
            rhs = np.column_stack([np.bincount(self._scatter, contrib[:, d], len(x)) for d in range(3)])
            x[free] = lu.solve(rhs[free] + const)
            if not hard_skin:  # held at the blend: the linear in-between as it is, lips and all
                contacts = self._contact(x)
        full = target.copy()
        full[self.verts] = x[: self.n_outer]
        dist = float(np.sqrt(np.mean(np.sum((x[: self.n_outer] - tgt[: self.n_outer]) ** 2, axis=1))))
        return FleshResult(full, self.soft_volume_change(x), dist, contacts, x)
