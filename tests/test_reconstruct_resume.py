"""A take stopped at any moment resumes from its last checkpoint when the same command is run again, and the
outputs are those of a run never stopped, bit for bit."""

from __future__ import annotations

import filecmp
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgi.cli import main
from lgi.io.record import RECORD_FILE

FILES = ("meshes.npz", "diagnostics.csv", "per_frame.csv", "run.json")
# The command line with a checkpoint after every block of 8 frames: a small shot stops between checkpoints.
RUNNER = """
import sys
import lgi.jobs.reconstruct.run as run
run.CHECKPOINT_SECONDS = 0.0
run.BLOCK_FRAMES = 8
from lgi.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.fixture(scope="module")
def shot(tmp_path_factory) -> Path:
    t = tmp_path_factory.mktemp("resume")
    assert main(["synth", "--out", str(t / "s"), "--vertices", "2500", "--frames", "60", "-q"]) == 0
    assert main(["build", str(t / "s" / "dataset"), "--markers", str(t / "s" / "markers.csv"), "--out",
                 str(t / "idx"), "-q", "--jaw-rig", str(t / "s" / "jaw_rig.npz")]) == 0
    d = pd.read_csv(t / "s" / "bundles.csv")
    rng = np.random.default_rng(5)
    for c in ("x", "y", "z"):
        d[c] += rng.normal(0.0, 0.003, len(d))
    d.drop(index=rng.choice(len(d), len(d) // 30, replace=False)).to_csv(t / "noisy.csv", index=False)
    (t / "runner.py").write_text(RUNNER)
    return t


def _run(shot: Path, out: Path, extra: list[str], quiet: bool = True) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(shot / "runner.py"), "reconstruct", str(shot / "idx"), "--bundles",
                             str(shot / "noisy.csv"), "--out", str(out), *(["-q"] if quiet else []), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _stop_after_checkpoints(proc: subprocess.Popen, out: Path, checkpoints: int, how: int) -> int:
    """Stop ``proc`` with signal ``how`` once its staging folder has seen ``checkpoints`` checkpoints; returns
    the frames its last one holds."""
    import json

    seen: set[int] = set()
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        for note in out.glob(".lgi-staging-*/.resume.json"):
            try:
                seen.add(json.loads(note.read_text())["done"])
            except (OSError, ValueError):
                pass
        if len(seen) >= checkpoints:
            proc.send_signal(how)
            proc.wait(60)
            return max(seen)
        time.sleep(0.02)
    raise AssertionError(f"the run ended before {checkpoints} checkpoints: {proc.stderr.read()}")


@pytest.mark.parametrize("extra", [["--max-gap", "3"], ["--smooth", "3", "--obj"]], ids=["plain", "smoothed"])
def test_a_killed_run_resumes_to_the_same_bits(shot: Path, extra: list[str]) -> None:
    whole = shot / f"whole{len(extra)}"
    p = _run(shot, whole, extra)
    assert p.wait(240) == 0, p.stderr.read()
    out = shot / f"stopped{len(extra)}"
    done = _stop_after_checkpoints(_run(shot, out, extra), out, 3, signal.SIGKILL)
    assert 0 < done < 60
    assert not (out / "meshes.npz").exists()  # nothing published by the stopped run
    p = _run(shot, out, extra, quiet=False)
    said, err = p.communicate(timeout=240)
    assert p.returncode == 0, err
    assert f"its {done} frames written are kept" in said
    for name in FILES:
        assert filecmp.cmp(whole / name, out / name, shallow=False), name
    if "--obj" in extra:
        assert sorted(p.name for p in (out / "obj").iterdir()) == sorted(p.name for p in (whole / "obj").iterdir())
        assert all(filecmp.cmp(whole / "obj" / f.name, f, shallow=False) for f in (out / "obj").iterdir())
    # The stopped run's staging folder was taken over, then published: lgi's record alone is left.
    assert [p.name for p in out.glob(".lgi-*")] == [RECORD_FILE]


def test_an_interrupted_run_resumes_and_another_job_does_not(shot: Path) -> None:
    out = shot / "interrupted"
    _stop_after_checkpoints(_run(shot, out, ["--max-gap", "3"]), out, 2, signal.SIGINT)
    assert list(out.glob(".lgi-staging-*/.resume.json"))  # kept for the same command
    # Another job into the same folder (other options) does not take it over, and sweeps it.
    p = _run(shot, out, ["--max-gap", "2"], quiet=False)
    said, err = p.communicate(timeout=240)
    assert p.returncode == 0, err
    assert "resumed" not in said
    assert [p.name for p in out.glob(".lgi-*")] == [RECORD_FILE]


def test_a_killed_flow_resumes_from_its_chunks(shot: Path, prefect_api: str, tmp_path: Path) -> None:
    """``--flow``: the chunks a killed run chose and finished are taken over by the same command, and the
    outputs are the plain run's."""
    import os

    env = dict(os.environ, PREFECT_API_URL=prefect_api, PREFECT_HOME=str(tmp_path / "home"),
               PREFECT_LOGGING_LEVEL="INFO", PREFECT_SERVER_ANALYTICS_ENABLED="false")
    cmd = [sys.executable, str(shot / "runner.py"), "reconstruct", str(shot / "idx"), "--bundles",
           str(shot / "noisy.csv"), "--flow", "--chunk-size", "6", "--max-gap", "3"]
    plain = shot / "whole-flow"
    p = _run(shot, plain, ["--max-gap", "3"])
    assert p.wait(240) == 0, p.stderr.read()
    out = shot / "flow"
    proc = subprocess.Popen([*cmd, "--out", str(out)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if len(list(out.parent.glob(f".{out.name}.chunks-*/choice_*.npz"))) >= 4:
            os.killpg(proc.pid, signal.SIGKILL)
            break
        time.sleep(0.02)
    proc.wait(60)
    assert proc.returncode == -signal.SIGKILL, "the flow ended before it could be killed"
    again = subprocess.run([*cmd, "--out", str(out)], env=env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "resuming a stopped run of this shot" in again.stdout + again.stderr
    # ... and the command's own report says so (Prefect's log is off by default)
    assert re.search(r"resumed a stopped run of the same command: its [1-9]\d* chunks chosen", again.stdout)
    for name in FILES:
        assert filecmp.cmp(plain / name, out / name, shallow=False), name
    assert not list(out.parent.glob(f".{out.name}.chunks-*"))
