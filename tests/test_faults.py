"""Faults of the machinery under a correct job: a full disk, a read-only stage cache, a killed worker, a restarted
Prefect server. Each case checks what must hold afterwards: the earlier outputs intact, nothing partial under a
final name, one clear message naming the path, and the next run succeeding without anyone cleaning up.

Full disks and read-only folders are small tmpfs mounts made by the test (root in a container can); where the
machine cannot make one, the case is skipped with the reason. See docs/faults.md."""

from __future__ import annotations

import contextlib
import filecmp
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from lgi.io.record import RECORD_FILE

ROOT = Path(__file__).resolve().parents[1]
LEFTOVER_MARKS = (".tmp-", ".old-", ".lgi-staging-", ".chunks-")


def _env(tmp: Path, api: str | None = None) -> dict:
    env = dict(os.environ)
    env.update(PREFECT_HOME=str(tmp / "prefect-home"), PREFECT_LOCAL_STORAGE_PATH=str(tmp / "prefect-storage"),
               PREFECT_LOGGING_LEVEL="WARNING", PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="180")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])
    if api:
        env["PREFECT_API_URL"] = api
    return env


@contextlib.contextmanager
def tmpfs(where: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` at ``where``, unmounted afterwards; skips the test where none can be mounted."""
    where.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)], capture_output=True,
                       text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root or CAP_SYS_ADMIN): {r.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def remount(where: Path, options: str) -> None:
    r = subprocess.run(["mount", "-o", f"remount,{options}", str(where)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def fill(where: Path, leave: int) -> None:
    """Fill the file system of ``where`` until ``leave`` bytes are free."""
    st = os.statvfs(where)
    free = st.f_bavail * st.f_frsize
    (where / "filler").write_bytes(b"\0" * max(0, free - leave))


def leftovers(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if any(m in p.name for m in LEFTOVER_MARKS)]


def snapshot(folder: Path) -> dict[str, bytes]:
    """The files' bytes (lgi's record of them aside: it holds their modification times)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != RECORD_FILE}


def lgi(*argv: str, cwd: Path, env: dict | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """The command as a user runs it (its own process: what reaches the terminal is what the test reads)."""
    return subprocess.run([sys.executable, "-c", "from lgi._entry import run; run()", *argv], cwd=cwd,
                          env=env or _env(cwd), capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def shot(tmp_path_factory) -> Path:
    """A small synthetic actor's index and a short shot's bundles (built once for the module)."""
    from lgi.cli import main

    d = tmp_path_factory.mktemp("shot")
    assert main(["synth", "--out", str(d / "s"), "--vertices", "1500", "--frames", "6", "-q"]) == 0
    assert main(["build", str(d / "s" / "dataset"), "--markers", str(d / "s" / "markers.csv"), "--out",
                 str(d / "index"), "-q"]) == 0
    return d


# --- a full disk --------------------------------------------------------------------------------------------


def test_full_disk_while_reconstruct_writes_meshes(shot: Path, tmp_path: Path) -> None:
    """lgi reconstruct into a folder on a full disk: exit 2, "no space left" naming meshes.npz, the earlier
    outputs byte for byte, no staging folder; with space again the same command succeeds as is."""
    args = (str(shot / "index"), "--bundles", str(shot / "s" / "bundles.csv"))
    first = lgi("reconstruct", *args, "--out", str(tmp_path / "ref"), "-q", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    with tmpfs(tmp_path / "disk", "2m") as disk:
        out = disk / "recon"
        shutil.copytree(tmp_path / "ref", out)  # the earlier run's outputs, on the disk about to be full
        before = snapshot(out)
        # Less room than meshes.npz (written first) needs.
        fill(disk, (tmp_path / "ref" / "meshes.npz").stat().st_size // 2)
        r = lgi("reconstruct", *args, "--out", str(out), "-q", cwd=tmp_path)
        assert r.returncode == 2, (r.returncode, r.stderr)
        errors = [line for line in r.stderr.splitlines() if "error" in line]
        assert "Traceback" not in r.stderr and len(errors) == 1, r.stderr
        assert "no space left on device" in r.stderr and str(out / "meshes.npz") in r.stderr, r.stderr
        assert snapshot(out) == before and not leftovers(disk)
        assert sorted(p.name for p in disk.iterdir()) == ["filler", "recon"]
        (disk / "filler").unlink()  # space again; nothing else is cleaned by hand
        r = lgi("reconstruct", *args, "--out", str(out), "-q", cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        assert snapshot(out) == before and not leftovers(disk)  # the same job, the same bytes


def test_full_scratch_folder_names_it_and_tmpdir(shot: Path, tmp_path: Path) -> None:
    """A full TMPDIR, where a take's bundles are spooled and its per-frame state kept: exit 2, one message naming
    the folder and TMPDIR, no output; with TMPDIR elsewhere the same command succeeds."""
    args = (str(shot / "index"), "--bundles", str(shot / "s" / "bundles.csv"), "--out", str(tmp_path / "out"),
            "-q")
    with tmpfs(tmp_path / "tmp", "1m") as tmp:
        # Room for Python's check that the folder is writable (else it quietly takes /tmp), not for the take.
        fill(tmp, 8192)
        env = _env(tmp_path) | {"TMPDIR": str(tmp)}
        r = lgi("reconstruct", *args, cwd=tmp_path, env=env)
        assert r.returncode == 2, (r.returncode, r.stderr)
        errors = [line for line in r.stderr.splitlines() if "error" in line]
        assert "Traceback" not in r.stderr and len(errors) == 1, r.stderr
        assert f"{tmp}: no space left on device" in r.stderr and "TMPDIR" in r.stderr, r.stderr
        assert not (tmp_path / "out").exists()
    r = lgi("reconstruct", *args, cwd=tmp_path)
    assert r.returncode == 0, r.stderr


def test_storage_error_names_the_output_for_writers_without_errno(tmp_path: Path) -> None:
    """Arrow reports a full disk as an OSError without errno; it is still a full disk, named by the output."""
    from lgi.errors import StorageError
    from lgi.io.atomic import atomic_file, job_outputs, storage_error

    arrow = OSError("Error writing bytes to file. Detail: [errno 28] No space left on device")
    assert isinstance(storage_error(arrow, tmp_path / "x.csv"), StorageError)
    assert storage_error(OSError(2, "No such file or directory"), tmp_path) is None
    with pytest.raises(StorageError, match=r"out\.csv: no space left on device"):
        with atomic_file(tmp_path / "out.csv") as t:
            t.write_text("partial")
            raise arrow
    assert not list(tmp_path.iterdir())
    with job_outputs(tmp_path / "job", ("a.npz", "b.csv")) as stage:
        (stage / "a.npz").write_bytes(b"earlier")
    with pytest.raises(StorageError, match=r"job/b\.csv: no space left"):
        with job_outputs(tmp_path / "job", ("a.npz", "b.csv")) as stage:
            (stage / "a.npz").write_bytes(b"new")
            (stage / "b.csv").write_text("partial")
            raise OSError(28, "No space left on device")
    assert sorted(p.name for p in (tmp_path / "job").iterdir()) == [RECORD_FILE, "a.npz"]
    assert (tmp_path / "job" / "a.npz").read_bytes() == b"earlier"


def _scans(obj_folder: Path, night: int) -> None:
    """New scans: one shape moved a little, so every stage of the rebuild misses the cache."""
    from lgi.io.obj import read_obj, write_obj

    m = read_obj(obj_folder / "pucker.obj")
    v = m.vertices + np.random.default_rng(night).normal(0, 1e-4, m.vertices.shape)
    write_obj(obj_folder / "pucker.obj", v, m.face_vertices, m.face_offsets, m.uvs, m.face_uvs)


def _cache_ok(cache: Path) -> list[dict]:
    """Every cache entry complete and loadable (its npz and JSON files read), and nothing half-written."""
    import json

    from lgi.io.cache import StageCache

    entries = StageCache(cache).entries()
    for e in entries:
        for f in Path(e["path"]).rglob("*"):
            if f.suffix == ".npz":
                with np.load(f, allow_pickle=False) as z:
                    [z[k] for k in z.files]
            elif f.suffix == ".json":
                json.loads(f.read_text())
    assert not leftovers(cache), leftovers(cache)
    assert all((d / ".complete").is_file() for d in cache.glob("*/[!.]*")), list(cache.glob("*/[!.]*"))
    return entries


def test_full_disk_while_rebuild_writes_the_stage_cache(prefect_harness, tmp_path: Path, obj_folder: Path,
                                                        layout_csv: Path) -> None:
    """The rebuild flow with its stage cache on a disk that fills: the flow fails at once (a full disk is not
    retried) with "no space left" naming the cache entry; the published dataset and index and the earlier cache
    entries are intact and load; with space again the next run succeeds and reuses nothing half-written."""
    from lgi.errors import StorageError
    from lgi.orchestration.rebuild import rebuild_dataset

    out = tmp_path / "out"
    with tmpfs(tmp_path / "disk", "16m") as disk:
        cache = disk / "cache"
        first = rebuild_dataset(str(obj_folder), str(out), markers=str(layout_csv), cache_dir=str(cache))
        published = snapshot(out / "index") | {f"dataset/{k}": v for k, v in snapshot(out / "dataset").items()}
        entries = _cache_ok(cache)
        assert len(entries) == 6
        _scans(obj_folder, 1)
        fill(disk, 64 * 1024)
        t0 = time.time()
        with pytest.raises(StorageError, match="no space left on device") as err:
            rebuild_dataset(str(obj_folder), str(out), markers=str(layout_csv), cache_dir=str(cache))
        assert str(cache) in str(err.value), err.value
        assert time.time() - t0 < 60  # failed at once, not after retries
        assert snapshot(out / "index") | {f"dataset/{k}": v for k, v in snapshot(out / "dataset").items()} == published
        assert {e["key"] for e in _cache_ok(cache)} >= {e["key"] for e in entries}
        assert not leftovers(out)
        (disk / "filler").unlink()
        again = rebuild_dataset(str(obj_folder), str(out), markers=str(layout_csv), cache_dir=str(cache))
        assert again["content_hash"] != first["content_hash"]
        assert len(_cache_ok(cache)) >= 11 and not leftovers(out)


# --- a read-only cache ---------------------------------------------------------------------------------------


def test_read_only_cache_is_refused_before_the_work(prefect_harness, tmp_path: Path, obj_folder: Path,
                                                    layout_csv: Path) -> None:
    """A stage cache that cannot be written (a read-only mount; root ignores permission bits) is refused before
    any stage runs, naming the folder and what to do; the outputs stay as they were; writable again, the next
    run succeeds."""
    from lgi.errors import StorageError
    from lgi.orchestration.rebuild import rebuild_dataset

    out = tmp_path / "out"
    # The cache where the flow and lgi import --flow keep it, OUT/.cache, as its own read-only mount.
    with tmpfs(out / ".cache", "16m") as cache:
        remount(cache, "ro")
        with pytest.raises(StorageError, match="the stage cache cannot be written here") as err:
            rebuild_dataset(str(obj_folder), str(out), markers=str(layout_csv))
        assert str(cache) in str(err.value) and "read-only file system" in str(err.value)
        assert "cache_dir" in str(err.value)
        assert [p.name for p in out.iterdir()] == [".cache"]  # refused before the work: nothing made
        # The command line says the same in one line, exit 2.
        r = lgi("import", str(obj_folder), "--out", str(out), "--markers", str(layout_csv), "--flow", cwd=tmp_path)
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert "read-only file system" in r.stderr and str(cache) in r.stderr, r.stderr
        assert [p.name for p in out.iterdir()] == [".cache"]
        remount(cache, "rw")
        s = rebuild_dataset(str(obj_folder), str(out), markers=str(layout_csv))
        assert not any(s["stages"].values()) and len(_cache_ok(cache)) == 6


def test_an_output_on_a_read_only_file_system_says_so(tmp_path: Path) -> None:
    with tmpfs(tmp_path / "ro", "1m") as disk:
        remount(disk, "ro")
        r = lgi("synth", "--out", str(disk / "out"), "--vertices", "500", "--frames", "2", "-q", cwd=tmp_path)
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert f"{disk}: the output cannot be written here: the file system is read-only" in r.stderr, r.stderr


def test_check_writable_probes_a_missing_folder_through_its_parent(tmp_path: Path) -> None:
    from lgi.errors import StorageError
    from lgi.io.atomic import check_writable

    check_writable(tmp_path / "a" / "b", "x", "y")
    assert not (tmp_path / "a").exists() and not list(tmp_path.iterdir())  # nothing made, nothing left
    with tmpfs(tmp_path / "ro", "1m") as disk:
        remount(disk, "ro")
        with pytest.raises(StorageError, match=r"ro/later: the stage cache cannot be written here \(read-only"):
            check_writable(disk / "later", "the stage cache", "fix it")


# --- a killed worker ----------------------------------------------------------------------------------------

SHOT_RUN = """
import sys
from flows.reconstruct_shot import reconstruct_shot

reconstruct_shot(sys.argv[1], sys.argv[2], sys.argv[3], chunk_size=int(sys.argv[4]),
                 dask_address=sys.argv[5] if sys.argv[5] != "-" else None)
print("COMPLETED")
"""


def _dask_workers(pid: int) -> list:
    """The worker processes of a LocalCluster started by process ``pid`` (its nannies spawn them)."""
    import psutil

    return [c for c in psutil.Process(pid).children(recursive=True)
            if "spawn_main" in " ".join(c.cmdline()) and "resource_tracker" not in " ".join(c.cmdline())]


@pytest.mark.slow  # about 2-3 min: three runs of a 90-frame shot, two of them on a Dask LocalCluster
def test_killed_dask_worker_mid_shot(prefect_api: str, tmp_path: Path) -> None:
    """SIGKILL to a Dask worker of reconstruct-shot (dask_address local:2) while its chunks run. Dask's nanny
    starts a new worker and the scheduler runs the lost chunks again (the chunk tasks only read their inputs and
    write their own files atomically), so the run completes, or fails with its error; either way the next run
    gives the undisturbed run's files byte for byte, with nothing left behind."""
    from lgi.cli import main

    assert main(["synth", "--out", str(tmp_path / "s"), "--vertices", "1500", "--frames", "90", "-q"]) == 0
    assert main(["build", str(tmp_path / "s" / "dataset"), "--markers", str(tmp_path / "s" / "markers.csv"),
                 "--out", str(tmp_path / "index"), "-q"]) == 0
    env = _env(tmp_path, prefect_api)

    def run(out: str, dask: str) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-c", SHOT_RUN, str(tmp_path / "index"),
                                 str(tmp_path / "s" / "bundles.csv"), str(tmp_path / out), "10", dask],
                                cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                start_new_session=True)

    clean = run("clean", "-")
    assert clean.wait(timeout=900) == 0, clean.stderr.read()[-3000:]
    killed = run("recon", "local:2")
    victim = None
    deadline = time.time() + 600
    while time.time() < deadline and killed.poll() is None and victim is None:
        # Once a chunk has been chosen, the workers are in the middle of the shot.
        if list(tmp_path.glob(".recon.chunks-*/*.npz")):
            workers = _dask_workers(killed.pid)
            if workers:
                victim = workers[0]
                victim.send_signal(signal.SIGKILL)
        time.sleep(0.2)
    assert victim is not None, "the shot ended before a Dask worker could be killed"
    out, err = killed.communicate(timeout=900)
    first = "COMPLETED" if killed.returncode == 0 else "FAILED"
    print(f"OUTCOME after SIGKILL of Dask worker {victim.pid}: {first} (exit {killed.returncode})")
    if killed.returncode != 0:
        assert "Traceback" in err or err  # a flow run that fails says why (the run's log)
        again = run("recon", "local:2")
        assert again.wait(timeout=900) == 0, again.stderr.read()[-3000:]
    a, b = tmp_path / "clean", tmp_path / "recon"
    assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())
    assert all(filecmp.cmp(a / f.name, b / f.name, shallow=False) for f in a.iterdir()
               if f.is_file() and f.name != RECORD_FILE)  # the record holds the files' times
    assert not leftovers(tmp_path), leftovers(tmp_path)


# --- a restarted server -------------------------------------------------------------------------------------

REBUILD_RUN = """
import sys
from flows.rebuild_dataset import rebuild_dataset

s = rebuild_dataset(sys.argv[1], sys.argv[2], markers=sys.argv[3], cache_dir=sys.argv[4])
print("STAGES", s["stages"])
"""
RUN_ONLY = ("build.json", "report.md", RECORD_FILE)  # describe the run (timings, cache hits), not the data


def _server(tmp: Path, env: dict, port: int, log: str) -> subprocess.Popen:
    from tests.test_deploy import _bin, _healthy, _start

    server = _start([_bin("prefect"), "server", "start"], tmp, env, tmp / log)
    deadline = time.time() + 300
    while not _healthy(f"http://127.0.0.1:{port}/api"):
        assert server.poll() is None, (tmp / log).read_text()[-3000:]
        assert time.time() < deadline, "the Prefect server did not start within 300 s"
        time.sleep(0.5)
    return server


@pytest.mark.slow  # about 3-5 min: a server started twice, three rebuilds
def test_server_restarted_during_a_rebuild(tmp_path: Path, obj_folder: Path, layout_csv: Path) -> None:
    """The local Prefect server stopped and started again while a rebuild flow runs against it. What must hold:
    the run either rides it out (the client retries its API calls) or fails with its error, never hangs; the
    outputs are whole (the earlier ones, or the new ones) with nothing partial; a re-run completes and gives the
    bytes of an undisturbed rebuild."""
    import httpx

    from tests.test_deploy import _free_port, _stop

    port = _free_port()
    api = f"http://127.0.0.1:{port}/api"
    env = {k: v for k, v in _env(tmp_path).items() if not k.startswith("PREFECT_API_URL")}
    env.update(PREFECT_HOME=str(tmp_path / "server-home"), PREFECT_SERVER_API_PORT=str(port))
    server = _server(tmp_path, env, port, "server.log")
    run_env = dict(_env(tmp_path, api))
    args = [str(obj_folder), str(tmp_path / "out"), str(layout_csv), str(tmp_path / "cache")]
    try:
        proc = subprocess.Popen([sys.executable, "-c", REBUILD_RUN, *args], cwd=ROOT, env=run_env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
        deadline = time.time() + 600
        while time.time() < deadline and proc.poll() is None:
            if any((d / ".complete").is_file() for d in (tmp_path / "cache").glob("read/*")):
                break
            time.sleep(0.1)
        assert proc.poll() is None, "the rebuild ended before the server could be stopped"
        t_down = time.time()
        _stop(server)
        time.sleep(5)
        server = _server(tmp_path, env, port, "server2.log")
        outage = time.time() - t_down
        out, err = proc.communicate(timeout=900)  # never hangs
        states = [r["state"]["type"] for r in httpx.post(f"{api}/flow_runs/filter", json={}, timeout=30).json()]
        print(f"OUTCOME server down {outage:.0f} s: the rebuild exited {proc.returncode}; flow run states {states}")
        for d in (tmp_path / "cache").glob("*/[!.]*"):
            assert (d / ".complete").is_file(), d
        assert not leftovers(tmp_path / "out") if (tmp_path / "out").exists() else True
        if proc.returncode != 0:
            assert err.strip() and "STAGES" not in out
            again = subprocess.run([sys.executable, "-c", REBUILD_RUN, *args], cwd=ROOT, env=run_env,
                                   capture_output=True, text=True, timeout=900)
            assert again.returncode == 0, again.stderr[-3000:]
        clean = subprocess.run([sys.executable, "-c", REBUILD_RUN, str(obj_folder), str(tmp_path / "clean"),
                                str(layout_csv), str(tmp_path / "cache-clean")], cwd=ROOT, env=run_env,
                               capture_output=True, text=True, timeout=900)
        assert clean.returncode == 0, clean.stderr[-3000:]
    finally:
        _stop(server)
    a, b = tmp_path / "out", tmp_path / "clean"
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.name not in RUN_ONLY)
    assert files and files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file() and p.name not in RUN_ONLY)
    assert all(filecmp.cmp(a / f, b / f, shallow=False) for f in files)
    assert not leftovers(tmp_path / "out") and not leftovers(tmp_path / "cache")


# --- a killed Prefect worker --------------------------------------------------------------------------------


def test_every_deployment_sends_the_heartbeats_the_automation_waits_for() -> None:
    import yaml

    from lgi.orchestration.deploy import HEARTBEAT_SECONDS, SILENT_SECONDS

    config = yaml.safe_load((ROOT / "prefect.yaml").read_text())
    assert any("lgi.orchestration.deploy.crash_silent_runs" in step for step in config["build"])
    for d in config["deployments"]:
        beat = d["work_pool"]["job_variables"]["env"]["PREFECT_FLOWS_HEARTBEAT_FREQUENCY"]
        assert int(beat) == HEARTBEAT_SECONDS < SILENT_SECONDS, d["name"]


@pytest.mark.slow  # about 4-6 min: a server, prefect deploy, two workers, two runs of a 90-frame shot
def test_killed_prefect_worker_mid_shot(tmp_path: Path) -> None:
    """SIGKILL to the process worker and the flow run it started (the machine's processes gone at once, as when
    a farm node dies) in the middle of a reconstruct-shot deployment run. What must hold: nothing partial under
    the shot's names, and a re-run of the deployment on a new worker completes with the files of an undisturbed
    run, byte for byte, sweeping the killed run's working folders. The killed run's state is reported (see
    docs/faults.md: no heartbeat is configured, so the server keeps it Running)."""
    import httpx

    from lgi.cli import main
    from lgi.orchestration.deploy import SILENT_SECONDS
    from tests.test_deploy import _bin, _free_port, _healthy, _readme_commands, _run_deployment, _start, _stop

    data = tmp_path / "data"
    shot = data / "shots" / "shot001"
    assert main(["synth", "--out", str(tmp_path / "s"), "--vertices", "1500", "--frames", "90", "-q"]) == 0
    assert main(["build", str(tmp_path / "s" / "dataset"), "--markers", str(tmp_path / "s" / "markers.csv"),
                 "--out", str(data / "datasets" / "ict" / "index"), "-q"]) == 0
    shot.mkdir(parents=True)
    shutil.copyfile(tmp_path / "s" / "bundles.csv", shot / "bundles.csv")
    # The undisturbed run: the plain command with the deployment's options (the flow gives its bytes).
    assert main(["reconstruct", str(data / "datasets" / "ict" / "index"), "--bundles", str(shot / "bundles.csv"),
                 "--out", str(tmp_path / "clean"), "--chunk-size", "10", "--review", "-q"]) == 0

    port = _free_port()
    api = f"http://127.0.0.1:{port}/api"
    env = {k: v for k, v in _env(tmp_path).items() if not k.startswith(("PREFECT_API_URL", "LGI_PROJECT_DIR"))}
    env.update(PREFECT_HOME=str(tmp_path / "home"), PREFECT_SERVER_API_PORT=str(port))
    server = _start([_bin("prefect"), "server", "start"], tmp_path, env, tmp_path / "server.log")
    env["PREFECT_API_URL"] = api
    worker = None
    params = {"chunk_size": 10, "usd": False, "plot": False}
    try:
        deadline = time.time() + 300
        while not _healthy(api):
            assert server.poll() is None and time.time() < deadline, (tmp_path / "server.log").read_text()[-3000:]
            time.sleep(1)
        deploy, start_worker = _readme_commands()
        r = subprocess.run([_bin("prefect"), "variable", "set", "lgi_data_root", str(data)], env=env,
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        r = subprocess.run(deploy, shell=True, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
        worker = _start(start_worker, tmp_path, env, tmp_path / "worker.log")
        dep = httpx.get(f"{api}/deployments/name/reconstruct-shot/reconstruct-shot", timeout=10).json()
        run = httpx.post(f"{api}/deployments/{dep['id']}/create_flow_run", json={"parameters": params},
                         timeout=10).json()
        deadline = time.time() + 600
        while time.time() < deadline and not list(shot.glob(".recon.chunks-*/choice_*.npz")):
            assert worker.poll() is None, (tmp_path / "worker.log").read_text()[-3000:]
            time.sleep(0.2)
        assert list(shot.glob(".recon.chunks-*/choice_*.npz")), "the run never reached its chunks"
        # The worker and the flow run it started (the process worker starts it in a session of its own).
        import psutil

        procs = [psutil.Process(worker.pid), *psutil.Process(worker.pid).children(recursive=True)]
        assert any("flow" in " ".join(p.cmdline()) or "prefect" in " ".join(p.cmdline()) for p in procs[1:])
        for p in procs:
            with contextlib.suppress(psutil.NoSuchProcess):
                p.kill()
        worker.wait()
        # Its heartbeats stop; the automation made by prefect deploy marks it Crashed.
        t_kill, state = time.time(), "RUNNING"
        while state == "RUNNING" and time.time() < t_kill + SILENT_SECONDS + 120:
            time.sleep(2)
            state = httpx.get(f"{api}/flow_runs/{run['id']}", timeout=10).json()["state"]["type"]
        print(f"OUTCOME the killed run: {state} {time.time() - t_kill:.0f} s after SIGKILL")
        assert state == "CRASHED", state
        assert not (shot / "recon").exists()  # nothing under the shot's final names
        worker = _start(start_worker, tmp_path, env, tmp_path / "worker2.log")
        again = _run_deployment(api, "reconstruct-shot", params)
        assert again["state"]["type"] == "COMPLETED", (again["state"], (tmp_path / "worker2.log").read_text()[-3000:])
    finally:
        if worker is not None:
            _stop(worker)
        _stop(server)
    a, b = tmp_path / "clean", shot / "recon"
    assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())
    # The files (the review page is a folder: the flow writes it, as the plain command with --review).
    assert all(filecmp.cmp(a / f.name, b / f.name, shallow=False) for f in a.iterdir()
               if f.is_file() and f.name != RECORD_FILE)
    assert not leftovers(data), leftovers(data)
