import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgi.capture.bundles import read_bundles
from lgi.cli import main
from lgi.dataset.markers import read_layout
from lgi.dataset.shapes import ShapeDataset
from lgi.io.record import RECORD_FILE
from tests.checks import THROUGH_MM, bundle_gaps_mm


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lgi.cli", *args], capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize("cmd", ["import", "synth", "bundles", "demo"])
def test_help(cmd: str) -> None:
    r = run(cmd, "--help")
    assert r.returncode == 0 and "usage: lgi" in r.stdout


def test_synth_writes_contract_files(tmp_path: Path) -> None:
    assert main(["synth", "--out", str(tmp_path / "s"), "--vertices", "3000", "--frames", "12", "-q"]) == 0
    out = tmp_path / "s"
    ds = ShapeDataset.load(out / "dataset", verify=True)
    layout = read_layout(out / "markers.csv", ds.triangles)
    truth = np.load(out / "truth.npz")
    assert truth["vertices"].shape == (12, ds.n_vertices, 3) and truth["vertices"].dtype == np.float32
    b = read_bundles(out / "bundles.csv", layout.names)
    np.testing.assert_allclose(b.positions, layout.evaluate(truth["vertices"].astype(float)), atol=1e-5)
    assert [p.name for p in out.glob(".*")] == [RECORD_FILE], "staging left behind"


def test_bundles_one_frame_per_shape(tmp_path: Path) -> None:
    main(["synth", "--out", str(tmp_path / "s"), "--vertices", "3000", "--frames", "2", "-q"])
    s = tmp_path / "s"
    assert main(["bundles", str(s / "dataset"), "--markers", str(s / "markers.csv"), "--out",
                 str(tmp_path / "b.parquet"), "--shapes", "smile*"]) == 0
    ds = ShapeDataset.load(s / "dataset").select(include="smile*")
    layout = read_layout(s / "markers.csv")
    b = read_bundles(tmp_path / "b.parquet", layout.names)
    assert len(b.frames) == ds.n_shapes
    np.testing.assert_allclose(b.positions[1], layout.evaluate(ds.shape(1)), atol=1e-9)
    assert (tmp_path / "b.shapes.csv").read_text().splitlines()[2] == f"1,{ds.names[1]}"


def _expect_failure(args: list[str], out: Path, *words: str) -> str:
    r = run(*args)
    assert r.returncode == 2, r.stderr
    for w in words:
        assert w in r.stderr, r.stderr
    assert not out.exists(), "partial output left behind"
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}")]
    return r.stderr


def test_import_bad_inputs_leave_nothing(tmp_path: Path, obj_folder: Path) -> None:
    out = tmp_path / "ds"
    # non-numeric value
    bad = obj_folder / "smile_L.obj"
    lines = bad.read_text().splitlines()
    lines[10] = "v 1.0 abc 2.0"
    bad.write_text("\n".join(lines) + "\n")
    _expect_failure(["import", str(obj_folder), "--out", str(out), "-q"], out, "smile_L.obj:11", "non-numeric")
    # face index out of range in the neutral
    shutil.copy(obj_folder / "pucker.obj", bad)
    neutral = obj_folder / "neutral.obj"
    text = neutral.read_text().splitlines()
    k = next(i for i, ln in enumerate(text) if ln.startswith("f "))
    text[k] = "f 1/1 2/2 99999/3"
    neutral.write_text("\n".join(text) + "\n")
    _expect_failure(["import", str(obj_folder), "--out", str(out), "-q"], out, f"neutral.obj:{k + 1}", "out of range")


def test_import_topology_mismatch_and_missing(tmp_path: Path, obj_folder: Path) -> None:
    out = tmp_path / "ds"
    p = obj_folder / "pucker.obj"
    text = p.read_text().splitlines()
    k = next(i for i, ln in enumerate(text) if ln.startswith("f "))
    parts = text[k].split()
    text[k] = " ".join([parts[0], parts[2], parts[1], *parts[3:]])
    p.write_text("\n".join(text) + "\n")
    _expect_failure(["import", str(obj_folder), "--out", str(out), "-q"], out, f"pucker.obj:{k + 1}", "face 0")
    v = [ln for ln in text if not ln.startswith("v ")] + [ln for ln in text if ln.startswith("v ")][:-1]
    p.write_text("\n".join(v) + "\n")
    _expect_failure(["import", str(obj_folder), "--out", str(out), "-q"], out, "pucker.obj", "vertex count")
    empty = tmp_path / "empty"
    empty.mkdir()
    _expect_failure(["import", str(empty), "--out", str(out)], out, "no OBJ files")
    (obj_folder / "neutral.obj").rename(obj_folder / "base.obj")
    _expect_failure(["import", str(obj_folder), "--out", str(out)], out, "no neutral found")


def test_import_existing_output_survives_failure(tmp_path: Path, obj_folder: Path) -> None:
    out = tmp_path / "ds"
    assert main(["import", str(obj_folder), "--out", str(out), "-q"]) == 0
    before = ShapeDataset.load(out).content_hash()
    (obj_folder / "jaw_open.obj").write_text("v 0 0 0\n")
    assert main(["import", str(obj_folder), "--out", str(out), "-q"]) == 2
    assert ShapeDataset.load(out, verify=True).content_hash() == before


def test_import_ict(tmp_path: Path, ict_dir: Path) -> None:
    r = run("import", str(ict_dir), "--out", str(tmp_path / "ict"), "--rigid-vertices",
            str(ict_dir / "vertex_indices.json"), "-q")
    assert r.returncode == 0, r.stderr
    ds = ShapeDataset.load(tmp_path / "ict", verify=True)
    assert ds.n_shapes == 57 and ds.n_vertices == 26719 and len(ds.face_offsets) - 1 == 26384
    assert ds.uvs.shape == (28911, 2)
    assert "identity000" not in ds.names and "mouthClose" in ds.names
    assert np.diff(ds.face_offsets).max() == 4  # quads kept


def test_import_ict_identity_blend(tmp_path: Path, ict_dir: Path) -> None:
    assert main(["import", str(ict_dir), "--out", str(tmp_path / "a"), "--include", "jawOpen,mouthSmile_L",
                 "--identity", "identity000=1.5,identity003=-1", "--rigid-vertices", "none", "-q"]) == 0
    assert main(["import", str(ict_dir), "--out", str(tmp_path / "b"), "--include", "jawOpen,mouthSmile_L",
                 "--rigid-vertices", "none", "-q"]) == 0
    a, b = ShapeDataset.load(tmp_path / "a"), ShapeDataset.load(tmp_path / "b")
    assert np.abs(a.neutral - b.neutral).max() > 0.1  # a different face
    np.testing.assert_allclose(a.deltas, b.deltas, atol=1e-5)  # the same expression deltas


@pytest.mark.parametrize("with_faces", [True, False])
def test_delta_import_matches_full_import(tmp_path: Path, obj_folder: Path, with_faces: bool) -> None:
    from lgi.io.obj import read_obj

    assert main(["import", str(obj_folder), "--out", str(tmp_path / "f"), "--rigid-vertices", "none", "-q"]) == 0
    full = ShapeDataset.load(tmp_path / "f")
    neutral = read_obj(obj_folder / "neutral.obj")
    dfolder = tmp_path / "deltas"
    dfolder.mkdir()
    shutil.copy(obj_folder / "neutral.obj", dfolder / "neutral.obj")
    for name in full.names:
        d = np.asarray(full.deltas[full.index(name)], np.float64)
        text = "".join(f"v {x:.7f} {y:.7f} {z:.7f}\n" for x, y, z in d)
        if with_faces:
            text += "".join(
                "f " + " ".join(str(v + 1) for v in neutral.face_vertices[a:b]) + "\n"
                for a, b in zip(neutral.face_offsets[:-1], neutral.face_offsets[1:], strict=True)
            )
        (dfolder / f"{name}.obj").write_text(text)
    assert main(["import", str(dfolder), "--out", str(tmp_path / "d"), "--deltas", "--rigid-vertices", "none",
                 "-q"]) == 0
    delta = ShapeDataset.load(tmp_path / "d")
    assert delta.names == full.names
    np.testing.assert_allclose(delta.deltas, full.deltas, atol=2e-6)


def test_build_reconstruct_verify(tmp_path: Path) -> None:
    s = tmp_path / "s"
    assert main(["synth", "--out", str(s), "--vertices", "2500", "--frames", "15", "-q"]) == 0
    assert main(["build", str(s / "dataset"), "--markers", str(s / "markers.csv"), "--out", str(tmp_path / "idx"),
                 "-q"]) == 0
    r = run("verify", str(tmp_path / "idx"), "-q")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "passed" in r.stdout and "jaw_open+smile_L" in r.stdout
    r = run("verify", str(tmp_path / "idx"), "-q", "--tolerance", "1e-12")
    assert r.returncode == 1 and "FAILED" in r.stdout
    out = tmp_path / "rec"
    assert main(["reconstruct", str(tmp_path / "idx"), "--bundles", str(s / "bundles.csv"), "--out", str(out),
                 "--obj", "-q"]) == 0
    m = np.load(out / "meshes.npz")
    truth = np.load(s / "truth.npz")["vertices"]
    assert m["vertices"].shape == truth.shape and m["frames"].tolist() == list(range(15))
    rms = np.sqrt(np.mean(np.sum((m["vertices"] - truth) ** 2, axis=2))) * 10
    assert rms < 0.2  # mm; measured 0.051
    diag = pd.read_csv(out / "diagnostics.csv")
    assert len(diag) == 15 * len(read_layout(s / "markers.csv"))
    gaps = bundle_gaps_mm(out / "meshes.npz", s / "markers.csv", s / "bundles.csv")
    assert len(gaps) == len(diag) and gaps.max() < THROUGH_MM
    assert set(diag.status) <= {"contained", "projected", "neighbour", "missing", "fitted"}
    assert len(list((out / "obj").glob("frame_*.obj"))) == 15


def test_reconstruct_bad_bundles_leave_nothing(tmp_path: Path) -> None:
    s = tmp_path / "s"
    main(["synth", "--out", str(s), "--vertices", "2500", "--frames", "3", "-q"])
    main(["build", str(s / "dataset"), "--markers", str(s / "markers.csv"), "--out", str(tmp_path / "idx"), "-q"])
    bad = tmp_path / "bad.csv"
    bad.write_text((s / "bundles.csv").read_text() + "2,no_such_marker,1,2,3\n")
    out = tmp_path / "rec"
    _expect_failure(["reconstruct", str(tmp_path / "idx"), "--bundles", str(bad), "--out", str(out)], out,
                    "frame 2", "no_such_marker", "unknown marker")


def test_augment_linear(tmp_path: Path) -> None:
    s = tmp_path / "s"
    main(["synth", "--out", str(s), "--vertices", "2500", "--frames", "2", "-q"])
    assert main(["augment", str(s / "dataset"), "--out", str(tmp_path / "aug"), "--linear", "--budget", "30",
                 "--markers", str(s / "markers.csv")]) == 0
    orig = ShapeDataset.load(s / "dataset")
    aug = ShapeDataset.load(tmp_path / "aug", verify=True)
    assert aug.n_shapes == orig.n_shapes + 30 and aug.names[: orig.n_shapes] == orig.names
    meta = aug.shape_meta[-1]
    assert "linear" in meta.tags and meta.extra["method"] == "linear" and len(meta.extra["sources"]) >= 2
    # An in-between is the weighted sum of its sources' displacements.
    expect = sum(w * np.asarray(orig.deltas[orig.index(n)], np.float64) for n, w in meta.extra["sources"].items())
    np.testing.assert_allclose(aug.deltas[-1], expect, atol=1e-5)
    rep = pd.read_csv(tmp_path / "aug" / "augmentation.csv")
    # In-betweens never displace a bundle's original points; each adds at most one point to a bundle's cloud (one
    # shape, one point), and pruning keeps some of them.
    assert (rep.points_augmented >= rep.points_original).all()
    assert (rep.kept <= rep.added).all() and rep.kept.sum() > 0
    assert (rep.kept == rep.points_augmented - rep.points_original).all()  # the report adds up
    assert (rep.kept < rep.added).any()  # an in-between that does not move a bundle adds no point to its cloud
    # Both methods on the same combinations, tagged; the report has a column pair per method.
    assert main(["augment", str(s / "dataset"), "--out", str(tmp_path / "both"), "--linear", "--simulate", "--budget",
                 "4", "--jaw-rig", str(s / "jaw_rig.npz"), "--markers", str(s / "markers.csv"), "-q"]) == 0
    both = ShapeDataset.load(tmp_path / "both")
    methods = [m.extra["method"] for m in both.shape_meta[orig.n_shapes:]]
    assert methods == ["linear"] * 4 + ["simulated"] * 4
    sims = both.shape_meta[orig.n_shapes + 4:]
    assert [m.extra["sources"] for m in sims] == [m.extra["sources"] for m in both.shape_meta[orig.n_shapes:][:4]]
    assert all(abs(m.extra["volume_change"]) < 0.05 for m in sims)
    rep = pd.read_csv(tmp_path / "both" / "augmentation.csv")
    assert {"kept_linear", "kept_simulated", "added_simulated"} <= set(rep.columns)
    # Choosing no method is bad input, and leaves nothing.
    assert main(["augment", str(s / "dataset"), "--out", str(tmp_path / "none")]) == 2
    assert not (tmp_path / "none").exists()


def test_demo_runs_end_to_end(tmp_path: Path) -> None:
    """The README's main job (`lgi demo`), small: every step runs, the meshes are close to the truth and pass
    through the bundles."""
    r = run("demo", "--out", str(tmp_path / "demo"), "--vertices", "1500", "--frames", "8")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "[4/4] reconstructed the 8-frame performance" in r.stdout
    m = np.load(tmp_path / "demo" / "meshes.npz")
    truth = np.load(tmp_path / "demo" / "truth.npz")["vertices"]
    assert m["vertices"].shape == truth.shape
    assert np.sqrt(np.mean(np.sum((m["vertices"] - truth) ** 2, axis=2))) * 10 < 0.5  # mm
    gaps = bundle_gaps_mm(tmp_path / "demo" / "meshes.npz", tmp_path / "demo" / "markers.csv",
                          tmp_path / "demo" / "bundles.csv")
    assert gaps.max() < THROUGH_MM
