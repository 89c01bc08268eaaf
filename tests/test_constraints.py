"""Markers seen by one camera: rays from the tracks table, the surface on them, the same on every schedule."""

from __future__ import annotations

import filecmp
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgi.cli import main


def _write_tracks(path: Path, rows: pd.DataFrame, rig=None) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    from lgi.capture.footage import RIG_METADATA

    table = pa.Table.from_pandas(rows, preserve_index=False)
    if rig is not None:
        table = table.replace_schema_metadata({**(table.schema.metadata or {}),
                                               RIG_METADATA: json.dumps(rig.to_json()).encode()})
    pq.write_table(table, str(path))


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    """The synthetic actor's performance as exact bundles, with some markers hidden from the bundles and seen by
    one camera of a rig: their observations (the true marker points projected through a moving head pose) in a
    tracks table as lgi track writes it (head pose columns, the rig in its metadata)."""
    from scipy.spatial.transform import Rotation

    from lgi.capture.footage import HEAD_POSE_COLUMNS
    from lgi.synthetic.hmc import hmc_rig

    t = tmp_path_factory.mktemp("rays")
    assert main(["synth", "--out", str(t / "s"), "--vertices", "2500", "--frames", "24", "-q"]) == 0
    assert main(["build", str(t / "s" / "dataset"), "--markers", str(t / "s" / "markers.csv"), "--out",
                 str(t / "idx"), "-q"]) == 0
    d = pd.read_csv(t / "s" / "bundles.csv")
    rng = np.random.default_rng(5)
    names = sorted(d.marker.unique())
    hidden = [(f, m) for f in range(0, 24, 2) for m in rng.choice(names, 3, replace=False)]
    key = set(hidden)
    keep = np.array([(int(f), m) not in key for f, m in zip(d.frame, d.marker, strict=True)])
    d[keep].to_csv(t / "bundles.csv", index=False)
    rig = hmc_rig("fisheye")
    rot = Rotation.from_rotvec(rng.normal(0, 0.01, (24, 3)))  # head -> rig frame, per frame
    trans = rng.normal(0, 1.0, (24, 3))  # mm
    rows = []
    for f, m in hidden:
        head_mm = d[(d.frame == f) & (d.marker == m)][["x", "y", "z"]].to_numpy()[0] * 10.0
        world = rot[f].apply(head_mm) + trans[f]
        uv = rig.cameras[f % 2].project(world[None])[0]
        rows.append({"frame": f, "marker": m, "camera": f % 2, "x": uv[0], "y": uv[1], "reprojection_px": np.nan,
                     "source": "forward", "triangulated": False,
                     **dict(zip(HEAD_POSE_COLUMNS, [*rot[f].as_quat(), *trans[f]], strict=True))})
    _write_tracks(t / "tracks.parquet", pd.DataFrame(rows), rig)
    return {"dir": t, "rig": rig, "rot": rot, "trans": trans, "hidden": hidden, "rows": pd.DataFrame(rows)}


def test_marker_seen_by_one_camera_ends_on_its_ray(shot) -> None:
    """With exact bundles, every hidden marker's surface point lies on its viewing ray (<= 0.01 mm): checked by
    projecting the final surface point through the head pose and the camera, independently of the rays."""
    from lgi.index.build import LGIIndex

    t = shot["dir"]
    assert main(["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(t / "rec"),
                 "--noise", "0", "--observations", str(t / "tracks.parquet"), "-q"]) == 0
    index = LGIIndex.load(t / "idx")
    v = np.load(t / "rec" / "meshes.npz")["vertices"]
    pts = index.layout().evaluate(v.astype(np.float64))
    d = pd.read_csv(t / "rec" / "diagnostics.csv")
    assert (d.constraint == "ray").sum() == len(shot["hidden"])
    for (f, m), row in zip(shot["hidden"], shot["rows"].itertuples(), strict=True):
        cam = shot["rig"].cameras[f % 2]
        world = shot["rot"][f].apply(pts[f, index.marker_names.index(m)] * 10.0) + shot["trans"][f]
        depth = cam.to_camera(world[None])[0, 2]
        px = np.linalg.norm(cam.project(world[None])[0] - [row.x, row.y])
        # a pixel offset at this depth, as a distance across the ray (fisheye: K's focal length near the centre)
        assert px * depth / cam.K[0, 0] <= 0.01, (f, m, px)
        r = d[(d.frame == f) & (d.marker == m)].iloc[0]
        assert r.constraint == "ray" and r.ray_distance_mm <= 0.01
    assert set(d.constraint) == {"bundle", "ray"}
    assert (t / "rec" / "bundles_constrained.parquet").is_file()


def test_rays_same_through_the_flow(prefect_harness, shot) -> None:
    """The flow (chunks of 7) writes the files lgi reconstruct writes, the constrained bundles included."""
    from lgi.orchestration.reconstruct import reconstruct_shot

    t = shot["dir"]
    main(["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(t / "plain"),
          "--observations", str(t / "tracks.parquet"), "-q"])
    reconstruct_shot(str(t / "idx"), str(t / "bundles.csv"), str(t / "flow"), chunk_size=7,
                     observations=str(t / "tracks.parquet"))
    for name in ("meshes.npz", "diagnostics.csv", "per_frame.csv", "bundles_constrained.parquet"):
        assert filecmp.cmp(t / "plain" / name, t / "flow" / name, shallow=False), name


BAD = {
    "no head pose": (lambda r: r.drop(columns=["head_qw"]), "head pose"),
    "unknown marker": (lambda r: r.assign(marker=["nose_tip_X", *r.marker[1:]]), "nose_tip_X"),
    "camera 2": (lambda r: r.assign(camera=[2, *r.camera[1:]]), "camera must be 0 or 1"),
    "NaN pixel": (lambda r: r.assign(x=[np.nan, *r.x[1:]]), "x must be a finite pixel coordinate"),
    "duplicate": (lambda r: pd.concat([r, r.iloc[:1]]), "a second observation"),
    "bad quaternion": (lambda r: r.assign(head_qw=2.0), "not a unit quaternion"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_tracks_tables_refused(shot, case: str, tmp_path: Path, capsys) -> None:
    t = shot["dir"]
    change, words = BAD[case]
    bad = tmp_path / "bad.parquet"
    _write_tracks(bad, change(shot["rows"]), shot["rig"])
    out = tmp_path / "rec"
    assert main(["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(out),
                 "--observations", str(bad), "-q"]) == 2
    err = capsys.readouterr().err
    assert words in err and "bad.parquet" in err and "Traceback" not in err
    assert not out.exists()


def test_tracks_without_rig_need_calib(shot, tmp_path: Path, capsys) -> None:
    t = shot["dir"]
    bare = tmp_path / "bare.parquet"
    _write_tracks(bare, shot["rows"])
    args = ["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(tmp_path / "r"),
            "--observations", str(bare), "--noise", "0", "-q"]
    assert main(args) == 2
    assert "pass --calib" in capsys.readouterr().err
    calib = tmp_path / "calib.json"
    shot["rig"].save(calib)
    assert main([*args, "--calib", str(calib)]) == 0
    d = pd.read_csv(tmp_path / "r" / "diagnostics.csv")
    assert d.loc[d.constraint == "ray", "ray_distance_mm"].max() <= 0.01
    assert main(["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(tmp_path / "r2"),
                 "--calib", str(calib)]) == 2
    assert "--observations" in capsys.readouterr().err


@pytest.mark.parametrize("noise", [0.0, 1.0])
def test_synthetic_lip_contours_are_the_true_lip_edges(tmp_path: Path, noise: float) -> None:
    """hmc/lip_contours.csv: the lips' inner edges of the true mesh, through the true head motion and cameras,
    where the camera sees them; with --contour-noise, that much pixel noise and no more."""
    from lgi.capture.camera import StereoRig
    from lgi.synthetic.actor import make_actor

    out = tmp_path / "s"
    assert main(["synth", "--out", str(out), "--vertices", "3000", "--frames", "6", "--hmc", "--image-size",
                 "640x512", "--board-views", "3", "--contour-noise", str(noise), "-q"]) == 0
    table = pd.read_csv(out / "hmc" / "lip_contours.csv")
    assert list(table.columns) == ["frame", "camera", "curve", "point", "x", "y"]
    assert set(table.curve) == {"upper_inner", "lower_inner"} and set(table.camera) == {0, 1}
    lips = make_actor(3000).lip_contours()
    truth = np.load(out / "truth.npz")["vertices"]
    head = np.load(out / "hmc" / "truth.npz")
    rig = StereoRig.from_calibration(json.loads((out / "hmc" / "cameras_true.json").read_text())["shot_head_frame"])
    err = []
    for (f, c, curve), rows in table.groupby(["frame", "camera", "curve"]):
        ids = lips[curve][rows.point.to_numpy()]
        world = truth[f, ids] * 10.0 @ head["head_rotation"][f].T + head["head_translation"][f]
        err.append(rows[["x", "y"]].to_numpy() - rig.cameras[c].project(world))
    err = np.concatenate(err)
    seen = len(table) / (2 * 6 * sum(len(v) for v in lips.values()))
    assert seen > 0.8, seen  # the inner edges are in view of both cameras most of the time
    if noise == 0:
        assert np.abs(err).max() < 1e-3
    else:
        assert 0.8 < err.std() < 1.2


def test_lip_edges_pulled_onto_a_traced_curve(shot) -> None:
    """A curve traced 3 px below where camera 0 sees the upper lip's edge: after the fit the edge's vertices
    project onto it (RMS < 0.3 px from 3), the markers' surface points have not moved, and the vertices far from
    the lips are untouched."""
    from lgi.dataset.mesh import triangulate
    from lgi.index.build import LGIIndex
    from lgi.solve.contours import ContourView, LipContours

    t = shot["dir"]
    index = LGIIndex.load(t / "idx")
    a = index.arrays
    lc = LipContours(a["neutral"], triangulate(a["face_vertices"], a["face_offsets"])[0], a["marker_vertices"],
                     a["marker_weights"])
    x = np.load(t / "s" / "truth.npz")["vertices"][5].astype(np.float64)
    cam, R, tr = shot["rig"].cameras[0], shot["rot"][5].as_matrix(), shot["trans"][5]
    chain = lc.chains["upper_inner"]
    seen = cam.project(x[chain] * 10.0 @ R.T + tr)
    curve = seen[1:-1] + [0.0, 3.0]  # the corners left out: the traced stretch ends before them
    y, before, after = lc.fit(x, [ContourView(cam, R, tr, "upper_inner", curve)])
    assert 2.5 < before < 3.5 and after < 0.3, (before, after)
    moved = cam.project(y[chain[1:-1]] * 10.0 @ R.T + tr)
    step = np.linspace(0, 1, 500)[:, None]
    dense = np.concatenate([p + step * (q - p) for p, q in zip(curve[:-1], curve[1:], strict=True)])
    gap = np.min(np.linalg.norm(moved[:, None] - dense[None], axis=2), axis=1)  # px, to the curve drawn densely
    assert np.median(gap) < 0.2 and gap.max() < 1.0, gap
    layout = index.layout()
    assert np.abs(layout.evaluate(y[None]) - layout.evaluate(x[None])).max() < 1e-9  # cm
    far = np.linalg.norm(a["neutral"] - a["neutral"][chain].mean(axis=0), axis=1) > 4.0
    assert np.array_equal(y[far], x[far])


CONTOUR_BAD = {
    "unknown curve": ("0,0,upper_outer,0,1,2\n0,0,upper_outer,1,2,2\n", "unknown curve 'upper_outer'"),
    "camera 2": ("0,2,upper_inner,0,1,2\n0,2,upper_inner,1,2,2\n", "camera must be 0 or 1"),
    "text": ("0,0,upper_inner,0,abc,2\n0,0,upper_inner,1,2,2\n", "contours.csv:2: non-numeric"),
    "duplicate point": ("0,0,upper_inner,0,1,2\n0,0,upper_inner,0,2,2\n", "a second row"),
    "outside the shot": ("900,0,upper_inner,0,1,2\n900,0,upper_inner,1,2,2\n", "no traced curve"),
}


@pytest.mark.parametrize("case", sorted(CONTOUR_BAD))
def test_bad_contour_files_refused(shot, case: str, tmp_path: Path, capsys) -> None:
    t = shot["dir"]
    rows, words = CONTOUR_BAD[case]
    path = tmp_path / "contours.csv"
    path.write_text("frame,camera,curve,point,x,y\n" + rows)
    out = tmp_path / "rec"
    assert main(["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(out),
                 "--observations", str(t / "tracks.parquet"), "--contours", str(path), "-q"]) == 2
    err = capsys.readouterr().err
    assert words in err and "contours.csv" in err and "Traceback" not in err
    assert not out.exists()
    assert main(["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(out),
                 "--contours", str(path), "-q"]) == 2
    assert "--observations" in capsys.readouterr().err


def test_contours_that_cannot_be_used_are_reported(shot, tmp_path: Path, capsys) -> None:
    """A curve nowhere near the lips (frame 0) and one in a frame the tracks table has no head pose for (frame 1):
    both are reported on stderr and leave the frame's contour columns empty, not silently dropped."""
    t = shot["dir"]
    path = tmp_path / "contours.csv"
    path.write_text("frame,camera,curve,point,x,y\n0,0,upper_inner,0,5,5\n0,0,upper_inner,1,9,5\n"
                    "1,0,upper_inner,0,5,5\n1,0,upper_inner,1,9,5\n")
    capsys.readouterr()
    assert main(["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(tmp_path / "r"),
                 "--observations", str(t / "tracks.parquet"), "--contours", str(path), "-q"]) == 0
    err = capsys.readouterr().err
    assert "no lip edge vertex projects within" in err and "no head pose" in err
    d = pd.read_csv(tmp_path / "r" / "diagnostics.csv")
    assert d.contour_px_before.isna().all()
