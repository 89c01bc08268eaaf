import filecmp
from pathlib import Path

from lgi.dataset.importing import import_obj_folder
from lgi.dataset.markers import write_layout
from lgi.dataset.shapes import ShapeDataset
from lgi.io.record import RECORD_FILE
from lgi.synthetic import actor as synth

# Files that describe a run (timings, which stages were cached), not the data: they may differ.
RUN_ONLY = ("build.json", "report.md", RECORD_FILE)


def _same_tree(a: Path, b: Path) -> bool:
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.name not in RUN_ONLY)
    return files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file() and p.name not in RUN_ONLY) and all(
        filecmp.cmp(a / f, b / f, shallow=False) for f in files)


def test_rebuild_flow_caches_by_content(prefect_harness, tmp_path: Path, obj_folder: Path, small_actor) -> None:
    from flows.rebuild_dataset import rebuild_dataset

    layout, _ = synth.default_layout(small_actor)
    markers = tmp_path / "markers.csv"
    write_layout(markers, layout, small_actor.neutral)
    cache = str(tmp_path / "cache")
    first = rebuild_dataset(str(obj_folder), str(tmp_path / "a"), markers=str(markers), cache_dir=cache)
    assert not any(first["stages"].values())  # everything computed
    ds = ShapeDataset.load(tmp_path / "a" / "dataset", verify=True)
    assert first["content_hash"] == import_obj_folder(obj_folder, show_progress=False).content_hash()
    assert first["n_shapes"] == 3 == ds.n_shapes
    assert first["verification"]["passed"] and (tmp_path / "a" / "index" / "manifest.json").is_file()
    # The published folders and the report, nothing else (no lock files beside them); the report's picture is
    # the per-shape chart, drawn with the verification.
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == [".cache", "dataset", "index", "report.md",
                                                                  "verification"]
    assert [p.name for p in (tmp_path / "a" / ".cache").iterdir() if not p.name.endswith(".lock")] == []
    assert (tmp_path / "a" / "verification" / "errors.png").stat().st_size > 5000
    assert "(verification/errors.png)" in (tmp_path / "a" / "report.md").read_text()

    again = rebuild_dataset(str(obj_folder), str(tmp_path / "b"), markers=str(markers), cache_dir=cache)
    assert all(again["stages"].values())  # nothing recomputed
    assert _same_tree(tmp_path / "a", tmp_path / "b")

    changed = rebuild_dataset(str(obj_folder), str(tmp_path / "c"), markers=str(markers), cache_dir=cache,
                              index_options={"min_motion_rel": 0.02})
    hits = changed["stages"]
    assert hits["read"] and hits["stabilise"] and hits["natural"]  # upstream of the change: reused
    assert not hits["clouds"] and not hits["index"] and not hits["verify"]  # downstream: recomputed


def test_import_command_runs_the_flow(prefect_harness, tmp_path: Path, obj_folder: Path, small_actor) -> None:
    from lgi.cli import main

    layout, _ = synth.default_layout(small_actor)
    write_layout(tmp_path / "m.csv", layout, small_actor.neutral)
    assert main(["import", str(obj_folder), "--out", str(tmp_path / "out"), "--flow", "--markers",
                 str(tmp_path / "m.csv")]) == 0
    assert ShapeDataset.load(tmp_path / "out" / "dataset", verify=True).n_shapes == 3
    assert (tmp_path / "out" / "verification" / "verification.csv").is_file()
    assert (tmp_path / "out" / "report.md").read_text().startswith("# Dataset rebuild")


def test_rebuild_flow_augments(prefect_harness, tmp_path: Path, obj_folder: Path, small_actor) -> None:
    from flows.rebuild_dataset import rebuild_dataset

    layout, _ = synth.default_layout(small_actor)
    markers = tmp_path / "m.csv"
    write_layout(markers, layout, small_actor.neutral)
    aug = {"linear": True, "simulate": True, "budget": 2, "levels": [0.5, 1.0]}
    first = rebuild_dataset(str(obj_folder), str(tmp_path / "a"), markers=str(markers), augmentation=aug,
                            cache_dir=str(tmp_path / "cache"))
    assert not first["stages"]["augment"] and first["augmented"]["n_shapes"] == 3 + 2 * 2
    ds = ShapeDataset.load(tmp_path / "a" / "dataset_augmented", verify=True)
    assert [m.extra.get("method") for m in ds.shape_meta[3:]] == ["linear", "linear", "simulated", "simulated"]
    assert first["verification"]["passed"]
    again = rebuild_dataset(str(obj_folder), str(tmp_path / "b"), markers=str(markers), augmentation=aug,
                            cache_dir=str(tmp_path / "cache"))
    assert again["stages"]["augment"] and _same_tree(tmp_path / "a" / "dataset_augmented",
                                                     tmp_path / "b" / "dataset_augmented")
