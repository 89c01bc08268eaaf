"""A rebuild killed midway and started again resumes from what finished and writes identical outputs."""

import filecmp
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from lgi.dataset.markers import write_layout
from lgi.io.record import RECORD_FILE
from lgi.synthetic import actor as synth

# Files that describe a run (timings, which stages were cached), not the data: they may differ.
RUN_ONLY = ("build.json", "report.md", RECORD_FILE)

RUN = """
import sys
from flows.rebuild_dataset import rebuild_dataset

s = rebuild_dataset(sys.argv[1], sys.argv[2], markers=sys.argv[3], cache_dir=sys.argv[4])
print("STAGES", s["stages"])
"""


def _env(tmp: Path, api: str | None = None) -> dict:
    """A subprocess's environment: its own Prefect home, and the session's API when given (no server of its
    own to start)."""
    env = dict(os.environ)
    env.update(PREFECT_HOME=str(tmp / "prefect-home"), PREFECT_LOCAL_STORAGE_PATH=str(tmp / "prefect-storage"),
               PREFECT_LOGGING_LEVEL="WARNING", PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="180")
    if api:
        env["PREFECT_API_URL"] = api
    return env


# 27 s (kill a worker mid-rebuild and resume): in the default set, as users rely on resuming
def test_kill_and_resume(prefect_api: str, tmp_path: Path, obj_folder: Path, small_actor) -> None:
    root = Path(__file__).resolve().parents[1]
    layout, _ = synth.default_layout(small_actor)
    markers = tmp_path / "markers.csv"
    write_layout(markers, layout, small_actor.neutral)
    args = [str(obj_folder), str(tmp_path / "killed"), str(markers), str(tmp_path / "cache")]
    proc = subprocess.Popen([sys.executable, "-c", RUN, *args], cwd=root, env=_env(tmp_path, prefect_api),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    # Kill it as soon as the natural-neighbour stage has finished (later stages still to run).
    deadline = time.time() + 300
    natural = tmp_path / "cache" / "natural"
    while time.time() < deadline and proc.poll() is None:
        # A result is complete once renamed to its key: a hidden temporary already holds its .complete marker
        # (written last, then renamed), and killing then leaves nothing to reuse.
        if natural.is_dir() and any((d / ".complete").is_file() for d in natural.iterdir()
                                    if not d.name.startswith(".")):
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the flow finished before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    # Nothing half-written under a result's name: every stage directory present is complete (the
    # killed stage's work is in a hidden temporary, removed when the stage runs again).
    for d in (tmp_path / "cache").glob("*/[!.]*"):
        assert (d / ".complete").is_file(), d
    resumed = subprocess.run([sys.executable, "-c", RUN, *args], cwd=root, env=_env(tmp_path, prefect_api),
                             capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    import ast

    stages = ast.literal_eval(resumed.stdout.split("STAGES", 1)[1].strip())
    assert stages["read"] and stages["stabilise"] and stages["natural"]  # finished before the kill: reused
    assert not list((tmp_path / "cache").glob("*/.*.tmp-*"))  # the killed run's temporaries are gone
    clean = subprocess.run([sys.executable, "-c", RUN, str(obj_folder), str(tmp_path / "clean"), str(markers),
                            str(tmp_path / "cache-clean")], cwd=root, env=_env(tmp_path, prefect_api),
                           capture_output=True, text=True, timeout=600)
    assert clean.returncode == 0, clean.stderr[-3000:]
    a, b = tmp_path / "killed", tmp_path / "clean"
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.name not in RUN_ONLY)
    assert files and files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file() and p.name not in RUN_ONLY)
    assert all(filecmp.cmp(a / f, b / f, shallow=False) for f in files)
