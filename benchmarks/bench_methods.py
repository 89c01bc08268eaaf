"""LGI against the baselines, same frames, same run: `lgi bench` (see lgi/evaluation/accuracy.py for the test sets).

    python benchmarks/bench_methods.py [--out DIR] [--frames F] [--noise MM] [--no-ict]
"""

import sys

from lgi.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
