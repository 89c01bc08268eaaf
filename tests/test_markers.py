from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgi.dataset.markers import layout_from_points, read_layout, write_layout
from lgi.dataset.mesh import triangulate
from lgi.errors import InputError
from lgi.io.obj import read_obj
from lgi.paths import shipped
from lgi.synthetic import actor as synth


def test_points_snap_to_surface_and_roundtrip(tmp_path: Path, small_actor: synth.SyntheticActor) -> None:
    a = small_actor
    rng = np.random.default_rng(0)
    tri = rng.integers(0, len(a.triangles), 30)
    w = rng.dirichlet(np.ones(3), 30)
    on = np.einsum("nk,nkd->nd", w, a.neutral[a.triangles[tri]])
    layout, dist = layout_from_points([f"p{i}" for i in range(30)], on + 1e-3 * np.array([0, 0, 1]), a.neutral,
                                      a.triangles)
    assert dist.max() < 2e-3
    np.testing.assert_allclose(layout.evaluate(a.neutral), on, atol=2e-3)
    write_layout(tmp_path / "m.csv", layout, a.neutral)
    back = read_layout(tmp_path / "m.csv", a.triangles)
    assert back.names == layout.names
    np.testing.assert_allclose(back.evaluate(a.neutral), layout.evaluate(a.neutral), atol=1e-7)


def test_layout_for_another_mesh_is_rejected(small_actor: synth.SyntheticActor) -> None:
    with pytest.raises(InputError, match="another mesh|out of range"):
        read_layout(shipped("markers_synth.csv"), small_actor.triangles)


def test_bad_layout_rows(tmp_path: Path) -> None:
    good = "name,triangle,v0,v1,v2,w0,w1,w2\na,0,0,1,2,0.2,0.3,0.5\n"
    (tmp_path / "a.csv").write_text(good + "b,0,0,1,2,0.2,x,0.5\n")
    with pytest.raises(InputError, match="w1") as e:
        read_layout(tmp_path / "a.csv")
    assert e.value.marker == "b" and e.value.line == 3
    (tmp_path / "b.csv").write_text(good + "a,0,0,1,2,0.2,0.3,0.5\n")
    with pytest.raises(InputError, match="duplicate"):
        read_layout(tmp_path / "b.csv")
    (tmp_path / "c.csv").write_text(good + "c,0,0,1,2,0.9,0.3,0.5\n")
    with pytest.raises(InputError, match="convex"):
        read_layout(tmp_path / "c.csv")


def test_shipped_synthetic_layout() -> None:
    a = synth.make_actor()
    layout = read_layout(shipped("markers_synth.csv"), a.triangles)
    assert 80 <= len(layout) <= 150
    p = layout.evaluate(a.neutral)
    xyz = pd.read_csv(shipped("markers_synth.csv"))[["x", "y", "z"]].to_numpy()
    np.testing.assert_allclose(p, xyz, atol=1e-6)
    eye = np.min([np.hypot(p[:, 0] - ex, p[:, 1] - ey) for ex, ey in synth.EYE_CENTERS], axis=0)
    assert eye.min() > 1.0  # no dots on the eyes
    inner_lip = (np.abs(p[:, 1] - synth.MOUTH_Y) < 0.2) & (np.abs(p[:, 0]) < synth.MOUTH_HALF_WIDTH)
    assert not inner_lip.any()
    d_mouth = np.hypot(p[:, 0], p[:, 1] - synth.MOUTH_Y)
    # Denser around the mouth than on the forehead (markers per unit area).
    near_mouth = (d_mouth < 3).sum() / (np.pi * 9)
    forehead = ((p[:, 1] > 5) & (p[:, 1] < 9.5) & (np.abs(p[:, 0]) < 6)).sum() / (4.5 * 12)
    assert near_mouth > 1.5 * forehead


def test_shipped_ict_layout(ict_dir: Path) -> None:
    mesh = read_obj(ict_dir / "generic_neutral_mesh.obj")
    tris, _ = triangulate(mesh.face_vertices, mesh.face_offsets)
    layout = read_layout(shipped("markers_ict.csv"), tris)
    assert 80 <= len(layout) <= 150
    assert layout.vertices.max() <= 6705  # narrow face area only: no eyeballs, teeth, mouth socket
    assert len(set(layout.names)) == len(layout)
