"""Scan files in PLY, STL and OFF: what pymeshlab would drop or cannot allocate is refused first, with the file and
the line or vertex at fault (lgi.io.meshfiles)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from lgi.errors import InputError
from lgi.evaluation.compare import read_scan
from lgi.io.meshfiles import check_mesh_file


def grid(n: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A bumpy n x n grid: (n*n, 3) vertices and its (2(n-1)^2, 3) triangles."""
    y, x = np.mgrid[0:n, 0:n].astype(np.float64)
    v = np.stack([x.ravel(), y.ravel(), 0.1 * np.sin(x.ravel() + y.ravel())], 1)
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    t = np.concatenate([np.stack([i, i + 1, i + n], 1), np.stack([i + 1, i + n + 1, i + n], 1)])
    return v, t


def saved(path: Path, binary: bool) -> Path:
    """The grid as pymeshlab writes it: the files a user's tools make."""
    import pymeshlab

    v, t = grid()
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(v, t.astype(np.int32)))
    kw = {} if path.suffix == ".off" else {"binary": binary}
    ms.save_current_mesh(str(path), save_vertex_color=False, save_face_color=False, **kw) \
        if path.suffix == ".ply" else ms.save_current_mesh(str(path), **kw)
    return path


@pytest.mark.parametrize("name,binary", [("a.ply", False), ("b.ply", True), ("a.stl", False), ("b.stl", True),
                                         ("c.off", False)])
def test_files_as_tools_write_them_pass(tmp_path, name, binary) -> None:
    p = saved(tmp_path / name, binary)
    check_mesh_file(p)
    assert len(read_scan(p).triangles) == 50


def poisoned_text(path: Path, old: bytes, new: bytes) -> int:
    """Replace the first ``old`` in a text file with ``new``; returns its 1-based line."""
    data = path.read_bytes()
    at = data.index(old)
    path.write_bytes(data[:at] + new + data[at + len(old):])
    return data.count(b"\n", 0, at) + 1


@pytest.mark.parametrize("name", ["a.ply", "c.off"])
@pytest.mark.parametrize("value", [b"nan", b"inf", b"-Infinity", b"1.#IND"])
def test_a_non_finite_text_vertex_is_refused_with_its_line(tmp_path, name, value) -> None:
    p = saved(tmp_path / name, binary=False)
    lines = p.read_bytes().split(b"\n")
    header = lines.index(b"end_header") + 1 if name.endswith(".ply") else 2
    row = header + 8  # vertex 7's line, 1-based
    lines[row - 1] = value + b" " + b" ".join(lines[row - 1].split()[1:])
    p.write_bytes(b"\n".join(lines))
    with pytest.raises(InputError) as e:
        read_scan(p)
    assert e.value.path == str(p) and e.value.line == row and "not a finite number" in e.value.message


def test_a_non_finite_binary_vertex_is_refused_with_its_index(tmp_path) -> None:
    p = saved(tmp_path / "b.ply", binary=True)
    data = bytearray(p.read_bytes())
    body = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:body].decode().split("element")[1].splitlines()  # the vertex element's lines
    kinds = [ln.split()[1] for ln in header if ln.startswith("property")]
    assert kinds[:3] in (["float"] * 3, ["double"] * 3), kinds
    size = {"float": 4, "double": 8, "uchar": 1, "int": 4}
    stride = sum(size[k] for k in kinds)
    struct.pack_into("<f" if kinds[1] == "float" else "<d", data, body + 9 * stride + size[kinds[0]],
                     float("nan"))  # vertex 9's y
    p.write_bytes(bytes(data))
    with pytest.raises(InputError) as e:
        read_scan(p)
    assert e.value.path == str(p) and "vertex 9 (0-based) has a non-finite y" in e.value.message


def test_non_finite_stl_vertices_are_refused(tmp_path) -> None:
    p = saved(tmp_path / "b.stl", binary=True)
    data = bytearray(p.read_bytes())
    struct.pack_into("<f", data, 84 + 50 * 3 + 12 + 4, float("inf"))  # triangle 3's first vertex's y
    p.write_bytes(bytes(data))
    with pytest.raises(InputError, match="triangle 3 "):
        read_scan(p)
    q = saved(tmp_path / "a.stl", binary=False)
    line = poisoned_text(q, b"vertex ", b"vertex nan ")
    with pytest.raises(InputError) as e:
        read_scan(q)
    assert e.value.path == str(q) and e.value.line == line


def test_a_header_that_declares_more_than_the_file_holds_is_refused(tmp_path) -> None:
    p = tmp_path / "huge.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 2147483647\nproperty float x\n"
                  b"property float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                  b"end_header\n" + bytes(64))
    with pytest.raises(InputError, match="2,147,483,647 vertex rows") as e:
        read_scan(p)
    assert e.value.line == 3
    q = tmp_path / "huge.off"
    q.write_text("OFF\n2147483647 1 0\n0 0 0\n")
    with pytest.raises(InputError, match="declares 2,147,483,647 vertices"):
        read_scan(q)
    s = tmp_path / "short.stl"
    s.write_bytes(bytes(80) + struct.pack("<I", 1000) + bytes(50))
    with pytest.raises(InputError, match="neither a binary STL"):
        read_scan(s)


def test_a_binary_triangle_ply_is_mapped_and_reads_as_pymeshlab_reads_it(tmp_path, monkeypatch) -> None:
    """Dense scans come as binary PLY: plyfile maps them (no copy in pymeshlab); the scan is the same either way,
    and PLY files plyfile cannot map as triangles (text, polygons) still load through pymeshlab."""
    import lgi.evaluation.compare as compare

    p = saved(tmp_path / "b.ply", True)
    mapped = read_scan(p, "mm")
    assert compare._triangle_ply(p) is not None
    monkeypatch.setattr(compare, "_triangle_ply", lambda path: None)  # pymeshlab's reading of the same file
    general = read_scan(p, "mm")
    monkeypatch.undo()
    assert np.array_equal(mapped.vertices, general.vertices) and np.array_equal(mapped.triangles, general.triangles)
    assert compare._triangle_ply(saved(tmp_path / "a.ply", False)) is None
    v, t = grid()
    quads = tmp_path / "q.ply"
    quads.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
                      b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                      + v[[0, 1, 7, 6]].astype("<f4").tobytes() + bytes([4]) + np.arange(4, dtype="<i4").tobytes())
    assert compare._triangle_ply(quads) is None and len(read_scan(quads).triangles) == 2
    # A face naming a vertex the file lacks is refused with the face.
    bad = tmp_path / "bad.ply"
    face = np.zeros(1, np.dtype([("n", "u1"), ("v", "<i4", 3)]))
    face["n"], face["v"] = 3, [0, 1, 9]
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    + v[:3].astype("<f4").tobytes() + face.tobytes())
    with pytest.raises(InputError, match="face 0 .* refers to a vertex"):
        read_scan(bad)
