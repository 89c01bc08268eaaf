"""The ``lgi`` command's entry point: a Ctrl-C while the command line's modules are still being imported ends
with status 130 and one line, like one that lands later (:func:`lgi.cli.main` handles those)."""

import atexit
import os
import signal
import sys


def run() -> None:
    try:
        from lgi.cli import main
    except KeyboardInterrupt:
        print("lgi: interrupted", file=sys.stderr)
        sys.exit(130)
    code = main()
    if code in (130, 143):
        # An interrupt that landed in a compiled kernel can leave a second one pending, which the interpreter's
        # shutdown would turn into death by SIGINT; the run's clean-up is done, so leave with the status now,
        # after the exit handlers with further interrupts ignored: os._exit skips them, and one of them stops the
        # local Prefect server that `--flow` started (left running, it would hold a port and a core forever).
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        try:
            atexit._run_exitfuncs()
        except BaseException:  # noqa: BLE001 - a failing handler must not change the exit status
            pass
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    sys.exit(code)
