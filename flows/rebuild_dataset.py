"""Deployment entry point of the rebuild-dataset flow (``prefect.yaml``); the flow is
:func:`lgi.orchestration.rebuild.rebuild_dataset`. Run locally with
``python -m flows.rebuild_dataset SHAPES_DIR OUT [MARKERS]``."""

from __future__ import annotations

import sys

from lgi.orchestration.rebuild import rebuild_dataset

__all__ = ["rebuild_dataset"]

if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit("usage: python -m flows.rebuild_dataset SHAPES_DIR OUT [MARKERS]  (or: lgi import ... --flow)")
    rebuild_dataset(sys.argv[1], sys.argv[2], markers=sys.argv[3] if len(sys.argv) > 3 else None)
