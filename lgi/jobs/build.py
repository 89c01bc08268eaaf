"""``lgi build``: the LGI index of a dataset for a marker layout (the rebuild-dataset flow's index stage calls
it with the same :class:`~lgi.index.build.IndexOptions`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from lgi.dataset.shapes import ENTRIES as DATASET_ENTRIES
from lgi.dataset.shapes import ShapeDataset
from lgi.io.atomic import check_output, files_in


def build(dataset_dir: str | Path, markers: str | Path, out: str | Path, options=None,
          jaw_rig: str | Path | None = None, show_progress: bool = False) -> dict[str, Any]:
    """``lgi build``: the index of a dataset for a marker layout (options: :class:`~lgi.index.build.IndexOptions`)
    saved to ``out``; returns a summary (:func:`build_report`)."""
    from lgi.dataset.markers import read_layout
    from lgi.index.build import ENTRIES, build_index

    check_output(out, "dir", inputs=[dataset_dir, markers, jaw_rig, *files_in(dataset_dir, DATASET_ENTRIES)],
                 owned=ENTRIES, what="lgi index")
    t0 = time.perf_counter()
    ds = ShapeDataset.load(dataset_dir)
    layout = read_layout(markers, ds.triangles)
    rig = None
    if jaw_rig:
        from lgi.solve.jaw import JawRig

        rig = JawRig.load(jaw_rig, ds.n_vertices)
    index, reports = build_index(ds, layout, options, show_progress=show_progress, jaw_rig=rig)
    index.save(out, reports)
    per = reports["bundles.csv"]
    return {"path": str(Path(out).resolve()), "counts": index.manifest["counts"], "seconds": time.perf_counter() - t0,
            "points_before": int(per.points_before.iloc[0]), "points_after_median": float(per.points_after.median()),
            "points_after_min": int(per.points_after.min()), "points_after_max": int(per.points_after.max()),
            "simplices_median": float(per.simplices.median()), "warnings": list(index.manifest["nn_conflicts"])}


def build_report(s: dict[str, Any]) -> list[str]:
    c = s["counts"]
    return [f"index of {c['shapes']} shapes x {c['markers']} markers built in {s['seconds']:.1f} s",
            f"points per bundle: {s['points_before']} before, {s['points_after_median']:.0f} median after pruning "
            f"({s['points_after_min']}-{s['points_after_max']}); simplices: {c['simplices']} "
            f"({s['simplices_median']:.0f} median per bundle)",
            *(f"warning: {msg}" for msg in s["warnings"]),
            f"index: {s['path']}  (reports: bundles.csv, pruning.csv)"]
