"""``python -m lgi``: the command line."""

from lgi._entry import run

run()
