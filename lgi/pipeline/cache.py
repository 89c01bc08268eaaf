"""A content-addressed cache of pipeline stages, stored as plain files.

A stage's key is the SHA-256 of its name, its inputs' content hashes, its parameters and the version of
the code that computes it (a hash of every ``lgi`` source file, not only the calling task's). Results
are directories under ``root/<stage>/<key>``, written to a temporary name and renamed when complete, so
a run killed midway leaves nothing half-written and a re-run resumes from the stages that finished.
Nothing is pickled.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any

from lgi.io.atomic import atomic_dir

_PACKAGE = Path(__file__).resolve().parent


@lru_cache(maxsize=1)
def code_version() -> str:
    """SHA-256 of the lgi package's source files (names and contents), so any code change invalidates."""
    h = hashlib.sha256()
    for p in sorted(_PACKAGE.rglob("*.py")):
        h.update(p.relative_to(_PACKAGE).as_posix().encode())
        h.update(p.read_bytes())
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


def stage_key(stage: str, inputs: dict[str, Any]) -> str:
    """The key of a stage run: its name, inputs (hashes and parameters, JSON-able) and the code version."""
    blob = json.dumps({"stage": stage, "code": code_version(), "inputs": inputs}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


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

    def run(self, stage: str, inputs: dict[str, Any], make: Callable[[Path], None]) -> tuple[Path, bool]:
        """The result directory of ``stage`` for ``inputs``, computing it with ``make(dir)`` if absent.

        Returns
        -------
        path : Path
        hit : bool
            True if the result was already there (nothing was computed).
        """
        key = stage_key(stage, inputs)
        out = self.path(stage, key)
        if (out / ".complete").is_file():
            return out, True
        # A run killed midway leaves its temporary directory; it is never read, and goes now. (Two runs
        # computing the same stage and key at the same moment are not supported.)
        if out.parent.is_dir():
            import shutil

            for stale in out.parent.glob(f".{key}.tmp-*"):
                shutil.rmtree(stale, ignore_errors=True)
        with atomic_dir(out) as tmp:
            make(tmp)
            (tmp / ".complete").write_text(json.dumps({"stage": stage, "inputs": inputs}, sort_keys=True,
                                                      default=str, indent=1))
        return out, False
