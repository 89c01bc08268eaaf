"""Errors raised on bad input, and the warnings of what a run could not do as asked.

Every error names where the problem is (file, line, frame, marker) so that a user can fix the input
without reading the code. The command line turns them into a one-line message and exit status 2.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Iterator
from os import PathLike

#: The most of a user's text an error quotes (a cell, a line): a 50 MB cell is not echoed into a terminal or log.
QUOTED_CHARS = 200
#: The longest message an error carries; the rest is cut, with a count of what was left out.
MESSAGE_CHARS = 2000


def _capped(s: str, limit: int) -> str:
    return s if len(s) <= limit else f"{s[:limit]}... ({len(s) - limit:,} more characters)"


class LgiError(ValueError):
    """Base class of all errors that lgi raises on bad input or bad configuration (a ValueError, so that
    validators such as pydantic's, which checks the flows' parameters, report them as bad values)."""


class InputError(LgiError):
    """Bad input data, located as precisely as possible.

    Parameters
    ----------
    message
        What is wrong, in words.
    path
        The file (or directory) that holds the problem.
    line
        1-based line number inside ``path``.
    frame, marker
        For per-frame marker data: the frame number and marker name.
    """

    def __init__(
        self,
        message: str,
        *,
        path: str | PathLike[str] | None = None,
        line: int | None = None,
        frame: int | None = None,
        marker: str | None = None,
    ) -> None:
        self.message = _capped(message, MESSAGE_CHARS)
        self.path = None if path is None else str(path)
        self.line = line
        self.frame = frame
        self.marker = None if marker is None else _capped(str(marker), QUOTED_CHARS)
        super().__init__(self._format())

    def _format(self) -> str:
        where = []
        if self.path is not None:
            where.append(self.path if self.line is None else f"{self.path}:{self.line}")
        if self.frame is not None:
            where.append(f"frame {self.frame}")
        if self.marker is not None:
            where.append(f"marker {self.marker!r}")
        return f"{', '.join(where)}: {self.message}" if where else self.message


class StorageError(LgiError):
    """The machine would not store an output: its file system is full, over quota or read-only. Named by the
    output's path; nothing was written under that name and what was there before is unchanged. Not retried by
    the flows (it fails the same way until someone frees space or remounts)."""

    def __init__(self, path: str | PathLike[str], reason: str, detail: str = "") -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}{detail}")


def cell_text(value: object) -> str:
    """A table cell as the user wrote it, for messages: text quoted, numbers plain (not numpy's
    ``np.float64(0.5)``), anything else (a list in a Parquet cell) as printed; at most :data:`QUOTED_CHARS` of
    it."""
    if isinstance(value, str):
        if len(value) <= QUOTED_CHARS:
            return repr(value)
        return f"{value[:QUOTED_CHARS]!r}... ({len(value) - QUOTED_CHARS:,} more characters)"
    item = getattr(value, "item", None)
    if item is not None and getattr(value, "ndim", 1) == 0:
        return str(item())
    return _capped(str(value), QUOTED_CHARS)


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler or a farm cancelling the job), unwound like Ctrl-C so the run cleans up after itself
    and ends with status 143."""


@contextlib.contextmanager
def collected_warnings(this_thread: bool = False) -> Iterator[list[str]]:
    """The warnings lgi logs inside the block (what a run could not do as asked), for the review page; with
    ``this_thread``, only those logged by the thread that entered it (a chunk task beside others)."""
    seen: list[str] = []
    me = threading.get_ident()

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if not this_thread or record.thread == me:
                seen.append(record.getMessage())

    handler = Collect(logging.WARNING)
    logging.getLogger("lgi").addHandler(handler)
    try:
        yield seen
    finally:
        logging.getLogger("lgi").removeHandler(handler)
