"""Prefect 3 tasks and flows over the job layer (:mod:`lgi.jobs`). Imported only when a flow runs: the
library's algorithms and jobs do not need Prefect. The top-level ``flows/`` and ``tasks/`` files that
``prefect.yaml`` points at re-export these."""

from __future__ import annotations

import base64
import hashlib
import logging
import re
import threading
from pathlib import Path

from lgi.errors import LgiError

#: Set by the command line's Ctrl-C handler during a flow run. Prefect may swallow the KeyboardInterrupt where
#: it lands (inside its engine's own exception handling); the chunk tasks also check this and stop, and the
#: command reports the interrupt even so.
INTERRUPTED = threading.Event()


def capture_library_logs() -> None:
    """Send the library's log records (``lgi.*``: every warning the command line prints, and its info lines) to
    the Prefect run they happen in, as ``PREFECT_LOGGING_EXTRA_LOGGERS=lgi`` would, whatever the process's
    settings (a worker's, a Dask worker's, the command line's). Idempotent."""
    import prefect.main  # noqa: F401 - configures Prefect's logging (its API handler), once per process

    lib = logging.getLogger("lgi")
    if lib.level == logging.NOTSET:
        lib.setLevel(logging.INFO)
    if not any(isinstance(h, _RunLogHandler) for h in lib.handlers):
        lib.addHandler(_RunLogHandler())


class _RunLogHandler(logging.Handler):
    """Forwards a record to Prefect's API handlers when it happens inside a flow or task run; outside one (the
    library used directly in the same process) it does nothing, where the API handler would warn."""

    def emit(self, record: logging.LogRecord) -> None:
        from prefect.context import FlowRunContext, TaskRunContext

        if FlowRunContext.get() is None and TaskRunContext.get() is None:
            return
        for handler in logging.getLogger("prefect.extra").handlers:
            if record.levelno >= handler.level:
                handler.handle(record)


capture_library_logs()


def artifact_key(kind: str, path: str | Path) -> str:
    """A Prefect artifact key unique to one output folder (a shot, a dataset) and stable across its re-runs, so
    the UI keeps each shot's report history apart: ``KIND-NAME-HASH`` (lowercase letters, digits, dashes)."""
    p = Path(path).resolve()
    name = re.sub(r"[^a-z0-9]+", "-", p.name.lower()).strip("-")[:40] or "out"
    return f"{kind}-{name}-{hashlib.sha256(str(p).encode()).hexdigest()[:8]}"


def embedded_png(path: Path, alt: str) -> str:
    """Markdown for a picture carried inside the artifact (a data URI): a remote UI shows it, where a link to
    the worker's disk would be broken."""
    data = base64.b64encode(Path(path).read_bytes()).decode()
    return f"![{alt}](data:image/png;base64,{data})"


def transient_only(task, task_run, state) -> bool:
    """A task's retry condition: retry for what may pass (a file system or network hiccup), never for bad
    input or a bug, which would fail the same way again."""
    try:
        state.result()
    except LgiError:
        return False
    except OSError:
        return True
    except Exception:  # noqa: BLE001 - a bug or bad data: retrying gives the same
        return False
    return False
