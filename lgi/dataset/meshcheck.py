"""Checks of a dataset's mesh on import, with pymeshlab's topological measures: what the index cannot use is
refused, with the count and where.

The OBJ itself is read by the project's reader (:func:`lgi.io.obj.read_obj`), not pymeshlab's: it keeps quads,
UV seams and materials as they are (pymeshlab triangulates and splits seam vertices, which would change the
vertex order every shape file must share), and it names the file and line of anything malformed. The checks run
on its canonical fan triangulation, handed to pymeshlab as arrays, so vertex and face indices in the messages are
the file's own.

Refused (each would break the index, whose smooth interpolation divides by vertex areas and cotangents and walks
the mesh's edges):

* **non-manifold edges** (an edge of three or more faces) and **non-manifold vertices** (faces meeting only at
  a vertex): pymeshlab's ``get_topological_measures`` counts them, its selection filters say where;
* **flipped faces**: a face whose winding disagrees with its neighbours'. pymeshlab's
  ``meshing_re_orient_faces_coherently`` re-orients a copy; in each connected piece the faces it turned that are
  the minority are the flipped ones;
* **degenerate faces**: zero area (repeated corners, collinear corners): a vertex area or cotangent of 0;
* **unreferenced vertices**: no face uses them, so they have no area;
* **isolated pieces**: a piece of fewer than :data:`MIN_PIECE_TRIANGLES` triangles apart from the main mesh:
  debris of an edit (a stray or duplicated face), never a modelled part (ICT FaceKit has 56 pieces; the smallest
  have 30 triangles).

Counted and reported (not refused): pieces, boundary loops (holes and outlines), the genus.
"""

from __future__ import annotations

import os
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np

from lgi.dataset.mesh import triangulate
from lgi.errors import InputError
from lgi.io.obj import PolyMesh

#: Pieces with fewer triangles than this, besides the largest, are refused as debris.
MIN_PIECE_TRIANGLES = 8
#: A triangle whose area is at most this fraction of its longest edge squared is degenerate: its height is within
#: 2e-6 of that edge, collinear up to the rounding of a file's six decimals (ICT's thinnest triangle has 0.0145).
DEGENERATE_AREA = 1e-6
#: How many indices a message lists of each problem.
SHOWN = 6


def _pieces(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """(T,) int: the connected piece (through shared vertices) of each triangle."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    t = np.asarray(triangles, np.int64)
    graph = sp.coo_matrix((np.ones(t.size), (t.ravel(), np.roll(t, 1, axis=1).ravel())), shape=(n_vertices,) * 2)
    return connected_components(graph, directed=False)[1][t[:, 0]]


def _same_winding(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(T,) bool: triangles ``b`` (T, 3) are cyclic rotations of ``a`` (the same winding)."""
    return np.any([np.all(np.roll(b, k, axis=1) == a, axis=1) for k in range(3)], axis=0)


def _face_lines(path: Path) -> list[int]:
    """1-based line number of every ``f`` line of an OBJ file, in order."""
    with open(path, "rb") as fh:
        return [i + 1 for i, ln in enumerate(fh) if ln[:2] == b"f "]


def _list(indices: np.ndarray) -> str:
    idx = [int(i) for i in np.unique(indices)]
    return ", ".join(map(str, idx[:SHOWN])) + (f" and {len(idx) - SHOWN} more" if len(idx) > SHOWN else "")


def check_mesh(mesh: PolyMesh, path: str | os.PathLike[str]) -> dict[str, Any]:
    """Check an imported mesh; returns its measures, or raises :class:`InputError` naming every problem.

    Parameters
    ----------
    mesh : PolyMesh
        As read from ``path`` (positions in any unit).
    path
        The OBJ it came from (messages give its face lines).

    Returns
    -------
    dict
        ``pieces``, ``boundary_loops``, ``boundary_edges``, ``genus`` (pymeshlab's, -1 when undefined),
        ``vertices``, ``faces``, ``triangles`` and ``checked_by``.
    """
    import pymeshlab

    path = Path(path)
    tris, tri_face = triangulate(mesh.face_vertices, mesh.face_offsets)
    tris = tris.astype(np.int64)
    v = np.asarray(mesh.vertices, np.float64)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(v, tris.astype(np.int32)))
    topo = ms.get_topological_measures()
    problems: list[tuple[str, np.ndarray | None, str]] = []  # (what, polygons at fault, vertices text)

    if topo["non_two_manifold_edges"]:
        ms.compute_selection_by_non_manifold_edges_per_face()
        faces = tri_face[np.flatnonzero(ms.current_mesh().face_selection_array())]
        e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
        uniq, count = np.unique(e, axis=0, return_counts=True)
        bad = uniq[count > 2]
        edges = ", ".join(f"{a}-{b}" for a, b in bad[:SHOWN].tolist()) + (
            f" and {len(bad) - SHOWN} more" if len(bad) > SHOWN else "")
        problems.append((f"{topo['non_two_manifold_edges']} non-manifold edge(s) (three or more faces on one edge)",
                         faces, f"vertices {edges}"))
        ms.set_selection_none()
    if topo["non_two_manifold_vertices"]:
        ms.compute_selection_by_non_manifold_per_vertex()
        verts = np.flatnonzero(ms.current_mesh().vertex_selection_array())
        problems.append((f"{topo['non_two_manifold_vertices']} non-manifold vertex(es) (faces meeting only at a "
                         "vertex)", None, f"vertices {_list(verts)}"))
        ms.set_selection_none()
    if topo["unreferenced_vertices"]:
        unused = np.setdiff1d(np.arange(len(v)), tris.ravel())
        problems.append((f"{len(unused)} unreferenced vertex(es) (no face uses them)", None,
                         f"vertices {_list(unused)}"))
    longest = np.linalg.norm(v[tris] - v[np.roll(tris, 1, axis=1)], axis=2).max(axis=1)
    area = 0.5 * np.linalg.norm(np.cross(v[tris[:, 1]] - v[tris[:, 0]], v[tris[:, 2]] - v[tris[:, 0]]), axis=1)
    degenerate = (area <= DEGENERATE_AREA * longest**2) | (tris[:, 0] == tris[:, 1]) | (tris[:, 1] == tris[:, 2]) \
        | (tris[:, 0] == tris[:, 2])
    if degenerate.any():
        faces = np.unique(tri_face[degenerate])
        problems.append((f"{len(faces)} degenerate face(s) (zero area)", faces, ""))
    piece = _pieces(tris, len(v))
    sizes = np.bincount(piece)
    small = np.flatnonzero((sizes > 0) & (sizes < MIN_PIECE_TRIANGLES))
    small = small[small != np.argmax(sizes)]
    if small.size:
        faces = np.unique(tri_face[np.isin(piece, small)])
        problems.append((f"{len(small)} isolated piece(s) of fewer than {MIN_PIECE_TRIANGLES} triangles (debris "
                         "apart from the mesh)", faces, ""))
    if not (topo["non_two_manifold_edges"] or topo["non_two_manifold_vertices"]):
        # Orientation is only defined on a manifold (pymeshlab refuses to re-orient otherwise).
        ms.meshing_re_orient_faces_coherently()
        turned = ~_same_winding(tris, np.asarray(ms.current_mesh().face_matrix(), np.int64))
        flipped = np.zeros(len(tris), bool)
        for p in np.unique(piece[turned]):
            members = piece == p
            # The re-orientation follows each piece's first face: the minority is what disagrees.
            minority = turned if turned[members].sum() <= members.sum() / 2 else ~turned
            flipped |= members & minority
        if flipped.any():
            faces = np.unique(tri_face[flipped])
            problems.append((f"{len(faces)} flipped face(s) (winding opposite to the neighbours')", faces, ""))
    if problems:
        lines = _face_lines(path)
        parts = []
        for what, faces, verts in problems:
            where = []
            if faces is not None and len(faces):
                first = int(faces[0])
                line = f", the first on line {lines[first]}" if first < len(lines) else ""
                where.append(f"faces {_list(faces)} (0-based, in file order{line})")
            if verts:
                where.append(verts)
            parts.append(f"{what}: {'; '.join(where)}")
        raise InputError("the mesh cannot be indexed: " + "; ".join(parts) + " (fix it in a modelling tool, e.g. "
                         "MeshLab's Cleaning and Repairing filters, keeping the vertex order every shape shares)",
                         path=path)
    return {"vertices": int(len(v)), "faces": mesh.n_faces, "triangles": int(len(tris)),
            "pieces": int(topo["connected_components_number"]), "boundary_loops": int(topo["number_holes"]),
            "boundary_edges": int(topo["boundary_edges"]), "genus": int(topo["genus"]),
            "checked_by": f"pymeshlab {_version()}"}


def _version() -> str:
    try:
        return version("pymeshlab")
    except PackageNotFoundError:
        return "?"


def check_report(m: dict[str, Any]) -> str:
    """One line saying what the checks found in an accepted mesh."""
    return (f"mesh checked ({m['checked_by']}): manifold, consistently oriented, no degenerate faces or unused "
            f"vertices; {m['pieces']} piece(s), {m['boundary_loops']} boundary loop(s) (holes and outlines)")
