"""Atomic output: write to a temporary sibling, then rename into place.

A crash, a kill or an exception midway leaves no partial file or directory under the final name. Every
temporary carries the writing process's id (``.NAME.tmp-<pid>-<random>``); a later run removes the
temporaries of processes that no longer exist (a killed run's leftovers), never those of a live one.
"""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import json
import logging
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar

from lgi.errors import InputError, StorageError
from lgi.io.record import RECORD_FILE, describe, read_record, record_files, unrecorded, write_record
from lgi.io.record import TEMP_PREFIX as RECORD_TEMP

F = TypeVar("F", bound=Callable[..., Any])

# Failures of the machine, not of the data: the same write fails again until space is freed or the file system
# remounted, so they become one message naming the output instead of a writer's bare "[errno 28]".
_STORAGE = {errno.ENOSPC: "no space left on device", errno.EDQUOT: "disk quota exceeded",
            errno.EROFS: "read-only file system"}


def _free_mb(path: Path) -> str:
    for p in (path, *path.parents):
        with contextlib.suppress(OSError):
            st = os.statvfs(p)
            return f" ({st.f_bavail * st.f_frsize / 1e6:.1f} MB were free)"
    return ""


def storage_error(exc: BaseException, path: str | os.PathLike[str], done: str | None = None) -> StorageError | None:
    """``exc`` (or an error it was raised from) as a :class:`StorageError` naming ``path``, when it is a full
    disk, an exceeded quota or a read-only file system; else None. Writers that report through their own
    ``OSError`` without an errno (Arrow's "Error writing bytes to file. Detail: [errno 28] ...") count too.
    ``done`` ends the message (default: that nothing was written under the output's name)."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, StorageError):
            return seen
        if isinstance(seen, OSError):
            code = seen.errno
            if code is None:
                text = str(seen)
                code = next((c for c in _STORAGE if f"[errno {c}]" in text.lower() or os.strerror(c) in text), None)
            if code in _STORAGE:
                where = Path(path)
                if done is None:
                    done = "; nothing was written under this name and what was there before is unchanged"
                return StorageError(where, _STORAGE[code], (_free_mb(where) if code != errno.EROFS else "") + done)
        seen = seen.__cause__ or seen.__context__
    return None


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def check_writable(folder: str | os.PathLike[str], what: str, remedy: str) -> None:
    """Refuse ``folder`` (made later if absent: then its nearest existing parent) when no file can be created in
    it: a read-only mount, an immutable folder, missing permission. Probed by creating an unnamed temporary
    file, as root passes permission checks that a real write then fails; nothing is left behind."""
    probe = Path(folder).absolute()
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        with tempfile.TemporaryFile(dir=probe):
            pass
    except OSError as exc:
        reason = _STORAGE.get(exc.errno or 0, exc.strerror or str(exc)).lower()
        raise StorageError(folder, f"{what} cannot be written here ({reason})", f": {remedy}") from exc


def stopped(name: str, prefix: str) -> bool:
    """Whether the entry ``name``, ``<prefix><pid>-...``, is a process's that is gone."""
    pid = name[len(prefix):].split("-", 1)[0]
    return name.startswith(prefix) and pid.isdigit() and not _alive(int(pid))


def sweep(parent: Path, prefix: str) -> int:
    """Remove the entries of ``parent`` named ``<prefix><pid>-...`` whose process is gone; returns how many."""
    removed = 0
    if not parent.is_dir():
        return 0
    for entry in parent.iterdir():
        if not stopped(entry.name, prefix):
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
        removed += 1
    return removed


def make_temp_dir(parent: Path, prefix: str) -> Path:
    """A new directory ``<prefix><pid>-<random>`` in ``parent`` with the permissions a plain ``mkdir`` gives."""
    tmp = Path(tempfile.mkdtemp(prefix=f"{prefix}{os.getpid()}-", dir=parent))
    # mkdtemp makes 0700 directories; outputs should follow the user's umask like any other file.
    tmp.chmod(0o777 & ~_umask())
    return tmp


def _fsync_tree(path: Path) -> None:
    """Flush a file, or every file of a directory, to disk (a rename must not publish data still in cache)."""
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    for f in files:
        fd = os.open(f, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _ours(name: str, owned: tuple[str, ...]) -> bool:
    """An entry an output directory of this kind may hold: one of its ``owned`` names (fnmatch patterns) or a
    temporary of an lgi run."""
    if name == RECORD_FILE or any(fnmatch.fnmatchcase(name, pat) for pat in owned):
        return True
    return name.startswith(".") and any(t in name for t in (".tmp-", ".old-", ".lgi-staging-", ".chunks-"))


def _resolved(p: str | os.PathLike[str]) -> Path:
    return Path(os.path.abspath(Path(p).expanduser())).resolve()


IMAGES = ("*.png", "*.jpg", "*.jpeg", "*.tif", "*.tiff", "*.bmp", "*.exr")


def files_in(folder: str | os.PathLike[str] | None, patterns: tuple[str, ...], recursive: bool = False) -> list[Path]:
    """The files of ``folder`` matching ``patterns`` (what a run reads there: listed as its inputs, so that no
    output lands on one of them)."""
    if not folder or not Path(folder).is_dir():
        return []
    root = Path(folder)
    return [p for pat in patterns for p in (root.rglob(pat) if recursive else root.glob(pat)) if p.is_file()]


def _not_empty(path: str | os.PathLike[str]) -> None:
    if isinstance(path, str) and not path.strip():
        # Path("") is the current folder: an empty option (a script's unset variable) would write there.
        raise InputError("the output path is empty: give a file or folder")
    try:
        os.fspath(path).encode("utf-8")
    except UnicodeEncodeError:
        # Bytes that are not UTF-8 (kept by Python as lone surrogates): the run's records (run.json) cannot hold
        # the path, which would fail only after the work.
        raise InputError("the output path is not UTF-8 text: rename it", path=os.fsdecode(os.fsencode(path))
                         .encode("utf-8", "backslashreplace").decode("utf-8")) from None


def check_output(path: str | os.PathLike[str], kind: str = "dir", *, inputs: Iterable[Any] = (),
                 owned: tuple[str, ...] | None = None, what: str = "lgi output", recorded: bool = True) -> None:
    """Refuse, before any work, an output path that cannot become a ``kind`` ("dir" or "file") output.

    Refused: the other kind is there; the nearest existing folder is not writable; the output is one of the
    run's ``inputs`` (files and folders; list the files read inside a folder with :func:`files_in`) or
    contains one (it would be replaced by the output); and, for a directory replaced as a
    whole (``owned`` given: the fnmatch patterns of what ``what`` holds), an existing directory holding anything
    else, or (``recorded``) files its record (:mod:`lgi.io.record`) does not vouch for: a folder that is not an
    earlier output of this kind is never wiped.
    """
    _not_empty(path)
    p = Path(path)
    if p.exists() or p.is_symlink():
        if kind == "dir" and not p.is_dir():
            raise InputError("the output must be a directory; a file of that name exists", path=p)
        if kind == "file" and p.is_dir():
            raise InputError("the output must be a file; a directory of that name exists", path=p)
    parent = p if (kind == "dir" and p.is_dir()) else p.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError("cannot create the output: a file is in its path", path=parent)
    if not os.access(parent, os.W_OK | os.X_OK):
        if os.statvfs(parent).f_flag & os.ST_RDONLY:
            raise InputError("the output cannot be written here: the file system is read-only", path=parent)
        raise InputError("the output cannot be written here (permission denied)", path=parent)
    target = _resolved(p)
    for inp in inputs:
        if inp is None or inp == "":
            continue
        src = _resolved(inp)
        if src == target or target in src.parents:
            raise InputError(f"the {what} would replace this run's input {inp}: choose another path", path=p)
    if owned is not None and kind == "dir" and p.is_dir():
        foreign = sorted(e.name for e in p.iterdir() if not _ours(e.name, owned))
        if foreign:
            shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
            raise InputError(f"the folder exists and holds entries that are not an {what}'s "
                             f"({shown}); lgi replaces this output as a whole, so it will not write here: remove "
                             "them or choose another path", path=p)
        if recorded and not _legacy_store(p):
            check_recorded(p, None, f"lgi replaces this {what} as a whole")


def check_job_folder(out: str | os.PathLike[str], outputs: tuple[str, ...], contents: dict[str, tuple[str, ...]],
                     inputs: Iterable[Any] = ()) -> None:
    """Refuse, before any work, a job's output folder ``out`` that cannot hold its ``outputs`` (entry names; those
    in ``contents`` are folders, with the patterns of what they hold), or whose outputs would replace one of the
    run's ``inputs``: :func:`check_output` on the folder and on each entry, :func:`check_not_in_store`, then
    :func:`check_contents` (after, so that an input there is named as one)."""
    inputs = list(inputs)
    check_output(out, "dir", inputs=inputs)
    check_not_in_store(out)
    for name in outputs:
        check_output(Path(out) / name, "dir" if name in contents else "file", inputs=inputs)
    check_contents(out, contents, outputs)


def check_recorded(folder: Path, names: Iterable[str] | None, why: str) -> None:
    """Refuse files under the entries ``names`` of ``folder`` (default: all) that lgi has no record of writing
    there (:func:`lgi.io.record.unrecorded`)."""
    foreign = unrecorded(folder, names)
    if foreign:
        raise InputError(f"holds files that lgi has no record of writing ({describe(foreign, folder)}: not in its "
                         f"{RECORD_FILE}, or changed since), and {why}: move them away or choose another output "
                         "folder", path=folder)


def remove_recorded(folder: Path, owned: tuple[str, ...], what: str) -> bool:
    """Remove ``folder``, an output lgi replaces as a whole (the fnmatch patterns ``owned`` of what it holds), if
    every file in it is one lgi recorded writing there; otherwise leave it and say so. Returns whether it went."""
    if not folder.is_dir() or folder.is_symlink():
        return False
    foreign = unrecorded(folder) or [e for e in folder.iterdir() if not _ours(e.name, owned)]
    if foreign:
        logging.getLogger(__name__).warning(
            "%s is left as it is, though it does not match this run: it holds files that lgi has no record of "
            "writing there (%s)", folder, describe(foreign, folder))
        return False
    shutil.rmtree(folder)
    return True


def _legacy_store(folder: Path) -> bool:
    """An index or shape dataset folder written before lgi kept records: known by its manifest's format."""
    if (folder / RECORD_FILE).is_file():
        return False
    try:
        return json.loads((folder / "manifest.json").read_text()).get("format") in STORE_FORMATS
    except (OSError, ValueError, AttributeError):
        return False


#: The manifests' formats of the folders lgi rebuilds as a whole (an index, a shape dataset): nothing else may be
#: written inside them, or the next ``lgi build`` or ``lgi import`` into the folder refuses the foreign entry.
STORE_FORMATS = {"lgi-index": "an LGI index", "lgi-shape-dataset": "a shape dataset"}


def check_not_in_store(path: str | os.PathLike[str], option: str = "--out") -> None:
    """Refuse an output inside an LGI index or shape dataset folder (one of its parents holds such a
    ``manifest.json``)."""
    target = _resolved(path)
    for parent in target.parents:
        manifest = parent / "manifest.json"
        if not manifest.is_file():
            continue
        try:
            fmt = json.loads(manifest.read_text()).get("format")
        except (OSError, ValueError, AttributeError):
            continue
        if fmt in STORE_FORMATS:
            raise InputError(f"{option} is inside {STORE_FORMATS[fmt]} ({parent}), which lgi rebuilds as a whole: "
                             "choose a path outside it", path=path)


def check_distinct(outputs: dict[str, Any]) -> None:
    """Refuse two outputs of one run (option name -> path; ``None`` for one not asked for) that are the same path
    or one inside the other: one would silently replace the other."""
    given = [(k, _resolved(v)) for k, v in outputs.items() if v]
    for i, (ka, a) in enumerate(given):
        for kb, b in given[i + 1:]:
            if a == b or a in b.parents or b in a.parents:
                raise InputError(f"{ka} and {kb} are the same path (or one is inside the other)",
                                 path=outputs[kb])


@contextlib.contextmanager
def atomic_dir(final: str | os.PathLike[str], owned: tuple[str, ...] | None = None,
               what: str = "lgi output") -> Iterator[Path]:
    """Yield a temporary directory that replaces ``final`` when the block exits without error.

    An existing ``final`` is replaced as a whole (moved aside, then removed), so readers never see a
    mix of old and new files. On error the temporary directory is removed and ``final`` is untouched.
    ``owned``/``what``: see :func:`check_output` (an existing folder holding anything else is refused).
    """
    final = Path(final)
    check_output(final, "dir", owned=owned, what=what)
    final.parent.mkdir(parents=True, exist_ok=True)
    for prefix in (f".{final.name}.tmp-", f".{final.name}.old-"):
        sweep(final.parent, prefix)
    try:
        tmp = make_temp_dir(final.parent, f".{final.name}.tmp-")
    except OSError as exc:
        raise (storage_error(exc, final) or exc) from exc
    try:
        yield tmp
        write_record(tmp, record_files(tmp, sorted(e.name for e in tmp.iterdir())))
        _fsync_tree(tmp)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        full = storage_error(exc, final) if isinstance(exc, Exception) else None
        if full is not None and full is not exc:
            raise full from exc
        raise
    old = None
    if final.exists():
        old = make_temp_dir(final.parent, f".{final.name}.old-")
        os.replace(final, old / final.name)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_file(final: str | os.PathLike[str], suffix: str = "", durable: bool = True) -> Iterator[Path]:
    """Yield a temporary path in ``final``'s directory that is renamed to ``final`` on success.

    ``suffix`` is kept on the temporary name so that writers which choose a format from the
    extension (pandas, numpy) still see it. ``durable=False`` skips the flush to disk before the rename, for
    a run's working files that a crash throws away anyway.
    """
    final = Path(final)
    check_output(final, "file")
    final.parent.mkdir(parents=True, exist_ok=True)
    sweep(final.parent, f".{final.name}.tmp-")
    try:
        fd, name = tempfile.mkstemp(prefix=f".{final.name}.tmp-{os.getpid()}-", suffix=suffix or final.suffix,
                                    dir=final.parent)
    except OSError as exc:
        raise (storage_error(exc, final) or exc) from exc
    os.close(fd)
    tmp = Path(name)
    tmp.chmod(0o666 & ~_umask())
    try:
        yield tmp
        if durable:
            _fsync_tree(tmp)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        full = storage_error(exc, final) if isinstance(exc, Exception) else None
        if full is not None and full is not exc:
            raise full from exc
        raise
    os.replace(tmp, final)


def check_contents(out: str | os.PathLike[str], contents: dict[str, tuple[str, ...]] | None,
                   owned: tuple[str, ...] = ()) -> None:
    """Refuse an owned directory of ``out`` (name -> the patterns of what it holds) holding anything else: the
    job replaces it whole (see :func:`job_outputs`); and any file under the entries ``owned`` of ``out`` that lgi
    has no record of writing there (the job replaces or removes them)."""
    for name, patterns in (contents or {}).items():
        p = Path(out) / name
        if p.is_symlink():
            # Replaced whole at the commit, it cannot take the link's place (nor should the link's target go).
            raise InputError(f"is a symbolic link (to {os.readlink(p)}), and lgi replaces its {name}/ folder as a "
                             "whole: remove the link, or choose another output folder", path=p)
        check_output(p, "dir", owned=patterns, what=f"lgi {name}/ folder", recorded=False)  # recorded in out
    if owned and Path(out).is_dir():
        check_recorded(Path(out), owned, "this run replaces or removes them")


#: A staging folder holding this file (a JSON object with the job's ``"key"``) is a stopped run's, to be resumed
#: by the next run of the same job (:func:`job_outputs`' ``resume``) instead of removed.
RESUME_FILE = ".resume.json"


def staged_key(path: Path) -> str | None:
    """The job key a staging folder's :data:`RESUME_FILE` names, or None (none, or not readable)."""
    try:
        return str(json.loads((path / RESUME_FILE).read_text())["key"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _adopt_stopped(out: Path, key: str) -> Path | None:
    """The staging folder of a stopped run of the job ``key`` in ``out`` (its process gone), renamed out of the
    way of the sweep, or None. Of several, the one that got farthest (the newest resume file)."""
    found = []
    for entry in [*out.glob(".lgi-staging-*"), *out.glob(".lgi-resuming-*")]:
        prefix = entry.name[:entry.name.index("-", 5) + 1]
        if stopped(entry.name, prefix) and entry.is_dir() and staged_key(entry) == key:
            found.append(((entry / RESUME_FILE).stat().st_mtime_ns, entry))
    if not found:
        return None
    taken = out / f".lgi-resuming-{os.getpid()}"
    os.replace(max(found)[1], taken)
    return taken


#: The lock file of an output folder a run is writing into (:func:`output_lock`); it holds the run's pid.
#: The lock of output folder ``OUT`` is ``.OUT.lgi-lock`` beside it (not inside: a run killed before its first
#: output then leaves nothing under the output's name).
LOCK_SUFFIX = ".lgi-lock"
# The folders this process holds the lock of, and how many times (a job inside a command that locked its folder).
_HELD: dict[Path, int] = {}
_HELD_LOCK = threading.Lock()


def lock_path(out: str | os.PathLike[str]) -> Path:
    """The lock file of output folder ``out`` (its path resolved): ``.NAME.lgi-lock`` beside it."""
    key = _resolved(out)
    return key.parent / f".{key.name}{LOCK_SUFFIX}"


@contextlib.contextmanager
def output_lock(out: str | os.PathLike[str]) -> Iterator[None]:
    """Hold the output folder ``out`` for this process: one run writes into a folder at a time, so two runs
    into one ``--out`` never leave a mixture of their outputs. A second run is refused at once (an
    :class:`~lgi.errors.InputError`, exit 2) naming the holder's pid.

    An OS lock (``flock``) on :func:`lock_path` beside ``out``, released by the kernel if the process dies; the
    file goes when the run ends (a killed run's is taken over by the next). Re-entrant in one process (a command
    that locks its folder runs jobs that lock it too).
    """
    import fcntl

    _not_empty(out)
    out = Path(out)
    key = _resolved(out)
    with _HELD_LOCK:
        if key in _HELD:
            _HELD[key] += 1
            held = True
        else:
            held = False
    if held:
        try:
            yield
        finally:
            with _HELD_LOCK:
                _HELD[key] -= 1
        return
    check_output(out, "dir")  # a file there, a folder that cannot be made: said before any folder is made
    lock = lock_path(out)
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise (storage_error(exc, out) or exc) from exc
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise (storage_error(exc, out) or exc) from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = ""
            for _ in range(20):  # the holder writes its pid just after it takes the lock
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
                if holder:
                    break
                time.sleep(0.01)
            os.close(fd)
            holder = holder or "unknown"
            raise InputError(f"another lgi run (pid {holder}) is writing into this folder: wait for it to end, or "
                             "choose another output", path=out) from None
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the holder removed the file as it ended: lock the next one
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    with _HELD_LOCK:
        _HELD[key] = 1
    try:
        yield
    finally:
        with _HELD_LOCK:
            del _HELD[key]
        with contextlib.suppress(OSError):
            lock.unlink()  # before the release: a run waiting on this file then locks a new one
        os.close(fd)


# The folders this process reads (:func:`reading`): the open descriptor holding the shared lock, and how many
# readers in this process share it.
_READ: dict[Path, list[int]] = {}
#: How often a reader or a commit kept waiting on the other says so (s).
WAIT_NOTE_S = 30.0


def _flock_dir(fd: int, mode: int, folder: Path, waiting: str) -> bool:
    """Take ``mode`` (``fcntl.LOCK_SH`` or ``LOCK_EX``) on the open folder ``fd``, waiting as long as it takes and
    saying so every :data:`WAIT_NOTE_S`; False (with a warning) where the file system cannot lock folders."""
    import fcntl

    log = logging.getLogger(__name__)
    start = time.monotonic()
    noted = 0.0
    while True:
        try:
            fcntl.flock(fd, mode | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            waited = time.monotonic() - start
            if waited >= noted:
                log.warning("%s (%s): waiting, %.0f s so far", waiting, folder, waited)
                noted += WAIT_NOTE_S
            time.sleep(0.05)
        except OSError as exc:  # NFS, for one, cannot lock a folder
            log.warning("%s cannot be locked (%s): readers are not kept from a run's commit there", folder, exc)
            return False


@contextlib.contextmanager
def reading(folder: str | os.PathLike[str]) -> Iterator[None]:
    """Read the output folder ``folder`` (a reconstruction) as one run's outputs: a run committing into it
    waits until the readers are done, and a reader waits for a commit under way, so no reader sees one run's
    meshes with another's tables. A shared ``flock`` on the folder itself (its entries are replaced, never the
    folder): nothing is written beside it. A folder that does not exist or cannot be opened is left to the
    reader's own checks to name."""
    import fcntl

    key = _resolved(folder)
    with _HELD_LOCK:
        mine = _READ.get(key)
        if mine is not None:
            mine[1] += 1
    if mine is None:
        try:
            fd = os.open(key, os.O_RDONLY | os.O_DIRECTORY)
        except OSError:
            yield
            return
        if not _flock_dir(fd, fcntl.LOCK_SH, key, "another lgi run is replacing the outputs being read"):
            os.close(fd)
            yield
            return
        with _HELD_LOCK:
            mine = _READ.get(key)  # another thread of this process may have taken it meanwhile
            if mine is None:
                _READ[key] = [fd, 1]
            else:
                mine[1] += 1
        if mine is not None:
            os.close(fd)
        from lgi._debug_stages import stage as debug_stage

        debug_stage("read")  # a test holds the reader here, its folder locked
    try:
        yield
    finally:
        with _HELD_LOCK:
            entry = _READ[key]
            entry[1] -= 1
            if entry[1] == 0:
                del _READ[key]
                os.close(entry[0])


def reads(param: str) -> Callable[[F], F]:
    """A job that reads the output folder passed as its argument ``param`` runs :func:`reading` it."""
    import functools
    import inspect

    def wrap(fn: F) -> F:
        sig = inspect.signature(fn)

        @functools.wraps(fn)
        def run(*args: Any, **kwargs: Any) -> Any:
            with reading(sig.bind_partial(*args, **kwargs).arguments[param]):
                return fn(*args, **kwargs)

        return run  # type: ignore[return-value]

    return wrap


@contextlib.contextmanager
def _committing(out: Path) -> Iterator[None]:
    """Hold ``out`` against its readers (:func:`reading`) while a commit replaces its entries: the readers in other
    processes finish first, and new ones wait for the commit. A folder this process reads itself keeps its
    shared lock after."""
    import fcntl

    key = _resolved(out)
    with _HELD_LOCK:
        mine = _READ.get(key)
    fd = mine[0] if mine is not None else os.open(key, os.O_RDONLY | os.O_DIRECTORY)
    locked = False
    try:
        locked = _flock_dir(fd, fcntl.LOCK_EX, key, "lgi is reading the outputs this run replaces")
        yield
    finally:
        if mine is not None:
            if locked:
                fcntl.flock(fd, fcntl.LOCK_SH)
        else:
            os.close(fd)


@contextlib.contextmanager
def job_outputs(out: str | os.PathLike[str], owned: tuple[str, ...],
                contents: dict[str, tuple[str, ...]] | None = None, resume: str | None = None) -> Iterator[Path]:
    """Yield a staging directory for a job whose outputs are the entries ``owned`` of directory ``out``.

    The one output-directory policy of every job that writes a directory of outputs: on success each staged
    entry replaces the one of the same name, and the job's entries this run did not write (an earlier run's
    ``obj/`` when ``--obj`` is not given now) are removed, so ``out`` never mixes two runs; entries that are
    not the job's are left alone. On error nothing in ``out`` changes and the staging directory is removed;
    a killed run's staging directory is removed by the next run. ``contents``: for the owned directories, the
    fnmatch patterns of what they hold; an existing one holding anything else is refused before the work (see
    :func:`check_output`), as it would be replaced whole.

    ``resume``: the job's key (its inputs and options). A stopped run of the same job (killed, or interrupted by a
    signal after writing a :data:`RESUME_FILE` with this key into its staging folder) is taken over: its staging
    folder is this run's, for the job to go on from what it wrote. An interrupt then keeps the staging folder
    when it holds such a file; an error removes it as ever.
    """
    out = Path(out)
    check_output(out, "dir")
    check_contents(out, contents, owned)
    with output_lock(out), _staged(out, owned, resume) as stage:
        yield stage


@contextlib.contextmanager
def _staged(out: Path, owned: tuple[str, ...], resume: str | None) -> Iterator[Path]:
    """:func:`job_outputs` in a folder this process holds (:func:`output_lock`)."""
    adopted = _adopt_stopped(out, resume) if resume else None
    for prefix in (".lgi-staging-", ".lgi-resuming-", RECORD_TEMP, *(f".{name}.old-" for name in owned)):
        sweep(out, prefix)
    stage, created = None, not out.exists()
    try:
        try:
            out.mkdir(parents=True, exist_ok=True)
            stage = make_temp_dir(out, ".lgi-staging-")
            if adopted is not None:
                stage.rmdir()
                os.replace(adopted, stage)
        except OSError as exc:
            raise (storage_error(exc, out) or exc) from exc
        yield stage
        written = {e.name for e in stage.iterdir()}
        unknown = written - set(owned)
        if unknown:
            raise RuntimeError(f"job wrote outputs it does not declare: {sorted(unknown)}")
        _fsync_tree(stage)
        with _committing(out):
            _commit(out, stage, owned, written)
        stage.rmdir()
    except BaseException as exc:
        if stage is None:
            # Stopped (a signal) while the staging folder was being made: this process's own, by its name.
            full = storage_error(exc, out) if isinstance(exc, Exception) else None
            for left in out.glob(f".lgi-staging-{os.getpid()}-*"):
                shutil.rmtree(left, ignore_errors=True)
        else:
            full = storage_error(exc, _written(exc, stage, out)) if isinstance(exc, Exception) else None
            if not (resume and isinstance(exc, KeyboardInterrupt | SystemExit) and staged_key(stage) == resume):
                shutil.rmtree(stage, ignore_errors=True)
            else:
                logging.getLogger(__name__).warning(
                    "stopped: what was written waits in %s for the same command to go on from (the next run of "
                    "another job into %s removes it)", stage, out)
        if created:
            with contextlib.suppress(OSError):
                out.rmdir()  # made for this run's outputs, and left empty: nothing under the output's name
        if full is not None and full is not exc:
            raise full from exc
        raise


def _commit(out: Path, stage: Path, owned: tuple[str, ...], written: set[str]) -> None:
    """Replace the ``owned`` entries of ``out`` with those ``written`` in ``stage``; remove the others."""
    from lgi._debug_stages import stage as debug_stage

    # The record lists the new files before any is moved in, and the replaced ones until all are: a run
    # stopped half way through leaves only files the next run knows as lgi's.
    recorded, _ = read_record(out)
    kept = {k: v for k, v in recorded.items() if k.split("/", 1)[0] not in owned}
    new = record_files(stage, sorted(written))
    write_record(out, {**kept, **new}, previous={k: v for k, v in recorded.items() if k not in kept})
    for k, name in enumerate(owned):
        if k == 1:
            debug_stage("commit")  # a test holds the run here, its first entry replaced
        entry, target = stage / name, out / name
        if name in written:
            if target.is_dir() and not target.is_symlink():
                old = make_temp_dir(out, f".{name}.old-")
                os.replace(target, old / name)
                os.replace(entry, target)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(entry, target)
        elif target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists() or target.is_symlink():
            target.unlink()
    write_record(out, {**kept, **new})


def _written(exc: BaseException, stage: Path, out: Path) -> Path:
    """The output a job was writing when it failed, under its final name: the file the error names, else the
    staged entry written last, else ``out`` itself (read before the staging folder goes)."""
    name = getattr(exc, "filename", None)
    with contextlib.suppress(ValueError, TypeError):
        if name:
            return out / Path(name).resolve().relative_to(stage.resolve())
    with contextlib.suppress(OSError, ValueError):
        entries = [p for p in stage.rglob("*") if p.is_file()]
        if entries:
            return out / max(entries, key=lambda p: p.stat().st_mtime_ns).relative_to(stage)
    return out
