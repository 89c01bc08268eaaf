"""The ``lgi`` command's entry point: the exit status of a signal, wherever it lands.

A Ctrl-C (SIGINT) or a SIGTERM while the command line's modules are still being imported ends with status 130 or
143 and one line, like one that lands during the work (:func:`lgi.cli.main` handles those). One that lands after
the command has returned its status, while the interpreter shuts down, finds the outputs complete: it is noted
and the command ends with 130 or 143 (the outputs stay), never with death by the signal (a status of -2 seen by
the caller, which a scheduler reads as a crash).
"""

import atexit
import os
import signal
import sys

from lgi._debug_stages import stage
from lgi.errors import Terminated

_STATUS = {signal.SIGINT: 130, signal.SIGTERM: 143}


def _flush() -> None:
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass


def run() -> None:
    done = False  # the command has returned its status: from then on a signal only changes the status
    noted: list[int] = []

    def on_signal(signum: int, frame: object) -> None:
        if done:
            noted.append(signum)
            return
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    def last(code_box: list[int]) -> None:
        # Registered before anything else, so it runs after every other exit handler (one of them stops the
        # local Prefect server that `--flow` started). What remains of the shutdown after it cannot be cut short:
        # ignored signals stay ignored through the interpreter's finalisation.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if noted and code_box[0] not in (130, 143):
            print("lgi: interrupted after the outputs of this run were written", file=sys.stderr)
            _flush()
            os._exit(_STATUS[noted[0]])

    code_box = [0]
    atexit.register(last, code_box)
    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        stage("start")
        from lgi.cli import main

        code = main()
    except KeyboardInterrupt as exc:
        code = 143 if isinstance(exc, Terminated) else 130
        print("lgi: terminated (SIGTERM)" if code == 143 else "lgi: interrupted", file=sys.stderr)
    except SystemExit as exc:  # argparse's usage errors and --help
        code = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 1
        if isinstance(exc.code, str):
            print(exc.code, file=sys.stderr)
    finally:
        done = True
    code_box[0] = code
    stage("shutdown", until=lambda: bool(noted))
    if noted and code not in (130, 143):
        code = code_box[0] = _STATUS[noted[0]]
        print("lgi: interrupted after the outputs of this run were written", file=sys.stderr)
    if code in (130, 143):
        # An interrupt that landed in a compiled kernel can leave a second one pending; the run's clean-up is done,
        # so leave with the status now, after the exit handlers with further signals ignored: os._exit skips them,
        # and one of them stops the local Prefect server that `--flow` started (left running, it would hold a port
        # and a core forever).
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        try:
            atexit._run_exitfuncs()
        except BaseException:  # noqa: BLE001 - a failing handler must not change the exit status
            pass
        _flush()
        os._exit(code)
    sys.exit(code)
