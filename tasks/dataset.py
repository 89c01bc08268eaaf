"""Dataset stages as Prefect tasks: read shapes, stabilise, save.

Results pass between tasks in memory and land on disk as dataset directories; nothing is pickled
(``persist_result=False``). Content-addressed caching of stages comes with the orchestration issue.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from lgi.dataset import ShapeDataset
from lgi.importers import RawShapes, assemble_dataset, read_shape_folder, stabilise_raw


@task(name="read-shapes", cache_policy=NO_CACHE, persist_result=False)
def read_shapes(shapes_dir: str, neutral: str | None = None, include: str | None = None,
                exclude: str | None = None, units: str = "cm", deltas: bool = False) -> RawShapes:
    """Read a folder of OBJ shapes (see :func:`lgi.importers.read_shape_folder`)."""
    return read_shape_folder(shapes_dir, neutral=neutral, include=include, exclude=exclude, units=units,
                             deltas=deltas, show_progress=False)


@task(name="stabilise", cache_policy=NO_CACHE, persist_result=False)
def stabilise(raw: RawShapes, rigid_vertices: str | None = "auto") -> ShapeDataset:
    """Remove head motion and assemble the dataset (see :func:`lgi.importers.stabilise_raw`)."""
    return assemble_dataset(raw, *stabilise_raw(raw, rigid_vertices))


@task(name="save-dataset", cache_policy=NO_CACHE, persist_result=False)
def save_dataset(dataset: ShapeDataset, out: str) -> dict:
    """Write the dataset directory atomically; returns a summary (JSON-friendly)."""
    dataset.save(out)
    stab = dataset.info.get("stabilisation", {})
    shifts = [float(np.linalg.norm(m.rigid_transform[:3, 3])) for m in dataset.shape_meta]
    return {
        "path": str(Path(out).resolve()),
        "content_hash": dataset.content_hash(),
        "n_shapes": dataset.n_shapes,
        "n_vertices": dataset.n_vertices,
        "stabilisation": stab.get("method", "none"),
        "max_translation_removed": max(shifts) if shifts else 0.0,
    }
