"""Deployment entry point of the reconstruct-shot flow (``prefect.yaml``); the flow is
:func:`lgi.orchestration.reconstruct.reconstruct_shot`. Run locally with
``python -m flows.reconstruct_shot INDEX_DIR BUNDLES OUT``."""

from __future__ import annotations

import sys

from lgi.orchestration.reconstruct import reconstruct_shot

__all__ = ["reconstruct_shot"]

USAGE = "usage: python -m flows.reconstruct_shot INDEX_DIR BUNDLES OUT  (or: lgi reconstruct ... --flow)"

if __name__ == "__main__":
    if sys.argv[1:] in (["-h"], ["--help"]):
        print(USAGE)
        sys.exit(0)
    if len(sys.argv) != 4:
        sys.exit(USAGE)
    reconstruct_shot(*sys.argv[1:])
