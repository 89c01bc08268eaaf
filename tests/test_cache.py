"""The rebuild's stage cache: keyed by the code a stage runs (not the whole package), computed once under
concurrency, listed and pruned by ``lgi cache``."""

from __future__ import annotations

import os
import shutil
import threading
import time
from pathlib import Path

import pytest

from lgi.cli import main
from lgi.io import cache as cache_mod
from lgi.io.cache import StageCache, module_closure


def test_stage_code_excludes_the_command_line_and_the_benchmarks() -> None:
    for stage_modules in (("lgi.jobs.dataset",), ("lgi.index.build",), ("lgi.jobs.verify",)):
        closure = module_closure(stage_modules)
        assert stage_modules[0] in closure and "lgi.errors" in closure
        assert not [m for m in closure if m.startswith(("lgi.cli", "lgi.jobs.bench", "lgi.orchestration"))], closure


@pytest.fixture()
def package_copy(tmp_path: Path, monkeypatch) -> Path:
    """A copy of the lgi sources that the cache's code versions are computed from."""
    src = Path(cache_mod.__file__).resolve().parents[1]
    dst = tmp_path / "lgi"
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("__pycache__", "*.csv"))
    monkeypatch.setattr(cache_mod, "_PACKAGE", dst)
    for f in (cache_mod._imports, cache_mod.code_version):
        f.cache_clear()
    yield dst
    for f in (cache_mod._imports, cache_mod.code_version):
        f.cache_clear()


def test_a_comment_in_the_benchmark_job_recomputes_no_stage(package_copy: Path) -> None:
    stages = [("lgi.jobs.dataset",), ("lgi.index.build",), ("lgi.jobs.verify",)]
    before = [cache_mod.code_version(m) for m in stages]
    with open(package_copy / "jobs" / "bench.py", "a") as f:
        f.write("\n# a comment\n")
    cache_mod.code_version.cache_clear()
    assert [cache_mod.code_version(m) for m in stages] == before
    with open(package_copy / "index" / "cloud.py", "a") as f:  # imported by the index stages, not the import
        f.write("\n# a comment\n")
    cache_mod._imports.cache_clear()
    cache_mod.code_version.cache_clear()
    after = [cache_mod.code_version(m) for m in stages]
    assert after[1] != before[1]


def test_concurrent_runs_of_one_stage_compute_once(tmp_path: Path) -> None:
    calls, results = [], []

    def make(out: Path) -> None:
        calls.append(1)
        time.sleep(0.5)
        (out / "r.txt").write_text("x")

    def run() -> None:
        results.append(StageCache(tmp_path).run("s", {"a": 1}, make))

    threads = [threading.Thread(target=run) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1
    assert len({str(p) for p, _ in results}) == 1 and sorted(h for _, h in results) == [False, True, True]


def test_ls_and_prune(tmp_path: Path, capsys) -> None:
    cache = StageCache(tmp_path / ".cache")
    now = time.time()
    for k in range(3):
        path, _ = cache.run("read", {"k": k}, lambda out: (out / "raw.npz").write_bytes(b"0" * 1000))
        os.utime(path / ".complete", (now - 86400 * (10 - k), now - 86400 * (10 - k)))  # used 10, 9, 8 days ago
    cache.run("verify", {"k": 0}, lambda out: (out / "summary.json").write_text("{}"))
    assert main(["cache", "ls", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "total: 4 results" in out and out.count("read ") == 3
    assert main(["cache", "prune", str(tmp_path), "--keep", "1"]) == 0
    left = cache.entries()
    assert sorted(e["stage"] for e in left) == ["read", "verify"]
    assert now - left[-1]["used"] == pytest.approx(8 * 86400, abs=60)  # the most recently used read result
    assert main(["cache", "prune", str(tmp_path), "--older-than", "5"]) == 0
    assert [e["stage"] for e in cache.entries()] == ["verify"]
    assert main(["cache", "prune", str(tmp_path)]) == 2  # says what to prune
