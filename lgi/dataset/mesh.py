"""Triangle-mesh geometry on plain arrays: triangulation, normals, areas, closest points.

The canonical triangulation of a polygon mesh is a fan from each polygon's first corner, polygons
in order. Marker layouts refer to triangles by their index in it, so it must never change.
"""

from __future__ import annotations

import numpy as np


def triangulate(face_vertices: np.ndarray, face_offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons.

    Parameters
    ----------
    face_vertices : (N,) int
        Polygon corners, flat.
    face_offsets : (F + 1,) int
        Polygon ``f`` spans ``face_vertices[face_offsets[f]:face_offsets[f + 1]]``.

    Returns
    -------
    triangles : (T, 3) int32
        Triangle ``(c0, ck, ck+1)`` for ``k = 1 .. n-2`` of every polygon, in polygon order.
    triangle_face : (T,) int32
        The polygon each triangle came from.
    """
    face_offsets = np.asarray(face_offsets, np.int64)
    sizes = np.diff(face_offsets)
    n_tri = np.maximum(sizes - 2, 0)
    face_of_tri = np.repeat(np.arange(sizes.size, dtype=np.int32), n_tri)
    # k-th triangle within its polygon
    first = np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    k = np.arange(face_of_tri.size) - first
    base = face_offsets[face_of_tri]
    fv = np.asarray(face_vertices, np.int32)
    tris = np.stack([fv[base], fv[base + 1 + k], fv[base + 2 + k]], axis=1)
    return tris.astype(np.int32), face_of_tri


def triangle_normals(vertices: np.ndarray, triangles: np.ndarray, normalize: bool = True) -> np.ndarray:
    """(T, 3) float64 triangle normals; unnormalised ones have length twice the triangle's area."""
    v = np.asarray(vertices, np.float64)
    n = np.cross(v[triangles[:, 1]] - v[triangles[:, 0]], v[triangles[:, 2]] - v[triangles[:, 0]])
    if normalize:
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return n


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(V, 3) float64 area-weighted unit vertex normals (zero for unreferenced vertices)."""
    fn = triangle_normals(vertices, triangles, normalize=False)
    vn = np.zeros((len(vertices), 3))
    for c in range(3):
        np.add.at(vn, triangles[:, c], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.divide(vn, norm, out=np.zeros_like(vn), where=norm > 0)


def triangle_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T,) float64 triangle areas, in squared mesh units."""
    return 0.5 * np.linalg.norm(triangle_normals(vertices, triangles, normalize=False), axis=1)


def closest_point_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the closest point on each triangle (Ericson's region tests).

    Parameters
    ----------
    p, a, b, c : (N, 3) float
        Query points and triangle corners, paired row by row.

    Returns
    -------
    (N, 3) float64
        Barycentric weights ``(wa, wb, wc)``, non-negative, summing to 1.
    """
    p, a, b, c = (np.asarray(x, np.float64) for x in (p, a, b, c))
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    out = np.empty((p.shape[0], 3))
    done = np.zeros(p.shape[0], bool)

    def put(mask: np.ndarray, w: np.ndarray) -> None:
        m = mask & ~done
        out[m] = w[m]
        done[m] = True

    one = np.ones_like(d1)
    zero = np.zeros_like(d1)
    put((d1 <= 0) & (d2 <= 0), np.stack([one, zero, zero], 1))
    put((d3 >= 0) & (d4 <= d3), np.stack([zero, one, zero], 1))
    with np.errstate(divide="ignore", invalid="ignore"):
        v = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - v, v, zero], 1))
        put((d6 >= 0) & (d5 <= d6), np.stack([zero, zero, one], 1))
        w = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - w, zero, w], 1))
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), np.stack([zero, 1 - w, w], 1))
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        put(np.ones_like(done), np.stack([1 - v - w, v, w], 1))
    return out


class ClosestPointQuery:
    """Closest points on a triangle mesh, for repeated queries against one surface.

    Candidate triangles come from a k-d tree of sample points on the triangles and are tested exactly; the
    candidate set grows until it provably contains the closest triangle (the k-th sample is farther than the best
    distance plus the samples' covering radius). A triangle is sampled by its centroid, or, when it is more than
    :data:`SAMPLE_RADIUS` times the median triangle's size, by the centroids of an n x n subdivision: with the
    whole triangles' centroids the bound was the largest triangle's radius, 7 times the median on ICT, and a
    whole-face query of ICT against itself went on to thousands of candidates per point (130 s, 22 GB).

    Parameters
    ----------
    vertices : (V, 3) float
    triangles : (T, 3) int
    """

    #: Triangles larger than this many median triangles' radii are subdivided into samples.
    SAMPLE_RADIUS = 2.0
    #: Candidate (point, triangle) pairs tested at once: about 250 bytes each of working arrays.
    PAIRS = 1 << 19

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        self.vertices = np.asarray(vertices, np.float64)
        self.triangles = np.asarray(triangles, np.int64)
        corners = self.vertices[self.triangles]
        self._centroids = corners.mean(axis=1)
        radius = np.linalg.norm(corners - self._centroids[:, None], axis=2).max(axis=1) if len(corners) else \
            np.zeros(0)
        cap = self.SAMPLE_RADIUS * float(np.median(radius)) if len(radius) else 0.0
        split = np.ones(len(radius), np.int64)
        if cap > 0:
            split = np.maximum(1, np.ceil(radius / cap)).astype(np.int64)
        samples, owner = [self._centroids[split == 1]], [np.flatnonzero(split == 1)]
        for n in np.unique(split[split > 1]):
            which = np.flatnonzero(split == n)
            # The n*n similar sub-triangles' centroids, in (edge 1, edge 2) coordinates: upward and downward ones.
            i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
            up = (i + j <= n - 1)
            down = (i + j <= n - 2)
            st = np.concatenate([np.stack([i[up] + 1 / 3, j[up] + 1 / 3], 1),
                                 np.stack([i[down] + 2 / 3, j[down] + 2 / 3], 1)]) / n
            c = corners[which]
            pts = c[:, None, 0] + st[None, :, :1] * (c[:, None, 1] - c[:, None, 0]) + \
                st[None, :, 1:] * (c[:, None, 2] - c[:, None, 0])
            samples.append(pts.reshape(-1, 3))
            owner.append(np.repeat(which, len(st)))
        self._owner = np.concatenate(owner)
        # Every point of a triangle is within its radius / n of one of its samples.
        self._radius = float((radius / split).max()) if len(radius) else 0.0
        from scipy.spatial import cKDTree  # here, not at the top: importing scipy.spatial costs every command 0.3 s

        self._tree = cKDTree(np.concatenate(samples))

    def query(self, points: np.ndarray, k: int = 16) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface point of each query point.

        Parameters
        ----------
        points : (N, 3) float

        Returns
        -------
        triangle : (N,) int64
            Index of the triangle holding the closest point (of equally close ones, the one whose centroid is
            nearest).
        bary : (N, 3) float64
            Its barycentric coordinates in that triangle.
        distance : (N,) float64
            Distance from the query point, in mesh units.
        """
        points = np.atleast_2d(np.asarray(points, np.float64))
        n = len(points)
        tri = np.zeros(n, np.int64)
        bary = np.zeros((n, 3))
        dist = np.full(n, np.inf)
        todo = np.arange(n)
        n_samples = len(self._owner)
        k = min(k, n_samples)
        while todo.size:
            unsure = []
            step = max(1, self.PAIRS // k)
            for lo in range(0, len(todo), step):
                part = todo[lo:lo + step]
                cd = self._nearest(points[part], k, tri, bary, dist, part)
                unsure.append(part[(cd < dist[part] + self._radius) & (k < n_samples)])
            todo = np.concatenate(unsure)
            k = min(4 * k, n_samples)
        return tri, bary, dist

    def _nearest(self, p: np.ndarray, k: int, tri: np.ndarray, bary: np.ndarray, dist: np.ndarray,
                 rows_out: np.ndarray) -> np.ndarray:
        """The closest of the triangles of the ``k`` samples nearest each of ``p`` (N, 3), written to ``tri``,
        ``bary`` and ``dist`` at ``rows_out``; returns the k-th sample's distance (N,)."""
        cd, si = self._tree.query(p, k=k)
        cd = cd.reshape(len(p), -1)
        ci = self._owner[si.reshape(len(p), -1)]
        q = np.repeat(p, ci.shape[1], axis=0)
        t = self.triangles[ci.ravel()]
        w = closest_point_on_triangles(q, self.vertices[t[:, 0]], self.vertices[t[:, 1]], self.vertices[t[:, 2]])
        cp = np.einsum("nk,nkd->nd", w, self.vertices[t])
        d = np.linalg.norm(cp - q, axis=1).reshape(len(p), -1)
        # Of equally close triangles (a point nearest a shared edge or vertex), the one whose centroid is nearest.
        tie = d == d.min(axis=1, keepdims=True)
        centre = np.linalg.norm(self._centroids[ci] - p[:, None], axis=2)
        best = np.argmin(np.where(tie, centre, np.inf), axis=1)
        rows = np.arange(len(p))
        tri[rows_out] = ci[rows, best]
        bary[rows_out] = w.reshape(len(p), -1, 3)[rows, best]
        dist[rows_out] = d[rows, best]
        return cd[:, -1]
