from pathlib import Path

import numpy as np
import pytest

from lgi.cli import main
from lgi.export.formats import displacement_map, read_exr, write_exr, write_usd
from lgi.io.record import RECORD_FILE
from lgi.synthetic import actor as synth


def test_usd_roundtrip(tmp_path: Path, small_actor) -> None:
    from pxr import Usd, UsdGeom

    a = small_actor
    acts = synth.random_performance(12, seed=1)
    verts = a.evaluate_many(acts)
    frames = np.arange(100, 112)
    write_usd(tmp_path / "perf.usdc", verts, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs, frames, fps=24)
    stage = Usd.Stage.Open(str(tmp_path / "perf.usdc"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/mesh"))
    pts = mesh.GetPointsAttr()
    assert pts.GetTimeSamples() == [float(f) for f in frames]
    np.testing.assert_allclose(np.asarray(pts.Get(105.0)), verts[5], atol=1e-6)
    assert stage.GetTimeCodesPerSecond() == 24 and UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [4] * (len(a.face_offsets) - 1)
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying
    np.testing.assert_allclose(np.asarray(st.Get())[np.asarray(st.GetIndices())], a.uvs[a.face_uvs], atol=1e-6)


def test_a_long_shot_is_value_clips_that_compose_to_the_single_file(tmp_path: Path, small_actor) -> None:
    from pxr import Usd, UsdGeom

    a = small_actor
    verts = a.evaluate_many(synth.random_performance(23, seed=2))
    frames = np.r_[np.arange(7), np.arange(12, 28)]  # a gap where the second clip starts
    write_usd(tmp_path / "one.usdc", verts, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs, frames, clip_frames=0)
    write_usd(tmp_path / "clips.usda", verts, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs, frames,
              clip_frames=7)
    assert sorted(p.name for p in (tmp_path / "clips.clips").iterdir()) == [RECORD_FILE,
        "clip_00000.usdc", "clip_00001.usdc", "clip_00002.usdc", "clip_00003.usdc", "manifest.usda"]
    one, clips = (Usd.Stage.Open(str(tmp_path / n)) for n in ("one.usdc", "clips.usda"))
    m1, m2 = (UsdGeom.Mesh(s.GetPrimAtPath("/Face/mesh")) for s in (one, clips))
    assert m1.GetPointsAttr().GetTimeSamples() == m2.GetPointsAttr().GetTimeSamples()
    assert (clips.GetStartTimeCode(), clips.GetEndTimeCode()) == (0, 27)
    for t in np.arange(-1, 29, 0.25):  # between frames and across the gap too, as one file interpolates
        for get in (lambda m: m.GetPointsAttr(), lambda m: m.GetExtentAttr()):
            assert np.array_equal(np.asarray(get(m1).Get(float(t))), np.asarray(get(m2).Get(float(t)))), t
    np.testing.assert_allclose(np.asarray(m2.GetPointsAttr().Get(14.0)), verts[9], atol=1e-6)
    # A shorter export of the same name is one file again, and the clips it no longer uses go.
    write_usd(tmp_path / "clips.usda", verts[:5], a.face_vertices, a.face_offsets, frames=frames[:5], clip_frames=7)
    assert not (tmp_path / "clips.clips").exists()


def test_displacement_map_and_exr(tmp_path: Path, small_actor) -> None:
    a = small_actor
    disp = np.tile([0.1, -0.2, 0.3], (a.n_vertices, 1))  # a constant shift paints a constant image
    img, mask = displacement_map(disp, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs, size=64)
    assert mask.mean() > 0.95
    np.testing.assert_allclose(img[mask], np.tile([0.1, -0.2, 0.3], (mask.sum(), 1)), atol=1e-6)
    write_exr(tmp_path / "d.exr", img)
    np.testing.assert_array_equal(read_exr(tmp_path / "d.exr"), img)
    # A field linear in the vertices' UVs is reproduced at pixel centres.
    lin = np.zeros((a.n_vertices, 3))
    lin[:, 0] = a.uvs[:, 0]
    img, mask = displacement_map(lin, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs, size=64)
    u = (np.arange(64) + 0.5) / 64
    np.testing.assert_allclose(img[32, mask[32], 0], u[mask[32]], atol=1e-5)


def test_export_command(tmp_path: Path, monkeypatch) -> None:
    from pxr import Usd, UsdGeom

    from lgi.export import clips

    s = tmp_path / "s"
    main(["synth", "--out", str(s), "--vertices", "2500", "--frames", "4", "-q"])
    main(["build", str(s / "dataset"), "--markers", str(s / "markers.csv"), "--out", str(tmp_path / "idx"), "-q"])
    main(["reconstruct", str(tmp_path / "idx"), "--bundles", str(s / "bundles.csv"), "--out", str(tmp_path / "r"),
          "-q"])
    assert main(["export", str(tmp_path / "r"), "--index", str(tmp_path / "idx"), "--usd", str(tmp_path / "p.usda"),
                 "--exr", str(tmp_path / "exr"), "--exr-size", "32", "-q"]) == 0
    assert (tmp_path / "p.usda").read_text().startswith("#usda")
    assert sorted(p.name for p in (tmp_path / "exr").iterdir()) == [RECORD_FILE,
                                                                    *(f"frame_{i:05d}.exr" for i in range(4))]
    assert main(["export", str(tmp_path / "nothing"), "--index", str(tmp_path / "idx"), "--usd", "x.usdc"]) == 2
    # Over USD_CLIP_FRAMES frames: value clips beside the file, from export and from reconstruct --usd alike.
    monkeypatch.setattr(clips, "USD_CLIP_FRAMES", 3)
    (tmp_path / "mine.clips").mkdir()
    (tmp_path / "mine.clips" / "notes.txt").write_text("a user's folder")
    assert main(["export", str(tmp_path / "r"), "--index", str(tmp_path / "idx"), "--usd",
                 str(tmp_path / "mine.usdc"), "--exr", str(tmp_path / "mine_exr"), "--exr-size", "32", "-q"]) == 2
    assert not (tmp_path / "mine.usdc").exists() and (tmp_path / "mine.clips" / "notes.txt").exists()
    assert not (tmp_path / "mine_exr").exists()  # refused before any map was written
    assert main(["export", str(tmp_path / "r"), "--index", str(tmp_path / "idx"), "--usd", str(tmp_path / "c.usdc"),
                 "-q"]) == 0
    assert sorted(p.name for p in (tmp_path / "c.clips").iterdir()) == [RECORD_FILE, "clip_00000.usdc",
                                                                          "clip_00001.usdc",
                                                                          "manifest.usda"]
    main(["reconstruct", str(tmp_path / "idx"), "--bundles", str(s / "bundles.csv"), "--out", str(tmp_path / "r"),
          "--usd", "-q"])
    assert (tmp_path / "r" / "shot.clips" / "clip_00001.usdc").is_file()
    ref = Usd.Stage.Open(str(tmp_path / "p.usda"))
    single = UsdGeom.Mesh(ref.GetPrimAtPath("/Face/mesh")).GetPointsAttr()
    for usd in (tmp_path / "c.usdc", tmp_path / "r" / "shot.usdc"):
        stage = Usd.Stage.Open(str(usd))
        pts = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/mesh")).GetPointsAttr()
        assert all(np.array_equal(np.asarray(pts.Get(f)), np.asarray(single.Get(f))) for f in range(4))
    main(["reconstruct", str(tmp_path / "idx"), "--bundles", str(s / "bundles.csv"), "--out", str(tmp_path / "r"),
          "-q"])
    assert not (tmp_path / "r" / "shot.clips").exists() and not (tmp_path / "r" / "shot.usdc").exists()


def test_usd_200_frames_of_ict(tmp_path: Path, ict_dir: Path) -> None:
    from pxr import Usd, UsdGeom

    from lgi.dataset.importing import import_obj_folder

    ds = import_obj_folder(ict_dir, include="jawOpen,mouthSmile_L,browInnerUp_L", rigid_vertices="none",
                           show_progress=False)
    w = np.abs(np.sin(np.linspace(0, 6, 200)[:, None] * np.array([1.0, 0.7, 1.3])))
    verts = (ds.neutral[None] + np.tensordot(w, np.asarray(ds.deltas, np.float64), axes=1)).astype(np.float32)
    write_usd(tmp_path / "ict.usdc", verts, ds.face_vertices, ds.face_offsets, ds.uvs, ds.face_uvs)
    stage = Usd.Stage.Open(str(tmp_path / "ict.usdc"))
    pts = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/mesh")).GetPointsAttr()
    assert len(pts.GetTimeSamples()) == 200
    for f in (0, 77, 199):
        np.testing.assert_array_equal(np.asarray(pts.Get(float(f))), verts[f])


def test_export_in_each_dccs_convention(tmp_path: Path) -> None:
    """--dcc blender (Z up, m) and --up-axis/--units: the points are lgi's turned +90 degrees about X and scaled,
    the stage says so, and the EXR maps' headers name the units, axis, neutral and frame. The default export is
    lgi's own convention, stated in the same header attributes."""
    import hashlib

    import OpenEXR
    from pxr import Usd, UsdGeom

    s = tmp_path / "s"
    main(["synth", "--out", str(s), "--vertices", "2500", "--frames", "3", "-q"])
    main(["build", str(s / "dataset"), "--markers", str(s / "markers.csv"), "--out", str(tmp_path / "idx"), "-q"])
    main(["reconstruct", str(tmp_path / "idx"), "--bundles", str(s / "bundles.csv"), "--out", str(tmp_path / "r"),
          "-q"])
    cm = np.load(tmp_path / "r" / "meshes.npz")["vertices"].astype(np.float64)
    base = ["export", str(tmp_path / "r"), "--index", str(tmp_path / "idx"), "--exr-size", "32", "-q"]
    for name, flags, up, mpu in (("lgi", [], "Y", 0.01), ("blender", ["--dcc", "blender"], "Z", 1.0),
                                 ("houdini", ["--dcc", "houdini"], "Y", 1.0), ("zcm", ["--up-axis", "Z"], "Z", 0.01),
                                 ("blender_cm", ["--dcc", "blender", "--units", "cm"], "Z", 0.01)):
        assert main([*base, *flags, "--usd", str(tmp_path / f"{name}.usdc"), "--exr", str(tmp_path / name)]) == 0
        stage = Usd.Stage.Open(str(tmp_path / f"{name}.usdc"))
        assert (UsdGeom.GetStageUpAxis(stage), UsdGeom.GetStageMetersPerUnit(stage)) == (up, mpu), name
        want = cm * (0.01 / mpu)
        if up == "Z":
            want = np.stack([want[..., 0], -want[..., 2], want[..., 1]], axis=-1)
        pts = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/mesh")).GetPointsAttr()
        got = np.stack([np.asarray(pts.Get(float(f)), np.float64) for f in range(3)])
        assert np.abs(got - want).max() * mpu * 1000 < 1e-3, name  # within a micrometre, in metres
        h = OpenEXR.File(str(tmp_path / name / "frame_00002.exr")).header()
        assert (h["lgi:units"], h["lgi:upAxis"], h["lgi:frame"]) == ("cm" if mpu == 0.01 else "m", up, 2), name
        neutral = np.load(tmp_path / "idx" / "index.npz")["neutral"]
        assert h["lgi:neutral"] == "idx"
        assert h["lgi:neutralSha256"] == hashlib.sha256(np.ascontiguousarray(neutral, "<f4").tobytes()).hexdigest()
        assert float(h["framesPerSecond"]) == 30.0
    # The maps turn and scale with the geometry: Blender's green is lgi's -z, in metres.
    lgi_map, bl_map = read_exr(tmp_path / "lgi" / "frame_00001.exr"), read_exr(tmp_path / "blender" / "frame_00001.exr")
    np.testing.assert_allclose(bl_map[..., 1], -lgi_map[..., 2] / 100, atol=1e-9)
    np.testing.assert_allclose(bl_map[..., 2], lgi_map[..., 1] / 100, atol=1e-9)
    # reconstruct --usd writes the same file in the same convention.
    assert main(["reconstruct", str(tmp_path / "idx"), "--bundles", str(s / "bundles.csv"), "--out",
                 str(tmp_path / "r2"), "--usd", "--dcc", "blender", "-q"]) == 0
    one, two = (Usd.Stage.Open(str(f)) for f in (tmp_path / "blender.usdc", tmp_path / "r2" / "shot.usdc"))
    assert UsdGeom.GetStageUpAxis(two) == "Z" and UsdGeom.GetStageMetersPerUnit(two) == 1.0
    p1, p2 = (UsdGeom.Mesh(x.GetPrimAtPath("/Face/mesh")).GetPointsAttr() for x in (one, two))
    assert all(np.array_equal(np.asarray(p1.Get(float(f))), np.asarray(p2.Get(float(f)))) for f in range(3))
    with pytest.raises(SystemExit) as e:
        main([*base, "--dcc", "modo", "--usd", str(tmp_path / "x.usdc")])
    assert e.value.code == 2
