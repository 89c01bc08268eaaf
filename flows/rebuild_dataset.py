"""The dataset rebuild flow: import a folder of shapes, stabilise them, save the dataset.

Run locally with ``python -m flows.rebuild_dataset SHAPES_DIR OUT`` or through the deployment in
``prefect.yaml``.
"""

from __future__ import annotations

import sys

from prefect import flow

from tasks.dataset import read_shapes, save_dataset, stabilise


@flow(name="rebuild-dataset", log_prints=True)
def rebuild_dataset(
    shapes_dir: str,
    out: str,
    neutral: str | None = None,
    include: str | None = None,
    exclude: str | None = None,
    rigid_vertices: str | None = "auto",
    units: str = "cm",
    deltas: bool = False,
) -> dict:
    """Import, stabilise and save a shape dataset; returns the saved dataset's summary."""
    raw = read_shapes(shapes_dir, neutral=neutral, include=include, exclude=exclude, units=units, deltas=deltas)
    dataset = stabilise(raw, rigid_vertices)
    summary = save_dataset(dataset, out)
    print(f"dataset {summary['path']}: {summary['n_shapes']} shapes, hash {summary['content_hash'][:16]}")
    return summary


if __name__ == "__main__":
    rebuild_dataset(sys.argv[1], sys.argv[2])
