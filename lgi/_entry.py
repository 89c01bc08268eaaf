"""The ``lgi`` command's entry point: a Ctrl-C while the command line's modules are still being imported ends
with status 130 and one line, like one that lands later (:func:`lgi.cli.main` handles those)."""

import os
import sys


def run() -> None:
    try:
        from lgi.cli import main
    except KeyboardInterrupt:
        print("lgi: interrupted", file=sys.stderr)
        sys.exit(130)
    code = main()
    if code == 130:
        # An interrupt that landed in a compiled kernel can leave a second one pending, which the interpreter's
        # shutdown would turn into death by SIGINT; the run's clean-up is done, so leave with the status now.
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(130)
    sys.exit(code)
