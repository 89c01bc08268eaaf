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
    from lgi.dataset._closest import closest_bary_rows

    return closest_bary_rows(*(np.ascontiguousarray(x, np.float64).reshape(-1, 3) for x in (p, a, b, c)))


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
    #: Candidate (point, triangle) pairs tested at once: 16 bytes each of the k-d tree's answer.
    PAIRS = 1 << 19
    #: Triangles whose corners are held at once while the query is built.
    BLOCK = 1 << 18

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        self.vertices = np.asarray(vertices, np.float64)
        self.triangles = np.asarray(triangles, np.int64)
        # Corners, centroids and radii a block of triangles at a time: whole, a 10-million-triangle scan's corners
        # alone were 720 MB.
        n_tri = len(self.triangles)
        self._centroids = np.empty((n_tri, 3))
        radius = np.empty(n_tri)
        for lo in range(0, n_tri, self.BLOCK):
            corners = self.vertices[self.triangles[lo:lo + self.BLOCK]]
            self._centroids[lo:lo + self.BLOCK] = corners.mean(axis=1)
            radius[lo:lo + self.BLOCK] = np.linalg.norm(corners - self._centroids[lo:lo + self.BLOCK, None],
                                                        axis=2).max(axis=1)
        cap = self.SAMPLE_RADIUS * float(np.median(radius)) if len(radius) else 0.0
        split = np.ones(len(radius), np.int64)
        if cap > 0:
            split = np.maximum(1, np.ceil(radius / cap)).astype(np.int64)
        # Each sample's triangle (None: the samples are the centroids, in order, as in a scan of even triangles).
        self._owner: np.ndarray | None = None
        if (split == 1).all():
            self._tree = self._kd_tree(self._centroids)
            self._radius = float(radius.max()) if len(radius) else 0.0
            return
        samples, owner = [self._centroids[split == 1]], [np.flatnonzero(split == 1)]
        for n in np.unique(split[split > 1]):
            which = np.flatnonzero(split == n)
            # The n*n similar sub-triangles' centroids, in (edge 1, edge 2) coordinates: upward and downward ones.
            i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
            up = (i + j <= n - 1)
            down = (i + j <= n - 2)
            st = np.concatenate([np.stack([i[up] + 1 / 3, j[up] + 1 / 3], 1),
                                 np.stack([i[down] + 2 / 3, j[down] + 2 / 3], 1)]) / n
            c = self.vertices[self.triangles[which]]
            pts = c[:, None, 0] + st[None, :, :1] * (c[:, None, 1] - c[:, None, 0]) + \
                st[None, :, 1:] * (c[:, None, 2] - c[:, None, 0])
            samples.append(pts.reshape(-1, 3))
            owner.append(np.repeat(which, len(st)))
        self._owner = np.concatenate(owner)
        # Every point of a triangle is within its radius / n of one of its samples.
        self._radius = float((radius / split).max()) if len(radius) else 0.0
        self._tree = self._kd_tree(np.concatenate(samples))

    @staticmethod
    def _kd_tree(samples: np.ndarray):
        from scipy.spatial import cKDTree  # here, not at the top: importing scipy.spatial costs every command 0.3 s

        return cKDTree(samples)

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
        n_samples = self._tree.n
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
        from lgi.dataset._closest import nearest_of_candidates

        cd, si = self._tree.query(p, k=k)
        cd = cd.reshape(len(p), -1)
        t, b, d = np.empty(len(p), np.int64), np.empty((len(p), 3)), np.empty(len(p))
        si = si.reshape(len(p), -1)
        nearest_of_candidates(p, si if self._owner is None else self._owner[si], self.vertices, self.triangles,
                              self._centroids, t, b, d)
        tri[rows_out], bary[rows_out], dist[rows_out] = t, b, d
        return cd[:, -1]
