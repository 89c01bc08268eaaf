"""What lgi wrote in a folder: the record by which it later replaces or removes only its own files.

Every folder lgi writes outputs into holds :data:`RECORD_FILE`, a JSON object listing each file it wrote there
(its path relative to the folder, size, modification time and, for a small file, SHA-256). Before a run replaces
or removes an entry of that folder, every file in the entry must match its record: a file of the same name that
lgi did not write (or one changed since) is never overwritten or deleted. A file matches when its size and
modification time are those recorded, or, for a small file whose time changed (copied with ``cp -r``), when its
content hash is; a large file copied with a new time is no longer recognised, and lgi refuses rather than
replace it.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
from collections.abc import Iterable
from pathlib import Path

RECORD_FILE = ".lgi-record.json"
#: Files up to this size are hashed when recorded (a run's tables and pages); larger ones (meshes, a take's OBJ
#: frames) are known by size and modification time, which costs no second read of gigabytes.
HASHED_BYTES = 1 << 20
FORMAT = "lgi-record"
#: A record being written (``<prefix><pid>-<thread>``): swept when its process is gone.
TEMP_PREFIX = f".{RECORD_FILE}.tmp-"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def fingerprint(path: Path) -> list:
    """``[size, mtime_ns, sha256 or None]`` of a file (the hash only up to :data:`HASHED_BYTES`)."""
    st = path.stat()
    return [st.st_size, st.st_mtime_ns, _sha256(path) if st.st_size <= HASHED_BYTES else None]


def _files(entry: Path) -> list[Path]:
    """The files of an entry: itself, or those under it (links not followed: a link is its own entry)."""
    if entry.is_dir() and not entry.is_symlink():
        return sorted(p for p in entry.rglob("*") if not p.is_dir() or p.is_symlink())
    return [entry]


def record_files(root: str | os.PathLike[str], names: Iterable[str]) -> dict[str, list]:
    """Fingerprints of the files under the entries ``names`` of ``root`` (relative POSIX path -> fingerprint)."""
    root = Path(root)
    return {f.relative_to(root).as_posix(): fingerprint(f) for name in names for f in _files(root / name)}


def read_record(folder: str | os.PathLike[str]) -> tuple[dict[str, list], dict[str, list]]:
    """The files recorded in ``folder`` (relative POSIX path -> fingerprint), and those of a commit under way
    (:func:`write_record`'s ``previous``); both empty when there is no record or it is not one."""
    path = Path(folder) / RECORD_FILE
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}, {}
    if not isinstance(data, dict) or data.get("format") != FORMAT or not isinstance(data.get("files"), dict):
        return {}, {}
    previous = data.get("previous")
    return data["files"], previous if isinstance(previous, dict) else {}


def write_record(folder: str | os.PathLike[str], files: dict[str, list], previous: dict[str, list] | None = None
                 ) -> None:
    """Write ``folder``'s record (atomically): ``files`` (:func:`record_files`), and while a commit replaces
    entries one by one, the ``previous`` files of those entries, which then still count as lgi's (a run killed
    half way through its commit leaves nothing the next run would refuse)."""
    folder = Path(folder)
    data = {"format": FORMAT, "version": 1, "files": dict(sorted(files.items()))}
    if previous:
        data["previous"] = dict(sorted(previous.items()))
    tmp = folder / f"{TEMP_PREFIX}{os.getpid()}-{threading.get_ident()}"
    tmp.write_text(json.dumps(data))
    os.replace(tmp, folder / RECORD_FILE)


def _matches(path: Path, recorded: list | None) -> bool:
    if not isinstance(recorded, list) or len(recorded) != 3 or path.is_symlink() or not path.is_file():
        return False
    st = path.stat()
    if st.st_size != recorded[0]:
        return False
    return st.st_mtime_ns == recorded[1] or (recorded[2] is not None and _sha256(path) == recorded[2])


def unrecorded(folder: str | os.PathLike[str], names: Iterable[str] | None = None) -> list[Path]:
    """The files under the entries ``names`` of ``folder`` (default: all of its entries but the record and lgi's
    temporaries) that its record does not vouch for: absent from it, or changed since. Entries that do not exist
    are skipped."""
    folder = Path(folder)
    files, previous = read_record(folder)
    entries = [folder / n for n in names] if names is not None else \
        [e for e in folder.iterdir() if e.name != RECORD_FILE and not e.name.startswith(TEMP_PREFIX)]
    out = []
    for entry in entries:
        if not (entry.exists() or entry.is_symlink()):
            continue
        for f in _files(entry):
            key = f.relative_to(folder).as_posix()
            if not (_matches(f, files.get(key)) or _matches(f, previous.get(key))):
                out.append(f)
    return out


def describe(files: list[Path], folder: Path) -> str:
    """A short list of the files :func:`unrecorded` found, for a message."""
    shown = ", ".join(str(f.relative_to(folder)) for f in files[:3])
    return shown + (f" and {len(files) - 3} more" if len(files) > 3 else "")
