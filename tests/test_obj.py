from pathlib import Path

import numpy as np
import pytest

from lgi.errors import InputError
from lgi.io.obj import read_obj, read_obj_positions, write_obj


def test_roundtrip_keeps_quads_triangles_and_uv_seams(tmp_path: Path) -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0.5, 0]], float)
    fv = np.array([0, 1, 2, 3, 1, 4, 2])
    off = np.array([0, 4, 7])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5], [0.9, 0.9]], np.float32)
    fuv = np.array([0, 1, 2, 3, 4, 5, 2])  # vertex 1 has two UVs: a seam
    write_obj(tmp_path / "m.obj", v, fv, off, uv, fuv)
    m = read_obj(tmp_path / "m.obj")
    assert m.face_sizes().tolist() == [4, 3]
    np.testing.assert_array_equal(m.face_vertices, fv)
    np.testing.assert_array_equal(m.face_uvs, fuv)
    np.testing.assert_allclose(m.vertices, v)
    np.testing.assert_allclose(m.uvs, uv, atol=1e-6)


def test_reads_materials_negative_indices_and_crlf(tmp_path: Path) -> None:
    text = "mtllib a.mtl\r\nv 0 0 0\r\nv 1 0 0\r\nv 0 1 0\r\nusemtl skin\r\nf -3 -2 -1\r\nusemtl lips\r\nf 1 2 3\r\n"
    (tmp_path / "m.obj").write_text(text)
    m = read_obj(tmp_path / "m.obj")
    assert m.mtllib == "a.mtl" and m.materials == ["skin", "lips"]
    assert m.face_material.tolist() == [0, 1]
    assert m.face_vertices.tolist() == [0, 1, 2, 0, 1, 2]


@pytest.mark.parametrize(
    "body, line, words",
    [
        ("v 0 0 0\nv 1 x 0\nv 0 1 0\nf 1 2 3\n", 2, "non-numeric"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", 4, "out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", 4, "corners"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 b 3\n", 4, "non-numeric vertex index"),
        ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", 2, "values"),
    ],
)
def test_malformed_obj_names_file_and_line(tmp_path: Path, body: str, line: int, words: str) -> None:
    p = tmp_path / "bad.obj"
    p.write_text(body)
    with pytest.raises(InputError) as e:
        read_obj(p)
    assert e.value.line == line and e.value.path == str(p)
    assert words in str(e.value) and f"bad.obj:{line}" in str(e.value)


def test_shape_with_other_topology_is_rejected(tmp_path: Path) -> None:
    (tmp_path / "n.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n")
    ref = read_obj(tmp_path / "n.obj")
    (tmp_path / "s.obj").write_text("v 0 0 1\nv 1 0 1\nv 0 1 1\nv 1 1 1\nf 1 2 3\nf 2 3 4\n")
    with pytest.raises(InputError, match="face 1 is") as e:
        read_obj_positions(tmp_path / "s.obj", ref)
    assert e.value.line == 6
    (tmp_path / "c.obj").write_text("v 0 0 1\nv 1 0 1\nv 0 1 1\nf 1 2 3\n")
    with pytest.raises(InputError, match="vertex count 3 differs"):
        read_obj_positions(tmp_path / "c.obj", ref)
    # Different formatting of the same faces is fine.
    (tmp_path / "ok.obj").write_text("v 0 0 1\nv 1 0 1\nv 0 1 1\nv 1 1 1\nf 1//1 2//1 3//1\nf 2 4 3\n")
    assert read_obj_positions(tmp_path / "ok.obj", ref)[0, 2] == 1.0
