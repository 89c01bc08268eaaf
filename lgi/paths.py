"""Where the files the project ships (``data/``) and the shared test data are found."""

from __future__ import annotations

import os
from pathlib import Path

from .errors import InputError

REPO_ROOT = Path(__file__).resolve().parents[1]


def shipped(name: str) -> Path:
    """Path of a file shipped in the repository's ``data/`` (lgi is installed from its source tree)."""
    path = REPO_ROOT / "data" / name
    if not path.is_file():
        raise InputError("shipped data file missing: install lgi from its source tree (pip install -e .)", path=path)
    return path


def shared_data(name: str) -> Path:
    """Path of a folder under the shared data directory (``$LGI_SHARED_DATA`` or ``../shared/data``)."""
    base = Path(os.environ.get("LGI_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))
    return base / name
