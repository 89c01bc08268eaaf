"""A reconstructed frame against a scan of the same moment, whatever the scan's topology.

Distances are point-to-surface, both ways, measured at vertices: every reconstruction vertex to the closest point
of the scan's triangles, and every scan vertex to the closest point of the reconstruction's triangles (not to the
nearest vertex). The reconstruction's vertices are measured by the project's
:class:`~lgi.dataset.mesh.ClosestPointQuery` on the scan (exact, signed by the closest triangle's normal); the
scan's vertices by pymeshlab's ``compute_scalar_by_distance_from_another_mesh_per_vertex``, a block at a time
(neither holds a dense scan's triangles twice). Where the closest point is (its triangle and barycentric
coordinates) decides coverage:

* a reconstruction vertex is **covered** when the closest scan point is not on the scan's border (an open edge:
  the scan's outline or one of its holes) and lies within the gate; elsewhere the scan says nothing about it;
* a scan vertex is **inside** when the closest reconstruction point is not on the border of the measured region
  (the mesh's outline, its eye and mouth openings, the edge of ``--region``) and lies within the gate; the others
  (hair, shoulders, the back of the head) are **outside**.

The statistics (RMS, 95th percentile, maximum) are over covered vertices and inside scan points, each vertex
counting once (no area weighting); the Hausdorff distance is the larger of the two maxima. Face interiors are not
sampled, so between vertices a surface can stray from the other by up to about the sagitta of its edges.

Everything here is in cm, the library's unit; reports convert to mm (:mod:`lgi.units`).
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lgi.dataset.mesh import triangle_normals
from lgi.errors import InputError
from lgi.units import MM_PER_CM, check_units

if TYPE_CHECKING:
    from lgi.dataset.mesh import ClosestPointQuery

#: Scan formats read by pymeshlab (OBJ goes through the project's reader, which names the file and line).
PYMESHLAB_FORMATS = (".ply", ".stl", ".off")


@dataclass
class Scan:
    """A scan as compared: a triangle mesh in cm.

    Attributes
    ----------
    path : str
        The file it was read from.
    vertices : (N, 3) float64, cm
        The vertices some triangle uses (unreferenced points of the file dropped).
    triangles : (T, 3) int64
        Indices into ``vertices`` (polygons fan-triangulated).
    file_index : (N,) int64
        Each vertex's 0-based index in the file.
    """

    path: str
    vertices: np.ndarray
    triangles: np.ndarray
    file_index: np.ndarray


def read_scan(path: str | os.PathLike[str], units: str = "cm") -> Scan:
    """Read a scan mesh (OBJ with the project's reader; PLY, STL, OFF with pymeshlab) and convert it to cm.

    Raises
    ------
    InputError
        Naming the file: missing, unreadable, of another format, without faces, with non-finite coordinates.
    """
    path = Path(path)
    to_cm = check_units(units, "--units")
    if not path.is_file():
        raise InputError("scan not found", path=path)
    suffix = path.suffix.lower()
    if suffix == ".obj":
        from lgi.dataset.mesh import triangulate
        from lgi.io.obj import read_obj

        # The project's reader: it keeps polygons and names the line of anything malformed.
        mesh = read_obj(path)
        vertices = mesh.vertices
        triangles = triangulate(mesh.face_vertices, mesh.face_offsets)[0].astype(np.int64)
    elif suffix in PYMESHLAB_FORMATS:
        import pymeshlab

        from lgi.io.meshfiles import check_mesh_file

        # pymeshlab drops non-finite vertices without a word and allocates what a header declares.
        check_mesh_file(path)
        triangle_ply = _triangle_ply(path) if suffix == ".ply" else None
        if triangle_ply is not None:
            vertices, triangles = triangle_ply
            return _scan(path, vertices, triangles, to_cm)
        ms = pymeshlab.MeshSet()
        try:
            ms.load_new_mesh(str(path))
        except pymeshlab.PyMeshLabException as exc:
            raise InputError(f"cannot read the scan: {str(exc).strip().splitlines()[-1]}", path=path) from None
        m = ms.current_mesh()
        vertices = np.asarray(m.vertex_matrix(), np.float64)
        triangles = np.asarray(m.face_matrix(), np.int64).reshape(-1, 3)
    else:
        raise InputError(f"unsupported scan format {suffix or '(none)'}: use .obj, .ply, .stl or .off", path=path)
    return _scan(path, vertices, triangles, to_cm)


def _triangle_ply(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The vertices (V, 3) float64 and triangles (T, 3) int64 of a binary PLY of triangles, read by plyfile
    through a memory map; None for any other PLY (text, polygons, other elements), which pymeshlab reads. A
    5-million-vertex scan took pymeshlab 1 GB of its own before lgi's arrays; this way it takes those alone."""
    import plyfile

    try:
        with open(path, "rb") as f:
            data = plyfile.PlyData.read(f, mmap="c", known_list_len={"face": {"vertex_indices": 3,
                                                                               "vertex_index": 3}})
            names = [e.name for e in data.elements]
            if data.text or "vertex" not in names or "face" not in names:
                return None
            v, f_ = data["vertex"].data, data["face"].data
            lists = [n for n in f_.dtype.names if n in ("vertex_indices", "vertex_index")]
            if not lists or not all(a in v.dtype.names for a in "xyz"):
                return None
            vertices = np.empty((len(v), 3))
            for k, a in enumerate("xyz"):
                vertices[:, k] = v[a]
            triangles = np.asarray(f_[lists[0]], np.int64).reshape(-1, 3)
    except (plyfile.PlyParseError, ValueError, KeyError, TypeError):
        return None  # not one plyfile maps as triangles: pymeshlab's general reader (and its messages)
    bad = np.flatnonzero((triangles < 0).any(axis=1) | (triangles >= len(vertices)).any(axis=1))
    if bad.size:
        raise InputError(f"face {int(bad[0])} (0-based) refers to a vertex the file does not have (it has "
                         f"{len(vertices):,}): {triangles[bad[0]].tolist()}", path=path)
    return vertices, triangles


def _scan(path: Path, vertices: np.ndarray, triangles: np.ndarray, to_cm: float) -> Scan:
    """The scan of ``vertices`` (V, 3) and ``triangles`` (T, 3) as read (file units), checked, in cm, without
    the vertices no triangle uses."""
    if len(triangles) == 0:
        raise InputError("the scan has no faces (a point cloud cannot be compared as a surface)", path=path)
    if not np.all(np.isfinite(vertices)):
        raise InputError("the scan has non-finite vertex coordinates", path=path)
    mask = np.zeros(len(vertices), bool)
    mask[triangles] = True
    used = np.flatnonzero(mask)
    if len(used) == len(vertices):  # a scanner's mesh: every vertex in a face (no copies of its millions)
        vertices *= to_cm
        return Scan(str(path), vertices, triangles, used)
    remap = np.full(len(vertices), -1, np.int64)
    remap[used] = np.arange(len(used))
    return Scan(str(path), vertices[used] * to_cm, remap[triangles], used)


def _meshset(*meshes: tuple[np.ndarray, np.ndarray]):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    for v, t in meshes:
        ms.add_mesh(pymeshlab.Mesh(np.ascontiguousarray(v, np.float64), np.ascontiguousarray(t, np.int32)))
    return ms


#: Points measured by pymeshlab at a time (:func:`point_to_surface`): its own copy of them is a few hundred bytes
#: each.
POINTS_BLOCK = 1 << 19


def point_to_surface(points: np.ndarray, surface: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Signed distance from points to the surface of a mesh, by pymeshlab, a block of points at a time.

    Parameters
    ----------
    points : (N, 3) float, cm
        The points measured (a dense scan's millions of vertices: pymeshlab holds a block of them at once).
    surface : ((M, 3) float, cm; (S, 3) int)
        The surface measured against.

    Returns
    -------
    (N,) float64, cm
        Distance to the closest point of ``surface``'s triangles, positive in front of it (along its face
        normals), negative behind.
    """
    import pymeshlab

    points = np.asarray(points, np.float64)
    sv = np.asarray(surface[0], np.float64)
    lo, hi = np.minimum(points.min(0), sv.min(0)), np.maximum(points.max(0), sv.max(0))
    # Beyond maxdist pymeshlab writes a sentinel instead of the distance: make it unreachable.
    far = pymeshlab.PureValue(4.0 * float(np.linalg.norm(hi - lo)) + 1.0)
    ms = _meshset(surface)
    out = np.empty(len(points))
    for start in range(0, len(points), POINTS_BLOCK):
        ms.add_mesh(pymeshlab.Mesh(np.ascontiguousarray(points[start:start + POINTS_BLOCK])))
        block = ms.current_mesh_id()  # a deleted mesh's id is not given again
        ms.compute_scalar_by_distance_from_another_mesh_per_vertex(measuremesh=block, refmesh=0, signeddist=True,
                                                                   maxdist=far)
        out[start:start + POINTS_BLOCK] = ms.mesh(block).vertex_scalar_array()
        ms.delete_current_mesh()
    return out


def signed_distances(points: np.ndarray, surface: tuple[np.ndarray, np.ndarray], query: ClosestPointQuery
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact signed distances from points to a mesh through its closest-point ``query`` (for a dense scan, whose
    own triangles would cost pymeshlab gigabytes).

    Returns
    -------
    signed : (N,) float64, cm
        Positive in front of the closest triangle (along its normal), negative behind, as :func:`point_to_surface`.
    triangle : (N,) int64
    bary : (N, 3) float64
        The closest point, as ``ClosestPointQuery.query`` gives it.
    """
    p = np.asarray(points, np.float64)
    tri, bary, dist = query.query(p)
    v, t = np.asarray(surface[0], np.float64), np.asarray(surface[1], np.int64)[tri]
    closest = np.einsum("nk,nkd->nd", bary, v[t])
    behind = np.einsum("nd,nd->n", p - closest, triangle_normals(v, t)) < 0
    return np.where(behind, -dist, dist), tri, bary


def edge_keys(a: np.ndarray, b: np.ndarray, n_vertices: int) -> np.ndarray:
    """(N,) int64: the edge of vertices ``a`` and ``b`` (either order) as one number, ``min * n + max``."""
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    return np.minimum(a, b) * n_vertices + np.maximum(a, b)


#: Triangles whose edges are looked at together by :func:`closest_on_border`.
BORDER_BLOCK = 1 << 20


def closest_on_border(triangles: np.ndarray, n_vertices: int, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(N,) bool: whether each closest point (triangle ``tri``, barycentric ``bary`` (N, 3)) lies on the mesh's
    border: at a vertex of an open edge (an edge of exactly one triangle), or on an open edge (the barycentric
    weight of the opposite corner is zero).

    Only the edges that touch the points' closest vertices and edges are counted, a block of triangles at a
    time: the memory is that of the answer, not of a scan's tens of millions of edges."""
    t_all = np.asarray(triangles, np.int64)
    t = t_all[tri]
    # closest_point_on_triangles gives exact 0 and 1 in its edge and vertex regions; 1e-9 absorbs the interior
    # formula's rounding next to them.
    at_vertex = np.full(len(tri), -1, np.int64)
    for k in range(3):
        hit = (at_vertex < 0) & (bary[:, k] >= 1 - 1e-9)
        at_vertex[hit] = t[hit, k]
    on_edge = np.full(len(tri), -1, np.int64)
    for k in range(3):
        hit = (at_vertex < 0) & (on_edge < 0) & (bary[:, k] <= 1e-9)
        on_edge[hit] = edge_keys(t[hit, (k + 1) % 3], t[hit, (k + 2) % 3], n_vertices)
    vertices = np.unique(at_vertex[at_vertex >= 0])
    edges = np.unique(on_edge[on_edge >= 0])
    touched = np.zeros(n_vertices, bool)
    touched[vertices] = True
    seen = []
    for lo in range(0, len(t_all), BORDER_BLOCK):
        block = t_all[lo:lo + BORDER_BLOCK]
        for i, j in ((0, 1), (1, 2), (2, 0)):
            a, b = block[:, i], block[:, j]
            keys = edge_keys(a, b, n_vertices)
            seen.append(keys[touched[a] | touched[b] | np.isin(keys, edges)])
    keys, count = np.unique(np.concatenate(seen) if seen else np.zeros(0, np.int64), return_counts=True)
    open_edges = keys[count == 1]
    border_vertex = np.zeros(n_vertices, bool)
    border_vertex[open_edges // n_vertices] = True
    border_vertex[open_edges % n_vertices] = True
    out = np.zeros(len(tri), bool)
    v = at_vertex >= 0
    out[v] = border_vertex[at_vertex[v]]
    e = on_edge >= 0
    out[e] = np.isin(on_edge[e], open_edges)
    return out


def submesh(triangles: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The triangles whose three vertices are all in ``keep`` (V,) bool, re-indexed onto their vertices.

    Returns
    -------
    vertices : (K,) int64
        The original index of each vertex of the submesh.
    triangles : (S, 3) int64
    """
    t = np.asarray(triangles, np.int64)
    t = t[np.all(keep[t], axis=1)]
    used = np.unique(t)
    remap = np.full(len(keep), -1, np.int64)
    remap[used] = np.arange(len(used))
    return used, remap[t]


def _rotation(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (Rodrigues)."""
    theta = float(np.linalg.norm(w))
    if theta < 1e-15:
        return np.eye(3)
    k = w / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx


def rigid_icp(points: np.ndarray, surface: tuple[np.ndarray, np.ndarray], gate: float, iterations: int = 30,
              tol: float = 1e-4, max_points: int = 10000) -> tuple[np.ndarray, int]:
    """Rigid transform moving ``points`` onto ``surface`` (point-to-plane ICP over the inside points).

    pymeshlab's ``compute_matrix_by_icp_between_meshes`` was tried first: on a remeshed face turned by 3.9 deg and
    moved 4.4 mm it stopped 1.7 mm off after 200 iterations (it samples a few thousand points and drops a quarter of the
    pairs) and prints every iteration on stdout, so this is a plain Gauss-Newton point-to-plane loop instead.

    Parameters
    ----------
    points : (N, 3) float, cm
        The scan's vertices.
    surface : ((V, 3) float cm, (T, 3) int)
        The reconstruction's measured region.
    gate : float, cm
        Pairs farther apart, or whose closest point is on the surface's border, are left out of each step.
    iterations, tol
        At most ``iterations`` steps; stop when a step moves no point by more than ``tol`` cm. Not much less than
        1e-4 cm (0.001 mm): points entering and leaving the inside set near the borders keep the steps at about
        that size.
    max_points : int
        A dense scan is thinned to about this many points (every k-th): six parameters need no more.

    Returns
    -------
    transform : (4, 4) float64
        ``x -> R x + t`` in homogeneous form, cm.
    steps : int
    """
    from lgi.dataset.mesh import ClosestPointQuery, triangle_normals

    v, t = np.asarray(surface[0], np.float64), np.asarray(surface[1], np.int64)
    q = ClosestPointQuery(v, t)
    normals = triangle_normals(v, t)
    p0 = np.asarray(points, np.float64)
    p0 = p0[::max(1, len(p0) // max_points)]
    centre = p0.mean(axis=0)
    rot, trans = np.eye(3), np.zeros(3)
    radius = float(np.linalg.norm(p0 - centre, axis=1).max()) + 1e-12
    steps = 0
    for steps in range(1, iterations + 1):  # noqa: B007 - the count is returned
        p = (p0 - centre) @ rot.T + centre + trans
        tri, bary, dist = q.query(p)
        ok = (dist <= gate) & ~closest_on_border(t, len(v), tri, bary)
        if ok.sum() < 6:
            raise InputError(f"rigid alignment: only {int(ok.sum())} scan points lie within the gate of the "
                             "reconstruction: the scan is not roughly in the reconstruction's frame")
        c = np.einsum("nk,nkd->nd", bary[ok], v[t[tri[ok]]])
        n = normals[tri[ok]]
        r = p[ok] - centre
        a = np.hstack([np.cross(r, n), n])
        b = np.einsum("nd,nd->n", c - p[ok], n)
        # The rotation part is scaled by the points' radius so both halves of the step are in cm.
        a[:, :3] /= radius
        x = np.linalg.lstsq(a, b, rcond=None)[0]
        w, dt = x[:3] / radius, x[3:]
        step_rot = _rotation(w)
        rot = step_rot @ rot
        trans = step_rot @ trans + dt
        if np.linalg.norm(w) * radius + np.linalg.norm(dt) < tol:
            break
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = centre + trans - rot @ centre
    return out, steps


def apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3): ``points`` (N, 3) moved by the homogeneous ``transform`` (4, 4)."""
    return np.asarray(points, np.float64) @ transform[:3, :3].T + transform[:3, 3]


@dataclass
class Comparison:
    """One frame against one scan (arrays in cm; :func:`stats_mm` reports mm).

    Attributes
    ----------
    distance : (V,) float64, cm
        Each reconstruction vertex's distance to the scan surface (NaN outside the region).
    signed : (V,) float64, cm
        The same, positive in front of the scan (along its normals).
    covered : (V,) bool
        Region vertices the scan covers (see the module docstring).
    region : (V,) bool
    scan_distance : (N,) float64, cm
        Each scan vertex's distance to the region of the reconstruction.
    inside : (N,) bool
        Scan vertices facing the region (not outside).
    transform : (4, 4) float64
        Applied to the scan before measuring (identity without alignment), cm.
    icp_steps : int
    """

    distance: np.ndarray
    signed: np.ndarray
    covered: np.ndarray
    region: np.ndarray
    scan_distance: np.ndarray
    inside: np.ndarray
    transform: np.ndarray
    icp_steps: int = 0


def compare_frame(vertices: np.ndarray, triangles: np.ndarray, scan: Scan, region: np.ndarray | None = None,
                  gate: float = 1.0, align: str = "none") -> Comparison:
    """Distances between a reconstructed frame and a scan, both ways, with coverage.

    Parameters
    ----------
    vertices : (V, 3) float, cm
        The reconstructed frame.
    triangles : (T, 3) int
        Its triangulation.
    scan : Scan
    region : (V,) bool, optional
        The vertices to measure (default all).
    gate : float, cm
        Farther pairs count as not covered / outside.
    align : "none" or "rigid"
        ``rigid``: the scan is first moved onto the reconstruction by :func:`rigid_icp`.
    """
    from lgi.dataset.mesh import ClosestPointQuery

    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    region = np.ones(len(v), bool) if region is None else np.asarray(region, bool)
    keep, sub_t = submesh(t, region)
    if len(sub_t) == 0:
        raise InputError("the region holds no whole triangle of the mesh: nothing to measure")
    sub_v = v[keep]
    transform, steps = np.eye(4), 0
    if align == "rigid":
        transform, steps = rigid_icp(scan.vertices, (sub_v, sub_t), gate)
    elif align != "none":
        raise InputError(f"--align must be none or rigid, not {align!r}")
    s_v = apply(transform, scan.vertices)
    s_t = scan.triangles

    # Reconstruction -> scan, at the region's vertices: exact, through the scan's closest-point query.
    measured = np.flatnonzero(region)
    signed = np.full(len(v), np.nan)
    signed[measured], tri, bary = signed_distances(v[measured], (s_v, s_t), ClosestPointQuery(s_v, s_t))
    distance = np.abs(signed)
    near = distance[measured] <= gate
    covered = np.zeros(len(v), bool)
    covered[measured[near]] = ~closest_on_border(s_t, len(s_v), tri[near], bary[near])

    # Scan -> the region of the reconstruction. Which triangle is closest matters only within the gate (whether
    # that point is on the region's border): a point far from the surface needs thousands of candidate triangles
    # to be sure of it, and most of a dense scan can be far from a face's region.
    scan_distance = np.abs(point_to_surface(s_v, (sub_v, sub_t)))
    near = np.flatnonzero(scan_distance <= gate)
    tri, bary, _ = ClosestPointQuery(sub_v, sub_t).query(s_v[near])
    inside = np.zeros(len(s_v), bool)
    inside[near] = ~closest_on_border(sub_t, len(sub_v), tri, bary)
    return Comparison(distance, signed, covered, region, scan_distance, inside, transform, steps)


def stats_mm(distance_cm: np.ndarray) -> dict[str, float]:
    """RMS, 95th percentile and maximum (mm) of distances in cm (NaN for none)."""
    d = np.asarray(distance_cm, np.float64) * MM_PER_CM
    if d.size == 0:
        return {"rms_mm": float("nan"), "p95_mm": float("nan"), "max_mm": float("nan")}
    return {"rms_mm": float(np.sqrt(np.mean(d**2))), "p95_mm": float(np.percentile(d, 95)),
            "max_mm": float(d.max())}


def rotation_deg(transform: np.ndarray) -> float:
    """The rotation angle (degrees) of a homogeneous rigid transform."""
    c = (np.trace(transform[:3, :3]) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def remeshed_scan(vertices: np.ndarray, triangles: np.ndarray, edge: float,
                  hole: tuple[float, float, float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A scan of a known surface, for tests and benchmarks: the surface remeshed by pymeshlab (another topology)
    with a rectangular hole cut out.

    pymeshlab's ``meshing_isotropic_explicit_remeshing`` (6 iterations, its surface-distance check at 0.05 mm)
    reprojects every new vertex onto the original surface, so the scan's vertices lie on it and the original's
    vertices are off the scan only by the chords of the new triangles (measure that with
    :class:`~lgi.dataset.mesh.ClosestPointQuery` for a bound).

    Parameters
    ----------
    vertices : (V, 3) float, cm; triangles : (T, 3) int
        The surface.
    edge : float, cm
        Target edge length of the remeshing.
    hole : (cx, cy, hx, hy), cm, optional
        Faces whose centroid has ``|x - cx| < hx`` and ``|y - cy| < hy`` are deleted (a hole in front of the face
        when the rectangle lies on it, e.g. the forehead).

    Returns
    -------
    vertices : (N, 3) float64, cm
    triangles : (S, 3) int64
    """
    import pymeshlab

    ms = _meshset((vertices, triangles))
    ms.meshing_isotropic_explicit_remeshing(iterations=6, targetlen=pymeshlab.PureValue(edge),
                                            maxsurfdist=pymeshlab.PureValue(0.005))
    w = np.asarray(ms.current_mesh().vertex_matrix(), np.float64)
    g = np.asarray(ms.current_mesh().face_matrix(), np.int64)
    if hole is not None:
        c = w[g].mean(axis=1)
        cx, cy, hx, hy = hole
        g = g[~((np.abs(c[:, 0] - cx) < hx) & (np.abs(c[:, 1] - cy) < hy))]
    used = np.unique(g)
    remap = np.full(len(w), -1, np.int64)
    remap[used] = np.arange(len(used))
    return w[used], remap[g]


def subdivided(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A denser scan of the same surface, for tests and benchmarks: one midpoint subdivision (a vertex at each
    edge's middle, each triangle split in four; the vertex count about four times).

    Parameters
    ----------
    vertices : (V, 3) float; triangles : (T, 3) int

    Returns
    -------
    vertices : (V + E, 3) float64
    triangles : (4 T, 3) int64
    """
    t = np.asarray(triangles, np.int64)
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    uniq, inverse = np.unique(e, axis=0, return_inverse=True)
    mid = (len(vertices) + inverse.reshape(3, -1)).T  # (T, 3): the middles of edges 01, 12, 20
    v = np.concatenate([vertices, 0.5 * (vertices[uniq[:, 0]] + vertices[uniq[:, 1]])])
    a, b, c = t.T
    ab, bc, ca = mid.T
    return v, np.concatenate([np.stack(x, 1) for x in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])


def write_ply(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    """Write a scan as a binary little-endian PLY, as scanners do (float32 vertices (V, 3), uchar-counted int32
    triangles (T, 3)), for tests and benchmarks."""
    face = np.zeros(len(triangles), np.dtype([("n", "u1"), ("v", "<i4", 3)]))
    face["n"], face["v"] = 3, triangles
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write((f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\nproperty float x\n"
                 f"property float y\nproperty float z\nelement face {len(triangles)}\n"
                 "property list uchar int vertex_indices\nend_header\n").encode())
        f.write(np.ascontiguousarray(vertices, "<f4").tobytes())
        f.write(face.tobytes())


def frame_fingerprint(vertices: np.ndarray) -> str:
    """SHA-256 of a frame's vertices as ``meshes.npz`` stores them (float32, little-endian): ``lgi review --scans``
    checks with it that the distances were measured on the frames it shows."""
    v = np.ascontiguousarray(vertices, np.dtype("<f4"))
    return hashlib.sha256(v.tobytes()).hexdigest()
