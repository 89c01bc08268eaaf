"""Atomic output: write to a temporary sibling, then rename into place.

A crash, a kill or an exception midway leaves no partial file or directory under the final name.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def make_temp_dir(parent: Path, prefix: str) -> Path:
    """A new directory in ``parent`` with the permissions a plain ``mkdir`` would give."""
    tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    # mkdtemp makes 0700 directories; outputs should follow the user's umask like any other file.
    tmp.chmod(0o777 & ~_umask())
    return tmp


@contextlib.contextmanager
def atomic_dir(final: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary directory that replaces ``final`` when the block exits without error.

    An existing ``final`` is replaced as a whole (moved aside, then removed), so readers never see a
    mix of old and new files. On error the temporary directory is removed and ``final`` is untouched.
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = make_temp_dir(final.parent, f".{final.name}.tmp-")
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if final.exists():
        old = final.parent / f".{final.name}.old-{os.getpid()}-{tmp.name[-8:]}"
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_file(final: str | os.PathLike[str], suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path in ``final``'s directory that is renamed to ``final`` on success.

    ``suffix`` is kept on the temporary name so that writers which choose a format from the
    extension (pandas, numpy) still see it.
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{final.name}.tmp-", suffix=suffix or final.suffix, dir=final.parent)
    os.close(fd)
    tmp = Path(name)
    tmp.chmod(0o666 & ~_umask())
    try:
        yield tmp
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, final)


@contextlib.contextmanager
def job_outputs(out: str | os.PathLike[str], owned: tuple[str, ...]) -> Iterator[Path]:
    """Yield a staging directory for a job whose outputs are the entries ``owned`` of directory ``out``.

    The one output-directory policy of every job that writes a directory of outputs: on success each staged
    entry replaces the one of the same name, and the job's entries this run did not write (an earlier run's
    ``obj/`` when ``--obj`` is not given now) are removed, so ``out`` never mixes two runs; entries that are
    not the job's are left alone. On error nothing in ``out`` changes and the staging directory is removed.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        from lgi.errors import InputError

        raise InputError("the output must be a directory; a file of that name exists", path=out)
    out.mkdir(parents=True, exist_ok=True)
    stage = make_temp_dir(out, ".lgi-staging-")
    try:
        yield stage
        written = {e.name for e in stage.iterdir()}
        unknown = written - set(owned)
        if unknown:
            raise RuntimeError(f"job wrote outputs it does not declare: {sorted(unknown)}")
        for name in owned:
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
        stage.rmdir()
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
