"""lgi: facial performance capture by Local Geometric Indexing.

The core library works on plain numpy arrays and has no Prefect dependency; see the README for the
command line and ``docs/`` for the file formats.
"""

from lgi.dataset.shapes import ShapeDataset, ShapeMeta
from lgi.errors import InputError, LgiError

__version__ = "0.1.0"

__all__ = ["InputError", "LgiError", "ShapeDataset", "ShapeMeta", "__version__"]
