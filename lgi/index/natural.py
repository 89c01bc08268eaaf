"""Natural-neighbour (Sibson) weights of the bundles over the mesh, from a geodesic Voronoi diagram.

Distances are geodesic on the mesh, measured in UV space (the paper found UV-space weights smoother
than 3D ones): every mesh edge is as long as it is in the texture, scaled to centimetre-equivalents by
one global factor. The graph is the welded 3D mesh, so a UV seam cuts nothing and the weights are
continuous across it, while holes (mouth, eyes) are walked around, never crossed.

Sibson weights are computed by discrete "area stealing" (Park et al. 2006): a query vertex ``q``
steals every surface sample ``s`` with ``d(q, s) < r(s)``, where ``r(s)`` is the distance from ``s`` to
its nearest bundle; its weight for bundle ``j`` is the stolen area of ``j``'s Voronoi cell over all
stolen area. Samples are ``n x n`` sub-triangles per triangle (centroids, area-weighted), distances
inside a triangle are interpolated from its corners, and the Voronoi owner of a sample is the bundle
with the smallest interpolated distance, so cell boundaries are resolved below the triangle size.

Rules beyond the interpolation:

* the vertices of each bundle's own triangle take weight 1 for that bundle, so the blended surface
  passes exactly through the bundle (the Sibson weight there is already close to 1);
* vertices farther than ``region_radius`` from every bundle, or not connected to any (eyeballs,
  teeth, back of the head), copy the weights of the nearest region vertex (3D distance on the neutral).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from lgi.dataset.mesh import triangulate


@dataclass
class NaturalNeighbours:
    """Natural-neighbour weights of M bundles at V vertices.

    Attributes
    ----------
    weights : scipy.sparse.csr_matrix (V, M) float32
        Rows sum to 1.
    neighbours : list of (K_i,) int arrays
        Bundles whose Voronoi cells touch bundle i's (its natural neighbours).
    distance : (V,) float64
        UV-geodesic distance (cm-equivalent) from each vertex to its nearest bundle (inf if unreachable).
    owner : (V,) int64
        Nearest bundle of each vertex (-1 if unreachable).
    region : (V,) bool
        Vertices whose weights are Sibson weights (the others copy a region vertex's).
    uv_scale : float
        cm per UV unit used for the metric.
    conflicts : list of str
        Vertices claimed by two bundles' triangles (the later claim lost).
    """

    weights: sp.csr_matrix
    neighbours: list[np.ndarray]
    distance: np.ndarray
    owner: np.ndarray
    region: np.ndarray
    uv_scale: float
    conflicts: list[str]


def uv_metric_graph(
    vertices: np.ndarray, face_vertices: np.ndarray, face_offsets: np.ndarray,
    uvs: np.ndarray | None, face_uvs: np.ndarray | None,
) -> tuple[sp.csr_matrix, float]:
    """Welded mesh graph with UV-space edge lengths in cm-equivalents.

    Every pair of corners of a polygon is an edge (so quads get both diagonals, which lowers the
    metrication error of graph distances). An edge on a UV seam has one length per side; their mean
    is used. Without UVs the 3D lengths are used.

    Returns
    -------
    graph : (V, V) csr_matrix, symmetric, edge lengths
    scale : float
        cm per UV unit (median ratio of 3D to UV edge length), 1.0 without UVs.
    """
    fo = np.asarray(face_offsets, np.int64)
    sizes = np.diff(fo)
    rows_a, rows_b, la = [], [], []
    for n in np.unique(sizes):
        polys = np.flatnonzero(sizes == n)
        idx = fo[polys][:, None] + np.arange(n)[None]
        pv = np.asarray(face_vertices)[idx]
        pu = None if face_uvs is None else np.asarray(face_uvs)[idx]
        for i in range(n):
            for j in range(i + 1, n):
                rows_a.append(pv[:, i])
                rows_b.append(pv[:, j])
                if pu is not None:
                    la.append(np.linalg.norm(uvs[pu[:, i]] - uvs[pu[:, j]], axis=1))
    a = np.concatenate(rows_a)
    b = np.concatenate(rows_b)
    l3 = np.linalg.norm(vertices[a] - vertices[b], axis=1)
    if uvs is not None and face_uvs is not None:
        luv = np.concatenate(la)
        ok = (luv > 1e-12) & (l3 > 1e-12)
        scale = float(np.median(l3[ok] / luv[ok]))
        length = luv * scale
    else:
        scale, length = 1.0, l3
    length = np.maximum(length, 1e-9)  # csgraph treats an explicit 0 as "no edge"
    n_v = len(vertices)
    key = np.minimum(a, b) * n_v + np.maximum(a, b)
    uniq, inv = np.unique(key, return_inverse=True)
    mean_len = np.bincount(inv, weights=length) / np.bincount(inv)
    ua, ub = uniq // n_v, uniq % n_v
    g = sp.coo_matrix((np.r_[mean_len, mean_len], (np.r_[ua, ub], np.r_[ub, ua])), shape=(n_v, n_v)).tocsr()
    return g, scale


def _site_graph(graph: sp.csr_matrix, site_vertices: np.ndarray, site_lengths: np.ndarray) -> sp.csr_matrix:
    """The graph plus one node per site joined to its triangle's corners (directed away from sites)."""
    n_v = graph.shape[0]
    m = len(site_vertices)
    rows = np.repeat(np.arange(n_v, n_v + m), 3)
    extra = sp.coo_matrix((np.maximum(site_lengths.ravel(), 1e-9), (rows, site_vertices.ravel())),
                          shape=(n_v + m, n_v + m))
    base = sp.block_diag([graph, sp.csr_matrix((m, m))]).tocsr()
    return (base + extra).tocsr()


@nb.njit(cache=True)
def _steal(dq, tri, bary, r_s, owner_s, area_s, limit, m, out):  # pragma: no cover - compiled
    """Accumulate stolen areas for a chunk of queries.

    dq (Q, V) distances from each query; tri (T, 3); bary (n, 3) sample patterns; r_s, owner_s,
    area_s (T, n); out (Q, M) accumulates area per bundle.
    """
    nq = dq.shape[0]
    for q in range(nq):
        for t in range(tri.shape[0]):
            d0 = dq[q, tri[t, 0]]
            d1 = dq[q, tri[t, 1]]
            d2 = dq[q, tri[t, 2]]
            if d0 > limit or d1 > limit or d2 > limit:
                continue
            for s in range(bary.shape[0]):
                ds = bary[s, 0] * d0 + bary[s, 1] * d1 + bary[s, 2] * d2
                if ds < r_s[t, s]:
                    out[q, owner_s[t, s]] += area_s[t, s]


def sample_pattern(n: int) -> np.ndarray:
    """(n*n, 3) barycentric centroids of the n x n sub-triangles of a triangle (equal areas)."""
    pts = []
    for i in range(n):
        for j in range(n - i):
            pts.append(((i + 1 / 3) / n, (j + 1 / 3) / n))  # upward sub-triangle
            if i + j < n - 1:
                pts.append(((i + 2 / 3) / n, (j + 2 / 3) / n))  # downward sub-triangle
    uv = np.asarray(pts)
    return np.column_stack([1 - uv.sum(1), uv[:, 0], uv[:, 1]])


def natural_neighbour_weights(
    vertices: np.ndarray,
    face_vertices: np.ndarray,
    face_offsets: np.ndarray,
    uvs: np.ndarray | None,
    face_uvs: np.ndarray | None,
    site_triangles: np.ndarray,
    site_bary: np.ndarray,
    region_radius: float = 3.0,
    subdivisions: int = 3,
    chunk: int = 256,
) -> NaturalNeighbours:
    """Sibson weights of bundles (sites on the neutral surface) at every vertex.

    Parameters
    ----------
    vertices : (V, 3) float, cm
        The neutral mesh.
    face_vertices, face_offsets, uvs, face_uvs
        Its polygons and texture coordinates (see :class:`lgi.io.obj.PolyMesh`).
    site_triangles : (M,) int
        Each bundle's triangle in the canonical triangulation.
    site_bary : (M, 3) float
        Its barycentric coordinates there.
    region_radius : float, cm-equivalent
        Vertices farther than this from every bundle copy the weights of the nearest region vertex.
    subdivisions : int
        Samples per triangle edge for the stolen-area integral (``n*n`` samples per triangle).
    chunk : int
        Queries per Dijkstra batch (memory: ``chunk * V * 8`` bytes).
    """
    vertices = np.asarray(vertices, np.float64)
    n_v = len(vertices)
    m = len(site_triangles)
    tris, _ = triangulate(face_vertices, face_offsets)
    tri_uv = None if face_uvs is None else triangulate(face_uvs, face_offsets)[0]
    graph, scale = uv_metric_graph(vertices, face_vertices, face_offsets, uvs, face_uvs)

    st = tris[site_triangles]  # (M, 3) vertices of each site's triangle
    if tri_uv is not None:
        corner_uv = uvs[tri_uv[site_triangles]]  # (M, 3, 2)
        site_uv = np.einsum("mk,mkd->md", site_bary, corner_uv)
        site_len = np.linalg.norm(corner_uv - site_uv[:, None], axis=2) * scale
    else:
        corner = vertices[st]
        site_len = np.linalg.norm(corner - np.einsum("mk,mkd->md", site_bary, corner)[:, None], axis=2)
    g2 = _site_graph(graph, st, site_len)
    site_nodes = np.arange(n_v, n_v + m)

    dist, _, src = dijkstra(g2, indices=site_nodes, min_only=True, return_predecessors=True)
    dist = dist[:n_v]
    owner = np.where(np.isfinite(dist), src[:n_v] - n_v, -1)
    region = np.isfinite(dist) & (dist <= region_radius)

    # Region triangles and their samples: distance to nearest bundle, owner, area.
    rt = np.flatnonzero(region[tris].any(1))
    rtri = tris[rt]
    bary = sample_pattern(subdivisions)
    limit_site = float(dist[rtri.ravel()][np.isfinite(dist[rtri.ravel()])].max()) * 1.5 + 1e-6
    dsite = dijkstra(g2, indices=site_nodes, limit=limit_site)[:, :n_v]  # (M, V), inf beyond
    cand = owner[rtri]  # (T, 3) candidate owners: those of the corners
    r_s = np.full((len(rt), len(bary)), np.inf)
    owner_s = np.zeros((len(rt), len(bary)), np.int64)
    for c in range(3):
        j = cand[:, c]
        ok = j >= 0
        dj = np.where(ok[:, None], dsite[np.maximum(j, 0)[:, None], rtri], np.inf)  # (T, 3)
        ds = dj @ bary.T  # (T, n)
        better = ds < r_s
        r_s = np.where(better, ds, r_s)
        owner_s = np.where(better, j[:, None], owner_s)
    if tri_uv is not None:
        uvt = uvs[tri_uv[rt]]
        e1, e2 = uvt[:, 1] - uvt[:, 0], uvt[:, 2] - uvt[:, 0]
        area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) * scale**2
    else:
        p = vertices[rtri]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    area_s = np.repeat(area[:, None] / len(bary), len(bary), axis=1)
    area_s[~np.isfinite(r_s)] = 0.0
    r_s[~np.isfinite(r_s)] = -1.0  # never stolen

    # Stolen areas for every region vertex. A sample can only be stolen from within r_max.
    queries = np.flatnonzero(region)
    r_max = float(r_s.max())
    w_region = np.zeros((len(queries), m))
    for a in range(0, len(queries), chunk):
        qs = queries[a:a + chunk]
        dq = dijkstra(graph, indices=qs, limit=r_max)
        out = np.zeros((len(qs), m))
        _steal(dq, rtri.astype(np.int64), bary, r_s, owner_s, area_s, r_max, m, out)
        w_region[a:a + len(qs)] = out
    tot = w_region.sum(1)
    empty = tot <= 0
    # A query at (or next to) a bundle steals nothing measurable: it belongs to that bundle's cell.
    w_region[empty] = 0.0
    w_region[empty, owner[queries[empty]]] = 1.0
    w_region /= w_region.sum(1, keepdims=True)

    w = np.zeros((n_v, m), np.float32)
    w[queries] = w_region
    # Exact interpolation: each bundle's triangle corners (with non-zero barycentric weight) are its own.
    claimed = np.full(n_v, -1)
    claim_w = np.zeros(n_v)
    conflicts = []
    for i in range(m):
        for c in range(3):
            v = st[i, c]
            if site_bary[i, c] <= 0:
                continue
            if claimed[v] >= 0 and claimed[v] != i:
                conflicts.append(f"vertex {v} is in the triangles of bundles {claimed[v]} and {i}")
                if site_bary[i, c] <= claim_w[v]:
                    continue
            claimed[v], claim_w[v] = i, site_bary[i, c]
    cv = np.flatnonzero(claimed >= 0)
    w[cv] = 0.0
    w[cv, claimed[cv]] = 1.0
    region[cv] = True

    outside = np.flatnonzero(~region)
    if outside.size:
        inside = np.flatnonzero(region)
        _, nearest = cKDTree(vertices[inside]).query(vertices[outside])
        w[outside] = w[inside[nearest]]

    # Natural neighbours: bundles whose Voronoi cells share a graph edge.
    gc = graph.tocoo()
    oa, ob = owner[gc.row], owner[gc.col]
    keep = (oa >= 0) & (ob >= 0) & (oa != ob) & region[gc.row] & region[gc.col]
    pairs = np.unique(np.stack([oa[keep], ob[keep]], 1), axis=0)
    neighbours = [pairs[pairs[:, 0] == i, 1] for i in range(m)]
    return NaturalNeighbours(
        weights=sp.csr_matrix(w), neighbours=neighbours, distance=dist, owner=owner, region=region,
        uv_scale=scale, conflicts=conflicts,
    )
