"""The reconstruct job: one implementation whatever the schedule (plain, flow, any chunk size)."""

import filecmp
import inspect
from dataclasses import fields
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgi.cli import main
from lgi.io.record import RECORD_FILE, read_record
from lgi.jobs.reconstruct import ReconstructOptions
from lgi.jobs.reconstruct.chunks import save_part as _save_part

FILES = ("meshes.npz", "diagnostics.csv", "per_frame.csv", "run.json")


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    t = tmp_path_factory.mktemp("job")
    assert main(["synth", "--out", str(t / "s"), "--vertices", "2500", "--frames", "30", "-q"]) == 0
    for name, rig in (("idx", []), ("idxr", ["--jaw-rig", str(t / "s" / "jaw_rig.npz")])):
        assert main(["build", str(t / "s" / "dataset"), "--markers", str(t / "s" / "markers.csv"), "--out",
                     str(t / name), "-q", *rig]) == 0
    d = pd.read_csv(t / "s" / "bundles.csv")
    rng = np.random.default_rng(3)
    for c in ("x", "y", "z"):
        d[c] += rng.normal(0.0, 0.03, len(d))  # 0.3 mm
    d = d.drop(index=rng.choice(len(d), len(d) // 30, replace=False))  # some markers missing
    d.to_csv(t / "noisy.csv", index=False)
    return t


def _same(a: Path, b: Path, names=FILES) -> None:
    for name in names:
        assert filecmp.cmp(a / name, b / name, shallow=False), name


def test_flow_signature_is_the_options() -> None:
    """Every option of the job is a flow parameter with the same default (a new option cannot be forgotten)."""
    from lgi.orchestration.reconstruct import reconstruct_shot

    params = inspect.signature(reconstruct_shot.fn).parameters
    for f in fields(ReconstructOptions):
        assert f.name in params, f.name
        assert params[f.name].default == f.default, f.name


def test_plain_and_flow_agree_with_non_default_options(prefect_harness, shot: Path) -> None:
    """--smooth, --obj, --jaw none and --bilateral, plain and through the flow in chunks of 7 and 30 frames:
    identical files."""
    common = [str(shot / "idx"), "--bundles", str(shot / "s" / "bundles.csv"), "--smooth", "3", "--obj",
              "--jaw", "none", "--bilateral", "1.5:0.5", "-q"]
    assert main(["reconstruct", *common, "--out", str(shot / "plain")]) == 0
    for chunk in ("7", "30"):
        out = shot / f"flow{chunk}"
        assert main(["reconstruct", *common, "--out", str(out), "--flow", "--chunk-size", chunk]) == 0
        _same(shot / "plain", out)
        names = sorted(p.name for p in (shot / "plain" / "obj").iterdir())
        assert sorted(p.name for p in (out / "obj").iterdir()) == names
        for p in (shot / "plain" / "obj").iterdir():
            assert filecmp.cmp(p, out / "obj" / p.name, shallow=False)
    assert not list(shot.glob(".flow*.chunks-*")), "chunk files left behind"


def test_noisy_rig_shot_same_on_every_schedule(prefect_harness, shot: Path) -> None:
    """Noisy bundles with gaps on a rigged index: the plain two-thread path and the flow in chunks of 8 give the
    same files, USD included; so do smoothed runs in chunks of 8 and 11."""
    common = [str(shot / "idxr"), "--bundles", str(shot / "noisy.csv"), "-q", "--usd", "--fps", "24"]
    assert main(["reconstruct", *common, "--out", str(shot / "np")]) == 0
    assert main(["reconstruct", *common, "--out", str(shot / "nf"), "--flow", "--chunk-size", "8"]) == 0
    _same(shot / "np", shot / "nf", (*FILES, "shot.usdc"))
    smooth = [*common, "--smooth", "5", "--jaw-smooth", "3", "--flow"]
    assert main(["reconstruct", *smooth, "--out", str(shot / "s8"), "--chunk-size", "8"]) == 0
    assert main(["reconstruct", *smooth, "--out", str(shot / "s11"), "--chunk-size", "11"]) == 0
    _same(shot / "s8", shot / "s11", (*FILES, "shot.usdc"))
    a = np.load(shot / "np" / "meshes.npz")["vertices"]
    b = np.load(shot / "s8" / "meshes.npz")["vertices"]
    assert np.abs(a - b).max() > 1e-4  # the smoothing did something


def test_a_flow_over_its_memory_budget_hands_chunks_on_through_files(prefect_harness, shot: Path,
                                                                     monkeypatch) -> None:
    """A long take's finished chunks wait for the writer on disk once those held in memory reach the budget: the
    same files as the plain path, and none held afterwards."""
    from lgi.jobs.reconstruct import chunks

    monkeypatch.setattr(chunks, "PARTS_KEPT_BYTES", 2 * 8 * 2600 * 12)  # two chunks of 8 frames in memory, no more
    saved = []
    monkeypatch.setattr(chunks, "save_part", lambda path, *a: (saved.append(path), _save_part(path, *a)))
    common = [str(shot / "idxr"), "--bundles", str(shot / "noisy.csv"), "-q"]
    assert main(["reconstruct", *common, "--out", str(shot / "bp")]) == 0
    assert main(["reconstruct", *common, "--out", str(shot / "bf"), "--flow", "--chunk-size", "8"]) == 0
    _same(shot / "bp", shot / "bf", FILES)
    assert saved, "every chunk was held in memory"
    assert not chunks._PARTS and chunks._PARTS_BYTES[0] == 0


def test_jaw_none_on_a_rigged_index_refused_on_both_paths(prefect_harness, shot: Path, capsys) -> None:
    for extra in ([], ["--flow"]):
        code = main(["reconstruct", str(shot / "idxr"), "--bundles", str(shot / "s" / "bundles.csv"), "--out",
                     str(shot / "refused"), "--jaw", "none", "-q", *extra])
        assert code == 2
        assert "jaw rig" in capsys.readouterr().err
    assert not (shot / "refused" / "meshes.npz").exists()


def test_rerun_replaces_the_jobs_outputs_only(shot: Path) -> None:
    out = shot / "rerun"
    args = ["reconstruct", str(shot / "idx"), "--bundles", str(shot / "s" / "bundles.csv"), "--out", str(out), "-q"]
    assert main([*args, "--obj", "--plot"]) == 0
    assert (out / "obj").is_dir() and (out / "per_frame.png").is_file()
    (out / "notes.txt").write_text("mine")
    assert main(args) == 0
    assert not (out / "obj").exists() and not (out / "per_frame.png").exists()  # nothing stale from the first run
    assert (out / "notes.txt").read_text() == "mine"  # not the job's: left alone
    # No temporaries left; lgi's record lists what this run wrote, and not the user's notes.
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == [RECORD_FILE]
    assert sorted(read_record(out)[0]) == ["diagnostics.csv", "meshes.npz", "per_frame.csv", "run.json"]


@pytest.mark.parametrize("flag,value", [("--smooth", "1002"), ("--jaw-smooth", "1002"), ("--chunk-size", "0"),
                                        ("--max-gap", "1000001"), ("--temporal-weight", "nan"), ("--noise", "-1"),
                                        ("--fps", "0"), ("--bilateral", "1:0")])
def test_bad_options_refused_before_any_work(shot: Path, flag: str, value: str, capsys) -> None:
    out = shot / "bad"
    code = main(["reconstruct", str(shot / "idx"), "--bundles", str(shot / "s" / "bundles.csv"), "--out", str(out),
                 "-q", flag, value])
    assert code == 2
    assert flag in capsys.readouterr().err
    assert not out.exists()


def test_slot_labels_match_python_formatting() -> None:
    """The diagnostics' shape and weight texts, built array-wise, are Python's own: unused slots anywhere in a
    row, weights at 4-decimal ties (decided on the exact binary value), above 1, and rows with nothing."""
    from lgi.solve.solver import slot_labels

    rng = np.random.default_rng(3)
    names = [f"shape_{i}" for i in range(40)]
    shapes = rng.integers(0, 40, (3000, 7))
    weights = rng.random((3000, 7))
    weights[rng.random(weights.shape) < 0.4] = 0.0
    weights[:500] = np.round(weights[:500] * 2e4) / 2e4  # x.xxxx5: ties
    weights[500:520] *= 40.0
    weights[520:530] = 0.0
    shape_text, weight_text = slot_labels(shapes, weights, names)
    for r in range(len(shapes)):
        used = weights[r] > 0
        assert shape_text[r] == ";".join(names[k] for k in shapes[r][used])
        assert weight_text[r] == " ".join(f"{w:.4f}" for w in weights[r][used])
    assert slot_labels(shapes[:0], weights[:0], names)[0].shape == (0,)


def test_run_record_beside_the_outputs_and_on_the_review_page(shot: Path) -> None:
    """run.json records the method, the options and the noise the solve used and estimated; a later
    ``lgi review`` of the folder shows them, as ``lgi reconstruct --review`` does."""
    import json

    out = shot / "rec-record"
    assert main(["reconstruct", str(shot / "idxr"), "--bundles", str(shot / "noisy.csv"), "--out", str(out),
                 "--smooth", "3", "-q"]) == 0
    rec = json.loads((out / "run.json").read_text())
    assert rec["method"] == "local" and rec["options"]["smooth"] == 3 and "chunk_size" not in rec["options"]
    # 0.3 mm of noise per coordinate was added: the estimate finds it and the solve uses it.
    assert rec["noise_estimated"] and 0.2 < rec["noise_estimate_mm"] < 0.4 and rec["noise_mm"] > 0.1
    assert main(["review", str(out), "--index", str(shot / "idxr"), "--out", str(shot / "page-record")]) == 0
    meta = json.loads((shot / "page-record" / "review_meta.js").read_text().split("=", 1)[1].strip().rstrip(";"))
    rows = dict((label, text) for label, text in meta["summary"] if label != "report")
    assert rows["noise estimate"].startswith(f"{rec['noise_estimate_mm']:.4f} mm")
    assert "smooth=3" in rows["options"] and rows["method"] == "local"


def test_the_summary_of_a_long_take_holds_no_block_of_the_diagnostics() -> None:
    # A view of one column of a block's diagnostics holds all of that block's numbers: over a long take the
    # summary grew by 9 kB per ICT frame.
    import gc
    import weakref
    from types import SimpleNamespace

    import pandas as pd

    from lgi.jobs.reconstruct.summary import ShotSummary

    n_m, n_f = 3, 4
    rng = np.random.default_rng(0)
    d = pd.DataFrame({"frame": np.repeat(np.arange(n_f), n_m), "status": ["contained", "projected"] * 6,
                      "projection_mm": rng.random(12), "residual_mm": rng.random(12), "source": "local fit",
                      "fit_rms_mm": np.repeat(rng.random(n_f), n_m), "far_share": rng.random(12)})
    res = SimpleNamespace(diagnostics=d, frames=np.arange(n_f), noise=0.0, jaw=rng.random((n_f, 4)))
    tally = ShotSummary(n_m)
    tally.add(res)
    refs = [weakref.ref(b.values) for b in d._mgr.blocks if b.values.dtype == np.float64]
    del res, d
    gc.collect()
    assert refs and all(r() is None for r in refs)
    assert tally.frames == n_f and len(tally.fit_rms[0]) == n_f


def test_a_finished_chunk_carries_its_warnings(tmp_path: Path) -> None:
    # A chunk finished in another process (a Dask worker) logs its warnings there: they travel with its part.
    from lgi.jobs.reconstruct.chunks import load_part

    diag = pd.DataFrame({"frame": [0, 1], "marker": ["a", "a"]})
    vertices = np.zeros((2, 4, 3), np.float32)
    for said in (["lip contours of 3 frames not used", "another"], []):
        _save_part(tmp_path / "part.npz", vertices, None, diag, said)
        v, jaw, d, back = load_part(tmp_path / "part.npz")
        assert back == said and jaw is None and np.array_equal(v, vertices) and d.equals(diag)
