"""Prefect 3 tasks and flows over the job layer (:mod:`lgi.jobs`). Imported only when a flow runs: the
library's algorithms and jobs do not need Prefect. The top-level ``flows/`` and ``tasks/`` files that
``prefect.yaml`` points at re-export these."""

from __future__ import annotations

import logging


def capture_library_logs() -> None:
    """Send the library's log records (``lgi.*``: every warning the command line prints, and its info lines) to
    the Prefect run they happen in, as ``PREFECT_LOGGING_EXTRA_LOGGERS=lgi`` would, whatever the process's
    settings (a worker's, a Dask worker's, the command line's). Idempotent."""
    import prefect.main  # noqa: F401 - configures Prefect's logging (its API handler), once per process

    lib = logging.getLogger("lgi")
    if lib.level == logging.NOTSET:
        lib.setLevel(logging.INFO)
    for handler in logging.getLogger("prefect.extra").handlers:
        if handler not in lib.handlers:
            lib.addHandler(handler)


capture_library_logs()
