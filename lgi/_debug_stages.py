"""Stage markers, for tests that interrupt a command at a chosen stage.

With ``LGI_DEBUG_STAGES`` naming a folder, a command creates the empty file ``FOLDER/<stage>`` as it enters each
stage: ``start`` (before the command line's modules are imported), ``solve`` (a reconstruction's solve begins),
``write`` (its outputs are being written), ``read`` (a job reading a reconstruction holds it against commits,
:func:`lgi.io.atomic.reading`), ``commit`` (a job's outputs are replacing an earlier run's, the first of
them replaced) and ``shutdown`` (the command has returned its status; the interpreter is about to exit). A test
then sends its signal once the stage it means to interrupt has begun, instead of guessing a delay that a loaded
machine turns wrong.

``LGI_DEBUG_HOLD=<stage>:<seconds>`` also holds the command at that stage for up to that long, ended early by a
signal, so that a signal can be made to land in a window that is otherwise milliseconds wide (the shutdown).

Unset (as for every user), each call costs one environment lookup. Only the standard library is imported here:
the entry point calls this before anything else is loaded.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

STAGES_ENV = "LGI_DEBUG_STAGES"
HOLD_ENV = "LGI_DEBUG_HOLD"


def stage(name: str, until: Callable[[], bool] | None = None) -> None:
    """Mark the stage ``name`` as begun (see the module docstring); hold there if ``LGI_DEBUG_HOLD`` asks, until
    the hold's time is up or ``until()`` is true (a signal was noted without interrupting)."""
    folder = os.environ.get(STAGES_ENV)
    if not folder:
        return
    os.makedirs(folder, exist_ok=True)
    # Created under a temporary name and renamed: a test that sees the file sees the stage begun.
    tmp = os.path.join(folder, f".{name}.{os.getpid()}")
    with open(tmp, "w") as f:
        f.write(str(os.getpid()))
    os.replace(tmp, os.path.join(folder, name))
    hold_stage, _, seconds = os.environ.get(HOLD_ENV, "").partition(":")
    if hold_stage != name:
        return
    deadline = time.monotonic() + float(seconds or 0)
    while time.monotonic() < deadline and not (until is not None and until()):
        time.sleep(0.01)  # a signal whose handler raises ends the hold with its exception
