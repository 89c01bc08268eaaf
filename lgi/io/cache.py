"""A content-addressed cache of pipeline stages, stored as plain files.

A stage's key is the SHA-256 of its name, its inputs' content hashes, its typed options and the version of
the code that computes it: the source of the stage's modules and of every lgi module they import, so a
comment added to the benchmark job recomputes nothing. Concurrent runs take turns on a lock per key (one
computes, the others then hit). ``lgi cache ls`` / ``lgi cache prune`` list and trim the results. Results
are directories under ``root/<stage>/<key>``, written to a temporary name and renamed when complete, so
a run killed midway leaves nothing half-written and a re-run resumes from the stages that finished.
Nothing is pickled.
"""

from __future__ import annotations

import ast
import contextlib
import fcntl
import hashlib
import inspect
import json
import os
import shutil
import time
from collections.abc import Callable, Iterator
from functools import cache
from pathlib import Path
from typing import Any

from lgi.io.atomic import atomic_dir

_PACKAGE = Path(__file__).resolve().parent.parent


def _module_file(name: str) -> Path | None:
    parts = name.split(".")[1:]
    if not parts:
        return _PACKAGE / "__init__.py"
    rel = Path(*parts)
    for cand in (_PACKAGE / rel.with_suffix(".py"), _PACKAGE / rel / "__init__.py"):
        if cand.is_file():
            return cand
    return None


@cache
def _imports(path: Path) -> tuple[str, ...]:
    """The lgi modules a source file imports, at module level or inside functions (lazy imports count)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.split(".")[0] == "lgi")
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "lgi":
            found.add(node.module)
            # ``from lgi.x import y`` may name a submodule y
            found.update(f"{node.module}.{a.name}" for a in node.names if _module_file(f"{node.module}.{a.name}"))
    return tuple(sorted(found))


def module_closure(modules: tuple[str, ...]) -> list[str]:
    """``modules`` and every lgi module they import, transitively (sorted)."""
    seen: set[str] = set()
    todo = list(modules)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        f = _module_file(name)
        if f is None:
            continue
        seen.add(name)
        parts = name.split(".")
        todo.extend(".".join(parts[:k]) for k in range(2, len(parts)))  # parent packages' __init__
        todo.extend(_imports(f))
    return sorted(seen)


@cache
def code_version(modules: tuple[str, ...] = ("lgi",)) -> str:
    """SHA-256 of the source of ``modules`` and of every lgi module they import (names and contents): a change
    to the code a stage runs invalidates its results, a change elsewhere (a comment in the benchmark job) does
    not."""
    h = hashlib.sha256()
    names = module_closure(modules) if modules != ("lgi",) else sorted(
        "lgi." + p.relative_to(_PACKAGE).with_suffix("").as_posix().replace("/", ".") for p in _PACKAGE.rglob("*.py"))
    for name in names:
        f = _module_file(name)
        if f is not None:
            h.update(name.encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def hash_file(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def hash_tree(path: str | os.PathLike[str], pattern: str = "*") -> str:
    """SHA-256 of the names and contents of the files matching ``pattern`` in a directory (sorted)."""
    root = Path(path)
    h = hashlib.sha256()
    for p in sorted(q for q in root.glob(pattern) if q.is_file()):
        h.update(p.name.encode())
        h.update(hash_file(p).encode())
    return h.hexdigest()


def stage_key(stage: str, inputs: dict[str, Any], code: tuple[str, ...] = ("lgi",)) -> str:
    """The key of a stage run: its name, inputs (hashes and typed options, JSON-able) and the version of the code
    it runs (``code``: the modules of the stage's function; see :func:`code_version`)."""
    blob = json.dumps({"stage": stage, "code": code_version(code), "inputs": inputs}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


@contextlib.contextmanager
def locked(path: Path) -> Iterator[None]:
    """An exclusive lock on ``path`` (created if absent) for the block: two runs computing or publishing the same
    thing take turns, the second then finds the first's result. The OS drops the lock of a killed process."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


class StageCache:
    """Stage results as directories under ``root``; see the module docstring.

    Parameters
    ----------
    root
        The cache directory (created when needed).
    """

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)

    def path(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def run(self, stage: str, inputs: dict[str, Any], make: Callable[[Path], None],
            code: tuple[str, ...] = ("lgi",)) -> tuple[Path, bool]:
        """The result directory of ``stage`` for ``inputs``, computing it with ``make(dir)`` if absent.

        Concurrent runs asking for the same stage and key take turns on a lock: one computes, the others wait
        and then find its result (a hit). ``code``: the modules whose source (with what they import) keys the
        result.

        Returns
        -------
        path : Path
        hit : bool
            True if the result was already there (nothing was computed).
        """
        # The make function's own source too: the stage's code around the library calls it makes.
        try:
            maker = hashlib.sha256(inspect.getsource(make).encode()).hexdigest()
        except (OSError, TypeError):
            maker = getattr(make, "__qualname__", "")
        key = stage_key(stage, {**inputs, "_make": maker}, code)
        out = self.path(stage, key)
        with locked(self.root / stage / f".{key}.lock"):
            if (out / ".complete").is_file():
                (out / ".complete").touch()  # last use, for lgi cache prune
                return out, True
            # atomic_dir removes the temporaries of killed runs (their process is gone), never a live run's.
            with atomic_dir(out) as tmp:
                make(tmp)
                (tmp / ".complete").write_text(json.dumps({"stage": stage, "inputs": inputs}, sort_keys=True,
                                                          default=str, indent=1))
        return out, False

    def entries(self) -> list[dict[str, Any]]:
        """Every complete result: stage, key, bytes, created and last used (POSIX seconds), newest use first."""
        rows = []
        if not self.root.is_dir():
            return rows
        for stage_dir in sorted(p for p in self.root.iterdir() if p.is_dir() and not p.name.startswith(".")):
            for d in stage_dir.iterdir():
                done = d / ".complete"
                if d.name.startswith(".") or not done.is_file():
                    continue
                size = sum(f.stat().st_size for f in d.rglob("*") if f.is_file())
                rows.append({"stage": stage_dir.name, "key": d.name, "bytes": size,
                             "created": d.stat().st_mtime, "used": done.stat().st_mtime, "path": str(d)})
        return sorted(rows, key=lambda r: -r["used"])

    def prune(self, keep: int | None = None, older_than_days: float | None = None,
              now: float | None = None) -> list[dict[str, Any]]:
        """Remove results: all but the ``keep`` most recently used of each stage, and/or those not used for
        ``older_than_days``. Returns the removed entries. A result being computed or read under its lock by
        another run is left alone."""
        now = time.time() if now is None else now
        by_stage: dict[str, int] = {}
        removed = []
        for e in self.entries():
            rank = by_stage[e["stage"]] = by_stage.get(e["stage"], 0) + 1
            old = older_than_days is not None and now - e["used"] > older_than_days * 86400
            if (keep is not None and rank > keep) or old:
                lock = self.root / e["stage"] / f".{e['key']}.lock"
                if not _try_lock_and_remove(lock, Path(e["path"]), shutil.rmtree):
                    continue
                removed.append(e)
        return removed


def _try_lock_and_remove(lock: Path, path: Path, remove: Callable[[Path], None]) -> bool:
    with open(lock, "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        try:
            remove(path)
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
    lock.unlink(missing_ok=True)
    return True
