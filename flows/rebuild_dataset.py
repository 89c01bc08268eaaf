"""The dataset rebuild flow: read, stabilise, and (given markers) index and verify, one task per stage.

Stages are cached by content (``lgi.cache``): a re-run with nothing changed computes nothing; changing
one option recomputes only the stages that depend on it. Run locally with
``python -m flows.rebuild_dataset SHAPES_DIR OUT [MARKERS]`` or through the deployment in ``prefect.yaml``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pandas as pd
from prefect import flow
from prefect.artifacts import create_markdown_artifact, create_table_artifact

from lgi.pipeline import options_from
from tasks.dataset import (
    assemble,
    augment,
    natural_neighbours,
    point_clouds,
    publish,
    read_shapes,
    stabilise,
    verify,
)


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
    augmentation: dict | None = None,
) -> dict:
    """Build ``OUT/dataset`` and, with ``markers``, ``OUT/index`` and ``OUT/verification.csv``.

    ``augmentation`` (parameters of :func:`lgi.pipeline.augment_stage`, e.g. ``{"simulate": True,
    "budget": 100}``) adds in-betweens: ``OUT/dataset_augmented``, which the index is then built from.

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
    if augmentation:
        aug, stages["augment"] = augment(cache, dataset_dir, augmentation, jaw_rig)
        dataset_dir = str(Path(aug) / "dataset")
        publish(dataset_dir, str(out_dir / "dataset_augmented"))
        aug_manifest = json.loads((Path(dataset_dir) / "manifest.json").read_text())
        summary["augmented"] = {"path": str((out_dir / "dataset_augmented").resolve()),
                                "n_shapes": aug_manifest["n_shapes"], **aug_manifest["info"].get("augmented", {})}
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
    report(summary, out_dir)
    print(f"dataset {summary['path']}: {summary['n_shapes']} shapes; stages computed: "
          f"{[k for k, hit in stages.items() if not hit] or 'none (all cached)'}")
    return summary


def report(summary: dict, out_dir: Path) -> None:
    """Table artifacts (shapes, bundles, verification), a heat map of the worst verification error and a
    markdown report linking it (``OUT/report.md`` too)."""
    manifest = json.loads((out_dir / "dataset" / "manifest.json").read_text())
    shapes = [{"shape": s["name"], "source": s["source"], "tags": ",".join(s["tags"]),
               "removed_translation": round(float(sum(v * v for v in [r[3] for r in s["rigid_transform"][:3]]) ** 0.5),
                                            6)} for s in manifest["shapes"]]
    create_table_artifact(table=shapes, key="dataset-shapes", description="shapes and the head motion removed")
    lines = ["# Dataset rebuild\n", f"`dataset/`: {summary['n_shapes']} shapes, {summary['n_vertices']} "
             f"vertices, content hash `{summary['content_hash'][:16]}`, stabilisation: {summary['stabilisation']}.\n",
             "| stage | " + " | ".join(summary["stages"]) + " |", "|---|" + "---|" * len(summary["stages"]),
             "| cached | " + " | ".join("yes" if v else "computed" for v in summary["stages"].values()) + " |\n"]
    if "verification" in summary:
        v = summary["verification"]
        bundles = pd.read_csv(out_dir / "index" / "bundles.csv")
        create_table_artifact(table=bundles.to_dict(orient="records"), key="index-bundles",
                              description="per bundle: points before/after pruning, simplices by kind")
        table = pd.read_csv(out_dir / "verification" / "verification.csv")
        create_table_artifact(table=table.round(6).to_dict(orient="records"), key="verification",
                              description="every shape from its own bundles: error in mm")
        png = _verification_heatmap(out_dir, v["worst_shape"])
        lines += [f"Verification of {v['shapes']} shapes: worst RMS {v['worst_rms_mm']:.5f} mm ({v['worst_shape']}), "
                  f"worst max {v['worst_max_mm']:.4f} mm; tolerance {v['tolerance_mm']} mm: "
                  f"{'passed' if v['passed'] else 'FAILED'}.\n",
                  f"Points per bundle after pruning: median {bundles.points_after.median():.0f} of "
                  f"{bundles.points_before.iloc[0]}; simplices: {bundles.simplices.sum()}.\n",
                  "![worst verification error](verification/worst.png)\n"]
    md = "\n".join(lines)
    # The file links relative paths (identical across runs and places); the artifact, absolute ones.
    (out_dir / "report.md").write_text(md)
    absolute = md.replace("(verification/worst.png)", f"({png.as_uri()})").replace(
        "`dataset/`", f"`{summary['path']}`")
    create_markdown_artifact(markdown=absolute, key="rebuild-report")


def _verification_heatmap(out_dir: Path, shape: str) -> Path:
    import numpy as np

    from lgi.index import LGIIndex
    from lgi.render import heatmap_row
    from lgi.solver import LGISolver

    index = LGIIndex.load(out_dir / "index")
    k = index.manifest["shapes"].index(shape)
    truth = np.asarray(index.arrays["neutral"], np.float64) + np.asarray(index.deltas[k + 1], np.float64)
    if index.jaw_rig() is not None:
        truth = index.jaw_rig().skin(truth, index.arrays["jaw_shape_params"][k])
    solver = LGISolver(index)
    r = solver.solve_frame(solver.layout.evaluate(truth), jaw=None if index.jaw_rig() is None
                           else index.arrays["jaw_shape_params"][k])
    err = np.linalg.norm(r.vertices - truth, axis=1) * 10
    from lgi.mesh import triangulate

    tris, _ = triangulate(index.arrays["face_vertices"], index.arrays["face_offsets"])
    return heatmap_row(out_dir / "verification" / "worst.png", index.arrays["neutral"], tris,
                       {f"{shape} (worst)": err}, mask=index.arrays["nn_region"],
                       title="verification: vertex error of the worst shape", label="error (mm)").resolve()


if __name__ == "__main__":
    rebuild_dataset(sys.argv[1], sys.argv[2], markers=sys.argv[3] if len(sys.argv) > 3 else None)
