"""``lgi compare``: a reconstructed frame against a scan of another topology, with known answers.

The scan is the true frame of the synthetic shot remeshed by pymeshlab (isotropic remeshing: other vertices,
other triangles) with a hole cut in the forehead. Its vertices lie on the true surface (the remesher reprojects
them), so the true frame's distance to it is the remesher's deviation between vertices, measured here with the
project's closest-point code (not the pymeshlab filter the command uses): that is the bound asserted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgi.cli import main
from lgi.dataset.mesh import ClosestPointQuery, vertex_normals
from lgi.dataset.shapes import ShapeDataset
from lgi.evaluation.compare import remeshed_scan
from lgi.io.npz import save_npz
from lgi.io.obj import write_obj

FRAME = 2
HOLE = (0.0, 6.0, 1.6, 1.2)  # forehead hole: centre x, y (cm), half width, half height


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


def save_scan(path: Path, vertices: np.ndarray, triangles: np.ndarray, scale: float = 1.0) -> Path:
    write_obj(path, vertices * scale, triangles.ravel(), np.arange(0, 3 * len(triangles) + 1, 3))
    return path


@pytest.fixture(scope="module")
def shot(tmp_path_factory) -> dict:
    """A synthetic shot reconstructed from its exact bundles, the truth as a reconstruction folder, and the
    remeshed true frame as a scan."""
    w = tmp_path_factory.mktemp("compare")
    assert main(["synth", "--out", str(w / "s"), "--vertices", "1500", "--frames", "4", "-q"]) == 0
    assert main(["build", str(w / "s" / "dataset"), "--markers", str(w / "s" / "markers.csv"), "--out",
                 str(w / "idx"), "-q"]) == 0
    assert main(["reconstruct", str(w / "idx"), "--bundles", str(w / "s" / "bundles.csv"), "--out",
                 str(w / "rec"), "-q"]) == 0
    truth = np.load(w / "s" / "truth.npz")
    (w / "true").mkdir()
    save_npz(w / "true" / "meshes.npz", vertices=truth["vertices"], frames=truth["frames"])
    ds = ShapeDataset.load(w / "s" / "dataset")
    tri = ds.triangles.astype(np.int64)
    x = truth["vertices"][FRAME].astype(np.float64)
    edge = np.linalg.norm(x[tri[:, 0]] - x[tri[:, 1]], axis=1).mean()
    sv, st = remeshed_scan(x, tri, 0.7 * edge, HOLE)
    # The bound: how far the true vertices are from the remeshed surface (independent of pymeshlab's filter).
    bound = ClosestPointQuery(sv, st).query(x)[2]
    return {"w": w, "tri": tri, "x": x, "scan_v": sv, "scan_t": st, "bound": bound,
            "scan": save_scan(w / "scan.obj", sv, st), "truth": truth["vertices"]}


def hole_vertices(x: np.ndarray, margin: float) -> np.ndarray:
    cx, cy, hx, hy = HOLE
    return (np.abs(x[:, 0] - cx) < hx - margin) & (np.abs(x[:, 1] - cy) < hy - margin) & (x[:, 2] > 0)


def tables(out: Path) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    return (pd.read_csv(out / "summary.csv"), pd.read_parquet(out / "vertex_distances.parquet"),
            pd.read_parquet(out / "scan_distances.parquet"))


def test_remeshed_truth_is_within_the_remeshing_deviation(shot, capsys) -> None:
    w = shot["w"]
    code, out, err = run(["compare", str(w / "true"), "--index", str(w / "s" / "dataset"), "--frame", str(FRAME),
                          "--scan", str(shot["scan"]), "--out", str(w / "c_true")], capsys)
    assert code == 0, err
    assert "Hausdorff" in out
    summary, vt, st = tables(w / "c_true")
    assert (w / "c_true" / "heatmaps" / f"frame_{FRAME:05d}_scan.png").is_file()
    cov = vt.covered.to_numpy()
    d = vt.distance_mm.to_numpy()
    bound_mm = shot["bound"][vt.vertex.to_numpy()] * 10
    assert bound_mm[cov].max() < 0.15  # the remesher's deviation between vertices on this coarse mesh
    # Each covered vertex is no farther from the scan than the remesher's deviation there, up to the OBJ's rounding
    # (six decimals of cm: 5e-6 mm per coordinate, under 1e-5 mm in all).
    assert np.all(d[cov] <= bound_mm[cov] + 1e-5)
    r = summary.iloc[0]
    assert r.max_mm <= bound_mm[cov].max() + 1e-5 and r.rms_mm < 0.05
    # The scan's vertices lie on the true surface: the other way the distances vanish.
    assert r.scan_max_mm < 1e-3 and r.inside_share > 0.9
    assert r.hausdorff_mm == pytest.approx(max(r.max_mm, r.scan_max_mm))
    # The hole is not covered; the face around it is.
    x = shot["x"]
    inner = hole_vertices(x, 0.3)
    assert inner.sum() >= 3 and not cov[inner].any()
    cx, cy, hx, hy = HOLE
    ring = (np.abs(x[:, 0] - cx) < hx + 1.5) & (np.abs(x[:, 1] - cy) < hy + 1.5) & ~hole_vertices(x, -0.3)
    assert cov[ring & (x[:, 2] > 0)].mean() > 0.99
    assert 0.8 < r.covered_share < 1.0


def test_offset_surface_gives_the_offset(shot, capsys) -> None:
    """The scan displaced along its normals by d: the measured distance is d (to the curvature's second order)."""
    w, d_cm = shot["w"], 0.1
    sv, st = shot["scan_v"], shot["scan_t"]
    moved = sv + d_cm * vertex_normals(sv, st)
    scan = save_scan(w / "offset.obj", moved, st, scale=10.0)
    code, out, err = run(["compare", str(w / "true"), "--index", str(w / "s" / "dataset"), "--frame", str(FRAME),
                          "--scan", str(scan), "--units", "mm", "--region", "face", "--out", str(w / "c_off")], capsys)
    assert code == 0, err
    summary, vt, _ = tables(w / "c_off")
    d = vt.distance_mm.to_numpy()[vt.covered.to_numpy()]
    assert np.median(d) == pytest.approx(1.0, abs=0.02)
    assert summary.rms_mm[0] == pytest.approx(1.0, abs=0.05)
    # Displaced outwards (along the normals the face shares with the scan): the frame is behind the scan.
    assert summary.mean_signed_mm[0] == pytest.approx(-1.0, abs=0.05)


def test_lgi_frame_obeys_the_triangle_inequality(shot, capsys) -> None:
    """LGI's frame from exact bundles: distance to the scan <= its vertex error + the remesher's deviation."""
    w = shot["w"]
    code, _, err = run(["compare", str(w / "rec"), "--index", str(w / "idx"), "--frame", str(FRAME), "--scan",
                        str(shot["scan"]), "--region", "marked", "--out", str(w / "c_lgi")], capsys)
    assert code == 0, err
    summary, vt, _ = tables(w / "c_lgi")
    rec = np.load(w / "rec" / "meshes.npz")["vertices"][FRAME].astype(np.float64)
    err_mm = np.linalg.norm(rec - shot["x"], axis=1) * 10
    v = vt.vertex.to_numpy()
    cov = vt.covered.to_numpy()
    assert np.all(vt.distance_mm.to_numpy()[cov] <= err_mm[v[cov]] + shot["bound"][v[cov]] * 10 + 1e-5)
    assert summary.rms_mm[0] < 0.5


def test_rigid_alignment_undoes_a_known_motion(shot, capsys) -> None:
    from scipy.spatial.transform import Rotation

    w = shot["w"]
    sv, st = shot["scan_v"], shot["scan_t"]
    rot = Rotation.from_euler("xyz", [1.5, -2.0, 1.0], degrees=True).as_matrix()
    shift = np.array([0.2, -0.15, 0.25])
    moved = (sv - sv.mean(0)) @ rot.T + sv.mean(0) + shift
    scan = save_scan(w / "moved.obj", moved, st)
    base = ["compare", str(w / "true"), "--index", str(w / "s" / "dataset"), "--frame", str(FRAME), "--scan",
            str(scan)]
    code, out, err = run([*base, "--out", str(w / "c_none")], capsys)
    assert code == 0, err
    assert tables(w / "c_none")[0].rms_mm[0] > 1.0  # misaligned by about 3 mm
    code, out, err = run([*base, "--align", "rigid", "--out", str(w / "c_rigid")], capsys)
    assert code == 0, err
    assert "scan moved by" in out
    summary, _, _ = tables(w / "c_rigid")
    aligned = tables(w / "c_rigid")[1]
    cov = aligned.covered.to_numpy()
    assert summary.max_mm[0] <= shot["bound"][aligned.vertex.to_numpy()[cov]].max() * 10 + 1e-3
    assert summary.rotation_deg[0] == pytest.approx(np.degrees(Rotation.from_matrix(rot).magnitude()), abs=1e-3)
    import json

    m = np.asarray(json.loads((w / "c_rigid" / "summary.json").read_text())[0]["transform_cm"])
    back = moved @ m[:3, :3].T + m[:3, 3]
    assert np.abs(back - sv).max() < 1e-4  # cm


def test_pairs_file_regions_and_obj_topology(shot, capsys, tmp_path) -> None:
    w = shot["w"]
    pairs = tmp_path / "pairs.csv"
    import shutil

    shutil.copyfile(shot["scan"], tmp_path / "copy.obj")
    pairs.write_text(f"frame,scan\n{FRAME},{shot['scan']}\n{FRAME},copy.obj\n")  # relative to the CSV's folder
    code, out, err = run(["compare", str(w / "true"), "--index", str(w / "s" / "dataset"), "--pairs", str(pairs),
                          "--region", "lips"], capsys)
    assert code == 0, err
    assert out.count("scan.obj") == 1 and "copy.obj" in out and "inner lip line" in out
    # Without --index the triangles come from the OBJ lgi reconstruct --obj writes.
    rec = tmp_path / "rec"
    assert main(["reconstruct", str(w / "idx"), "--bundles", str(w / "s" / "bundles.csv"), "--out", str(rec),
                 "--obj", "-q"]) == 0
    code, out, err = run(["compare", str(rec), "--frame", str(FRAME), "--scan", str(shot["scan"]), "--region",
                          "0:499"], capsys)
    assert code == 0, err
    assert "vertices 0-499" in out and "frame_00002.obj" in out
    code, _, err = run(["compare", str(rec), "--frame", str(FRAME), "--scan", str(shot["scan"]), "--region",
                        "lips"], capsys)
    assert code == 2 and "FIRST:LAST" in err


def test_two_scans_of_a_frame_with_one_name_keep_both_heat_maps(shot, capsys, tmp_path) -> None:
    w = shot["w"]
    for sub, dz in (("a", 0.0), ("b", 0.05)):
        (tmp_path / sub).mkdir()
        save_scan(tmp_path / sub / "scan.obj", shot["scan_v"] + [0.0, 0.0, dz], shot["scan_t"])
    out = tmp_path / "out"
    code, _, err = run(["compare", str(w / "true"), "--index", str(w / "s" / "dataset"), "--frame", str(FRAME),
                        "--scan", str(tmp_path / "a" / "scan.obj"), "--frame", str(FRAME), "--scan",
                        str(tmp_path / "b" / "scan.obj"), "--out", str(out)], capsys)
    assert code == 0, err
    summary = pd.read_csv(out / "summary.csv")
    assert list(summary["heatmap"]) == ["heatmaps/frame_00002_scan.png", "heatmaps/frame_00002_scan_2.png"]
    pictures = [(out / h).read_bytes() for h in summary["heatmap"]]
    assert sorted(p.name for p in (out / "heatmaps").iterdir()) == ["frame_00002_scan.png", "frame_00002_scan_2.png"]
    assert pictures[0] != pictures[1]  # the 0.5 mm offset scan's picture is its own


def test_bad_scans_exit_2_naming_the_file(shot, capsys, tmp_path) -> None:
    w = shot["w"]
    base = ["compare", str(w / "true"), "--index", str(w / "s" / "dataset"), "--frame", str(FRAME)]
    broken = tmp_path / "broken.obj"
    broken.write_text("v 0 0 0\nv 1 0 0\nv 0 x 0\nf 1 2 3\n")
    out_dir = tmp_path / "out"
    code, _, err = run([*base, "--scan", str(broken), "--out", str(out_dir)], capsys)
    assert code == 2 and f"{broken}:3" in err and "Traceback" not in err
    far = save_scan(tmp_path / "far.obj", shot["scan_v"] + [0.0, 0.0, 50.0], shot["scan_t"])
    code, _, err = run([*base, "--scan", str(far), "--out", str(out_dir)], capsys)
    assert code == 2 and str(far) in err and "covers no part of the face" in err
    ply = tmp_path / "junk.ply"
    ply.write_text("ply\nformat nonsense\n")
    code, _, err = run([*base, "--scan", str(ply)], capsys)
    assert code == 2 and str(ply) in err
    huge = tmp_path / "huge.ply"  # pymeshlab would try to allocate 2^31 - 1 vertices (std::bad_alloc, exit 3)
    huge.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2147483647\nproperty float x\nproperty float y\n"
                     b"property float z\nend_header\n0 0 0\n")
    code, _, err = run([*base, "--scan", str(huge)], capsys)
    assert code == 2 and f"{huge}:3" in err and "declares 2,147,483,647 vertex rows" in err
    code, _, err = run([*base, "--scan", str(tmp_path / "missing.obj")], capsys)
    assert code == 2 and "missing.obj" in err
    assert not out_dir.exists()  # no partial output
    code, _, err = run(["compare", str(w / "rec"), "--frame", str(FRAME), "--scan", str(shot["scan"])], capsys)
    assert code == 2 and "--index" in err
    code, _, err = run([*base, "--scan", str(shot["scan"]), "--frame", "1"], capsys)
    assert code == 2 and "one --scan per --frame" in err
    code, _, err = run([*base[:-1], "99", "--scan", str(shot["scan"])], capsys)
    assert code == 2 and "frame 99" in err
    code, _, err = run([*base, "--scan", str(shot["scan"]), "--out", str(w / "true")], capsys)
    assert code == 2 and "would replace this run's input" in err  # the output may not replace the reconstruction
    code, _, err = run([*base, "--scan", str(far), "--align", "rigid"], capsys)
    assert code == 2 and str(far) in err
