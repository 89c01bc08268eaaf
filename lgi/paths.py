"""Where the files the project ships and the shared test data are found.

The shipped files (marker layouts) are package resources in ``lgi/data/`` (the repository's top-level
``data/`` links to them), so an installed wheel has them wherever it runs.
"""

from __future__ import annotations

import os
from pathlib import Path

from lgi.errors import InputError

REPO_ROOT = Path(__file__).resolve().parents[1]


def shipped(name: str) -> Path:
    """Path of a file lgi ships (a package resource in ``lgi/data/``)."""
    path = Path(__file__).resolve().parent / "data" / name
    if not path.is_file():
        raise InputError("shipped data file missing: the lgi installation is incomplete (reinstall it)", path=path)
    return path


def shared_data(name: str) -> Path:
    """Path of a folder under the shared data directory (``$LGI_SHARED_DATA`` or ``../shared/data``)."""
    base = Path(os.environ.get("LGI_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))
    return base / name
