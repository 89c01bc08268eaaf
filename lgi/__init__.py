"""lgi: facial performance capture by Local Geometric Indexing.

The core library works on plain numpy arrays and has no Prefect dependency; see the README for the
command line and ``docs/`` for the file formats.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from lgi.errors import InputError, LgiError

if TYPE_CHECKING:
    from lgi.dataset.shapes import ShapeDataset, ShapeMeta

__version__ = "0.1.0"

__all__ = ["InputError", "LgiError", "ShapeDataset", "ShapeMeta", "__version__"]


def __getattr__(name: str) -> object:
    # The dataset classes load numpy on first use, not on ``import lgi``: the command's entry point is inside this
    # package and must set up its signal handling before a Ctrl-C could land in a long import.
    if name in ("ShapeDataset", "ShapeMeta"):
        from lgi.dataset import shapes

        return getattr(shapes, name)
    raise AttributeError(f"module 'lgi' has no attribute {name!r}")
