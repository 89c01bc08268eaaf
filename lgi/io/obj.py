"""Wavefront OBJ reading and writing, polygons kept as given (quads stay quads).

The reader is written for many files of one topology: :func:`read_obj` parses a mesh completely
(positions, texture coordinates with their seams, polygons, materials) and :func:`read_obj_positions`
reads only the positions of a further file, checking that its polygon list is the same as a reference
mesh's. Both name the file and the line of anything malformed.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lgi.errors import InputError
from lgi.io.atomic import atomic_file


@dataclass
class PolyMesh:
    """A polygon mesh in flat (CSR-like) form.

    Attributes
    ----------
    vertices : (V, 3) float64
        Positions, in the file's units.
    face_vertices : (N,) int32
        Vertex index of every polygon corner, polygons one after another (0-based).
    face_offsets : (F + 1,) int64
        Polygon ``f`` has corners ``face_vertices[face_offsets[f]:face_offsets[f + 1]]``.
    uvs : (T, 2) float32 or None
        Texture coordinates. ``T`` may exceed ``V``: a vertex on a UV seam has one UV per side.
    face_uvs : (N,) int32 or None
        Texture-coordinate index of every polygon corner (same layout as ``face_vertices``).
    face_material : (F,) int16
        Index into ``materials`` of each polygon, -1 where no ``usemtl`` preceded it.
    materials : list of str
        Material names in order of first use.
    mtllib : str or None
        The material library the file referenced.
    """

    vertices: np.ndarray
    face_vertices: np.ndarray
    face_offsets: np.ndarray
    uvs: np.ndarray | None = None
    face_uvs: np.ndarray | None = None
    face_material: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int16))
    materials: list[str] = field(default_factory=list)
    mtllib: str | None = None

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.face_offsets.shape[0] - 1)

    def face_sizes(self) -> np.ndarray:
        """(F,) int64: number of corners of each polygon."""
        return np.diff(self.face_offsets)


def _lines(path: Path) -> list[bytes]:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read file: {exc.strerror}", path=path) from exc
    # OBJ files from Windows tools carry \r; strip it once here rather than per token.
    if b"\r" in data:
        data = data.replace(b"\r", b"")
    return data.split(b"\n")


def _parse_floats(path: Path, lines: list[bytes], numbers: list[int], key: bytes, width: int) -> np.ndarray:
    """Parse the first ``width`` numbers of each ``key`` line; locate the first bad line on failure."""
    rows = [lines[i][len(key):] for i in numbers]
    try:
        flat = np.array(b" ".join(rows).split(), dtype=np.float64)
        if flat.size == width * len(rows):
            return _checked(path, numbers, flat.reshape(-1, width))
    except ValueError:
        pass
    # Slow path: some line is malformed or carries extra values (vertex colours, w).
    out = np.empty((len(rows), width), np.float64)
    for k, (i, row) in enumerate(zip(numbers, rows, strict=True)):
        tok = row.split()
        if len(tok) < width:
            raise InputError(
                f"{key.decode().strip()!r} line has {len(tok)} values, expected {width}: "
                f"{lines[i].decode(errors='replace')!r}",
                path=path, line=i + 1,
            )
        try:
            out[k] = [float(t) for t in tok[:width]]
        except ValueError:
            raise InputError(
                f"non-numeric value in {key.decode().strip()!r} line: {lines[i].decode(errors='replace')!r}",
                path=path, line=i + 1,
            ) from None
    return _checked(path, numbers, out)


#: Coordinates beyond this are no face in any unit (and near float32's limit once scaled): refused.
MAX_COORDINATE = 1e7


def _checked(path: Path, numbers: list[int], out: np.ndarray) -> np.ndarray:
    """``out`` if every value is finite and within :data:`MAX_COORDINATE`, else the first bad line."""
    ok = np.all(np.isfinite(out) & (np.abs(out) <= MAX_COORDINATE), axis=1)
    if not ok.all():
        bad = int(np.flatnonzero(~ok)[0])
        what = "non-finite coordinate" if not np.all(np.isfinite(out[bad])) else \
            f"coordinate beyond {MAX_COORDINATE:g} (not a face in any unit)"
        raise InputError(what, path=path, line=numbers[bad] + 1)
    return out


def _resolve_index(tok: bytes, count: int, path: Path, line_no: int, what: str) -> int:
    try:
        idx = int(tok)
    except ValueError:
        raise InputError(f"non-numeric {what} index {tok.decode(errors='replace')!r} in face", path=path,
                         line=line_no) from None
    # OBJ indices are 1-based; negative ones count back from the last element defined so far.
    resolved = idx - 1 if idx > 0 else count + idx
    if idx == 0 or not 0 <= resolved < count:
        raise InputError(f"face {what} index {idx} out of range (the file defines {count} so far)",
                         path=path, line=line_no)
    return resolved


def read_obj(path: str | os.PathLike[str]) -> PolyMesh:
    """Read an OBJ file completely.

    Parameters
    ----------
    path
        The file. Supports ``v``, ``vt``, polygon ``f`` lines with ``v``, ``v/vt``, ``v//vn`` and
        ``v/vt/vn`` corners, negative (relative) indices, ``usemtl`` and ``mtllib``. Normals, groups
        and smoothing groups are ignored.

    Returns
    -------
    PolyMesh
        Vertex order exactly as in the file.

    Raises
    ------
    InputError
        Naming the file and line of a non-numeric value, a face index out of range, a face with fewer
        than 3 corners, a file with no vertices or faces, or faces mixing corners with and without UVs.
    """
    path = Path(path)
    lines = _lines(path)
    v_no: list[int] = []
    vt_no: list[int] = []
    fv: list[int] = []
    fuv: list[int] = []
    offsets = [0]
    fmat: list[int] = []
    materials: list[str] = []
    mat_index: dict[str, int] = {}
    current_mat = -1
    mtllib = None
    has_uv: bool | None = None
    for i, raw in enumerate(lines):
        head = raw[:2]
        if head == b"v ":
            v_no.append(i)
        elif head == b"vt":
            vt_no.append(i)
        elif head == b"f ":
            corners = raw.split()[1:]
            if len(corners) < 3:
                raise InputError(f"face has {len(corners)} corners, at least 3 needed", path=path, line=i + 1)
            for c in corners:
                parts = c.split(b"/")
                fv.append(_resolve_index(parts[0], len(v_no), path, i + 1, "vertex"))
                corner_uv = len(parts) > 1 and parts[1] != b""
                if has_uv is None:
                    has_uv = corner_uv
                elif has_uv != corner_uv:
                    raise InputError("faces mix corners with and without texture coordinates", path=path,
                                     line=i + 1)
                if corner_uv:
                    fuv.append(_resolve_index(parts[1], len(vt_no), path, i + 1, "texture-coordinate"))
            offsets.append(len(fv))
            fmat.append(current_mat)
        elif raw.startswith(b"usemtl"):
            name = raw[6:].strip().decode(errors="replace")
            if name not in mat_index:
                mat_index[name] = len(materials)
                materials.append(name)
            current_mat = mat_index[name]
        elif raw.startswith(b"mtllib"):
            mtllib = raw[6:].strip().decode(errors="replace")
    if not v_no:
        raise InputError("no vertices ('v' lines) in file", path=path)
    if len(offsets) == 1:
        raise InputError("no faces ('f' lines) in file", path=path)
    vertices = _parse_floats(path, lines, v_no, b"v ", 3)
    uvs = _parse_floats(path, lines, vt_no, b"vt", 2).astype(np.float32) if has_uv else None
    return PolyMesh(
        vertices=vertices,
        face_vertices=np.asarray(fv, np.int32),
        face_offsets=np.asarray(offsets, np.int64),
        uvs=uvs,
        face_uvs=np.asarray(fuv, np.int32) if has_uv else None,
        face_material=np.asarray(fmat, np.int16),
        materials=materials,
        mtllib=mtllib,
    )


def _face_block(lines: list[bytes]) -> list[bytes]:
    return [ln for ln in lines if ln[:2] == b"f "]


def read_obj_positions(path: str | os.PathLike[str], reference: PolyMesh) -> np.ndarray:
    """Read only the vertex positions of an OBJ that must share ``reference``'s topology.

    Parameters
    ----------
    path
        The file.
    reference
        The mesh whose vertex count and polygon list this file must repeat.

    Returns
    -------
    (V, 3) float64
        Positions in file order.

    Raises
    ------
    InputError
        On malformed lines (file and line), a different vertex count, or a different polygon list
        (naming the first polygon that differs and its line).
    """
    path = Path(path)
    lines = _lines(path)
    v_no = [i for i, ln in enumerate(lines) if ln[:2] == b"v "]
    if len(v_no) != reference.n_vertices:
        raise InputError(
            f"vertex count {len(v_no)} differs from the neutral's {reference.n_vertices}", path=path
        )
    positions = _parse_floats(path, lines, v_no, b"v ", 3)
    faces = _face_block(lines)
    if len(faces) != reference.n_faces:
        raise InputError(f"face count {len(faces)} differs from the neutral's {reference.n_faces}", path=path)
    ref_fv, ref_off = reference.face_vertices, reference.face_offsets
    # Fast check: compare the polygons' vertex indices as one array (formatting differences are fine).
    cand = _first_indices(faces)
    fast_ok = cand is not None and cand.shape == ref_fv.shape and np.array_equal(cand, ref_fv)
    if not fast_ok:
        face_line = [i for i, ln in enumerate(lines) if ln[:2] == b"f "]
        for f, (i, ln) in enumerate(zip(face_line, faces, strict=True)):
            corners = ln.split()[1:]
            got = [_resolve_index(c.split(b"/")[0], reference.n_vertices, path, i + 1, "vertex") for c in corners]
            want = ref_fv[ref_off[f]:ref_off[f + 1]].tolist()
            if got != want:
                raise InputError(
                    f"face {f} is {[g + 1 for g in got]}, the neutral's is {[w + 1 for w in want]} "
                    "(face lists must match)",
                    path=path, line=i + 1,
                )
    return positions


def _first_indices(faces: list[bytes]) -> np.ndarray | None:
    """0-based vertex index of every corner of the given ``f`` lines, or None if any is unusual."""
    toks = b" ".join(f[2:] for f in faces).split()
    try:
        idx = np.array([t.split(b"/", 1)[0] for t in toks], dtype=np.int64)
    except ValueError:
        return None
    if np.any(idx <= 0):
        return None
    return (idx - 1).astype(np.int32)


def write_obj(
    path: str | os.PathLike[str],
    vertices: np.ndarray,
    face_vertices: np.ndarray,
    face_offsets: np.ndarray,
    uvs: np.ndarray | None = None,
    face_uvs: np.ndarray | None = None,
    header: str | None = None,
) -> None:
    """Write a polygon mesh as OBJ, atomically.

    Parameters
    ----------
    vertices : (V, 3) float
    face_vertices, face_offsets
        Polygons in the flat layout of :class:`PolyMesh`.
    uvs : (T, 2) float, optional
    face_uvs : (N,) int, optional
        Required with ``uvs``.
    header
        A comment written at the top.
    """
    vertices = np.asarray(vertices, np.float64)
    parts: list[str] = []
    if header:
        parts.extend(f"# {h}\n" for h in header.splitlines())
    parts.append("".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in vertices.tolist()))
    if uvs is not None:
        parts.append("".join(f"vt {u:.6f} {v:.6f}\n" for u, v in np.asarray(uvs).tolist()))
    fv = np.asarray(face_vertices) + 1
    fuv = None if face_uvs is None else np.asarray(face_uvs) + 1
    lines = []
    for f in range(len(face_offsets) - 1):
        a, b = int(face_offsets[f]), int(face_offsets[f + 1])
        if fuv is None:
            lines.append("f " + " ".join(str(v) for v in fv[a:b].tolist()))
        else:
            lines.append("f " + " ".join(f"{v}/{t}" for v, t in zip(fv[a:b].tolist(), fuv[a:b].tolist(),
                                                                      strict=True)))
    parts.append("\n".join(lines) + "\n")
    with atomic_file(path) as tmp:
        tmp.write_text("".join(parts))
