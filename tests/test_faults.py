"""Faults of the machinery under a correct job: a full disk, a read-only stage cache, a killed worker, a restarted
Prefect server. Each case checks what must hold afterwards: the earlier outputs intact, nothing partial under a
final name, one clear message naming the path, and the next run succeeding without anyone cleaning up.

Full disks and read-only folders are small tmpfs mounts made by the test (root in a container can); where the
machine cannot make one, the case is skipped with the reason. See docs/faults.md."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

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
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


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
    (tmp_path / "job").mkdir()
    (tmp_path / "job" / "a.npz").write_bytes(b"earlier")
    with pytest.raises(StorageError, match=r"job/b\.csv: no space left"):
        with job_outputs(tmp_path / "job", ("a.npz", "b.csv")) as stage:
            (stage / "a.npz").write_bytes(b"new")
            (stage / "b.csv").write_text("partial")
            raise OSError(28, "No space left on device")
    assert [p.name for p in (tmp_path / "job").iterdir()] == ["a.npz"]
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

    from lgi.pipeline.cache import StageCache

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


def test_check_writable_probes_a_missing_folder_through_its_parent(tmp_path: Path) -> None:
    from lgi.errors import StorageError
    from lgi.io.atomic import check_writable

    check_writable(tmp_path / "a" / "b", "x", "y")
    assert not (tmp_path / "a").exists() and not list(tmp_path.iterdir())  # nothing made, nothing left
    with tmpfs(tmp_path / "ro", "1m") as disk:
        remount(disk, "ro")
        with pytest.raises(StorageError, match=r"ro/later: the stage cache cannot be written here \(read-only"):
            check_writable(disk / "later", "the stage cache", "fix it")
