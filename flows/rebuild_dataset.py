"""The dataset rebuild flow: read, stabilise, and (given markers) index and verify, one task per stage.

Stages are cached by content (``lgi.cache``): a re-run with nothing changed computes nothing; changing
one option recomputes only the stages that depend on it. Run locally with
``python -m flows.rebuild_dataset SHAPES_DIR OUT [MARKERS]`` or through the deployment in ``prefect.yaml``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from prefect import flow

from lgi.pipeline import options_from
from tasks.dataset import assemble, natural_neighbours, point_clouds, publish, read_shapes, stabilise, verify


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
    markers: str | None = None,
    index_options: dict | None = None,
    jaw_rig: str | None = None,
    tolerance: float = 0.01,
    cache_dir: str | None = None,
) -> dict:
    """Build ``OUT/dataset`` and, with ``markers``, ``OUT/index`` and ``OUT/verification.csv``.

    Returns a summary: paths, the dataset's content hash, counts, verification figures, and which stages
    were cache hits (``stages``: name -> true if nothing was computed).
    """
    out_dir = Path(out)
    cache = cache_dir or str(out_dir / ".cache")
    stages: dict[str, bool] = {}
    raw, stages["read"] = read_shapes(cache, shapes_dir, neutral, include, exclude, units, deltas)
    staged, stages["stabilise"] = stabilise(cache, raw, rigid_vertices)
    dataset_dir = str(Path(staged) / "dataset")
    publish(dataset_dir, str(out_dir / "dataset"))
    manifest = json.loads((Path(dataset_dir) / "manifest.json").read_text())
    summary = {"path": str((out_dir / "dataset").resolve()), "content_hash": manifest["content_hash"],
               "n_shapes": manifest["n_shapes"], "n_vertices": manifest["n_vertices"],
               "stabilisation": manifest["info"].get("stabilisation", {}).get("method", "none"), "stages": stages}
    if markers:
        opts = options_from(index_options).to_json()
        nat, stages["natural"] = natural_neighbours(cache, dataset_dir, markers, opts)
        clouds, stages["clouds"] = point_clouds(cache, dataset_dir, markers, nat, opts, jaw_rig)
        idx, stages["index"] = assemble(cache, dataset_dir, markers, nat, clouds, opts, jaw_rig)
        ver, stages["verify"] = verify(cache, idx, tolerance)
        publish(str(Path(idx) / "index"), str(out_dir / "index"))
        publish(ver, str(out_dir / "verification"))
        summary["verification"] = json.loads((Path(ver) / "summary.json").read_text())
        summary["index"] = str((out_dir / "index").resolve())
    print(f"dataset {summary['path']}: {summary['n_shapes']} shapes; stages computed: "
          f"{[k for k, hit in stages.items() if not hit] or 'none (all cached)'}")
    return summary


if __name__ == "__main__":
    rebuild_dataset(sys.argv[1], sys.argv[2], markers=sys.argv[3] if len(sys.argv) > 3 else None)
