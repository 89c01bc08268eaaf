import filecmp
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgi.cli import main
from tests.checks import THROUGH_MM, bundle_gaps_mm


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    t = tmp_path_factory.mktemp("shot")
    assert main(["synth", "--out", str(t / "s"), "--vertices", "2500", "--frames", "40", "-q"]) == 0
    assert main(["build", str(t / "s" / "dataset"), "--markers", str(t / "s" / "markers.csv"), "--out",
                 str(t / "idx"), "-q"]) == 0
    return t


def test_shot_flow_thread_and_dask_agree(prefect_harness, shot: Path, monkeypatch) -> None:
    from flows.reconstruct_shot import reconstruct_shot
    from lgi.orchestration import reconstruct as orchestration

    args = dict(index_dir=str(shot / "idx"), bundles=str(shot / "s" / "bundles.csv"), chunk_size=15, usd=True,
                plot=True)
    summary = reconstruct_shot(out=str(shot / "thread"), **args)
    assert summary["frames"] == 40
    m = np.load(shot / "thread" / "meshes.npz")
    gaps = bundle_gaps_mm(shot / "thread" / "meshes.npz", shot / "s" / "markers.csv", shot / "s" / "bundles.csv")
    assert gaps.max() < THROUGH_MM  # through every bundle, measured on the meshes
    truth = np.load(shot / "s" / "truth.npz")["vertices"]
    assert np.sqrt(np.mean(np.sum((m["vertices"] - truth) ** 2, axis=2))) * 10 < 0.2  # mm
    assert (shot / "thread" / "per_frame.png").stat().st_size > 5000
    assert len(pd.read_csv(shot / "thread" / "per_frame.csv")) == 40
    assert not list(shot.glob(".thread.chunks*"))
    # The narrowest window on Dask (one chunk finishing at a time, beside the chain's one choosing): the result is
    # the same.
    monkeypatch.setattr(orchestration, "DASK_FINISHING", 1)
    reconstruct_shot(out=str(shot / "dask"), dask_address="local:2", **args)  # a deployment's parameter
    for name in ("meshes.npz", "diagnostics.csv", "per_frame.csv", "shot.usdc"):
        assert filecmp.cmp(shot / "thread" / name, shot / "dask" / name, shallow=False), name


def test_reconstruct_command_runs_the_flow(prefect_harness, shot: Path) -> None:
    assert main(["reconstruct", str(shot / "idx"), "--bundles", str(shot / "s" / "bundles.csv"), "--out",
                 str(shot / "via_flow"), "--flow", "--chunk-size", "40", "-q"]) == 0
    assert main(["reconstruct", str(shot / "idx"), "--bundles", str(shot / "s" / "bundles.csv"), "--out",
                 str(shot / "plain"), "-q"]) == 0
    a = np.load(shot / "via_flow" / "meshes.npz")["vertices"]
    b = np.load(shot / "plain" / "meshes.npz")["vertices"]
    np.testing.assert_array_equal(a, b)  # one chunk: the flow and the plain functions agree exactly
    # The shot's artifacts, under keys of its output folder: the report carries the per-frame plot even without
    # --plot (drawn for the report only), and the progress artifact is keyed too.
    from prefect.artifacts import Artifact

    from lgi.orchestration import artifact_key

    assert not (shot / "via_flow" / "per_frame.png").exists()
    report = Artifact.get(artifact_key("shot-report", shot / "via_flow"))
    assert report is not None and "![per-frame plot](data:image/png;base64," in report.data
    progress = Artifact.get(artifact_key("shot-progress", shot / "via_flow"))
    assert progress is not None and progress.type == "progress" and float(progress.data) == 100.0


def test_shot_flow_from_footage(prefect_harness, tmp_path: Path) -> None:
    from flows.reconstruct_shot import reconstruct_shot

    s = tmp_path / "s"
    assert main(["synth", "--out", str(s), "--vertices", "8000", "--frames", "12", "--hmc", "--board-views", "5",
                 "-q"]) == 0
    assert main(["build", str(s / "dataset"), "--markers", str(s / "markers.csv"), "--jaw-rig", str(s / "jaw_rig.npz"),
                 "--out", str(tmp_path / "idx"), "-q"]) == 0
    summary = reconstruct_shot(index_dir=str(tmp_path / "idx"), bundles=str(tmp_path / "tracked.csv"),
                               out=str(tmp_path / "rec"), footage=str(s / "hmc"),
                               calib=str(s / "hmc" / "cameras_true.json"), markers=str(s / "markers.csv"),
                               helmet=str(s / "hmc" / "helmet.csv"))
    assert summary["frames"] == 12 and summary["tracking"]["triangulated_share"] > 0.95
    assert (tmp_path / "tracked.tracks.parquet").is_file()
    m = np.load(tmp_path / "rec" / "meshes.npz")["vertices"]
    truth = np.load(s / "truth.npz")["vertices"]
    assert np.sqrt(np.mean(np.sum((m - truth) ** 2, axis=2))) * 10 < 1.0  # mm, footage to meshes


def test_shot_flow_on_threads_finishes_a_few_chunks_at_a_time(prefect_harness, shot: Path, monkeypatch) -> None:
    """The flow on its own threads finishes at most FINISHING chunks at once, however many chunks have their
    choices made (else a long take's chunks were all finished at once: 5 GB at 9,000 ICT frames), with the same
    meshes."""
    import threading
    import time

    from flows.reconstruct_shot import reconstruct_shot
    from lgi.orchestration import reconstruct as orch

    running, most, lock = [0], [0], threading.Lock()
    finish = orch.job.finish_chunk

    def counted(*a, **k):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        try:
            time.sleep(0.05)  # long enough for the chunks made ready meanwhile to start, were they allowed
            return finish(*a, **k)
        finally:
            with lock:
                running[0] -= 1

    monkeypatch.setattr(orch.job, "finish_chunk", counted)
    reconstruct_shot(index_dir=str(shot / "idx"), bundles=str(shot / "s" / "bundles.csv"), chunk_size=4,
                     out=str(shot / "few"), review=False)
    assert 1 <= most[0] <= orch.FINISHING, most[0]
    ref = shot / "few_plain"
    assert main(["reconstruct", str(shot / "idx"), "--bundles", str(shot / "s" / "bundles.csv"), "--out", str(ref),
                 "-q"]) == 0
    np.testing.assert_array_equal(np.load(shot / "few" / "meshes.npz")["vertices"],
                                  np.load(ref / "meshes.npz")["vertices"])


def test_the_flow_page_lists_the_warnings_the_commands_page_does(prefect_harness, shot: Path, tmp_path) -> None:
    # A marker seen in 5 of 40 frames of noisy bundles is too rarely seen to smooth, which the run can only say;
    # the flow's page (its chunks on Prefect's threads) lists it as the command's does, once.
    import json

    from flows.reconstruct_shot import reconstruct_shot

    table = pd.read_csv(shot / "s" / "bundles.csv")
    rare = table.marker.iloc[0]
    table = table[(table.marker != rare) | (table.frame < 5)]
    bundles = tmp_path / "rare.csv"
    table.to_csv(bundles, index=False)
    args = ["--noise", "0.05", "--review"]
    assert main(["reconstruct", str(shot / "idx"), "--bundles", str(bundles), "--out", str(tmp_path / "cli"), "-q",
                 *args]) == 0
    reconstruct_shot(index_dir=str(shot / "idx"), bundles=str(bundles), out=str(tmp_path / "flow"), noise=0.05,
                     review=True, chunk_size=15)

    def warnings(out: Path) -> list[str]:
        meta = (out / "review" / "review_meta.js").read_text()
        return json.loads(meta[meta.index("{"):meta.rindex("}") + 1])["warnings"]

    said = warnings(tmp_path / "cli")
    assert any("1 of 110 markers are seen in fewer than" in w for w in said), said
    assert warnings(tmp_path / "flow") == said and len(set(said)) == len(said)
