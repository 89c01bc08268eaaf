"""``python -m lgi``: the command line."""

import sys

from lgi.cli import main

sys.exit(main())
