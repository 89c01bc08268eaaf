"""The per-shot reconstruction flow: frames solved in chunks mapped over the task runner, then smoothed,
blended and written, with a report as Prefect artifacts.

Chunks are independent and deterministic, so any task runner gives identical results: the default
thread runner, or Dask through prefect-dask (``reconstruct_shot.with_options(task_runner=
DaskTaskRunner(...))``, a LocalCluster or an existing scheduler by address).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd
from prefect import flow, unmapped
from prefect.artifacts import (
    create_markdown_artifact,
    create_progress_artifact,
    create_table_artifact,
    update_progress_artifact,
)

from lgi.pipeline import shot_frames
from tasks.shot import finish_shot, solve_chunk, track_footage


@flow(name="reconstruct-shot", log_prints=True)
def reconstruct_shot(
    index_dir: str,
    bundles: str,
    out: str,
    chunk_size: int = 60,
    smooth: int = 1,
    jaw_smooth: int | None = None,
    max_gap: int = 0,
    temporal_weight: float = 0.02,
    spatial_weight: float = 1e-3,
    usd: bool = False,
    footage: str | None = None,
    calib: str | None = None,
    markers: str | None = None,
    helmet: str | None = None,
    noise: float | str = "auto",
    method: str = "local",
) -> dict:
    """Reconstruct a shot into ``out`` (meshes.npz, diagnostics.csv, per_frame.csv/png, shot.usdc).

    With ``footage`` (stereo frames), ``calib`` and ``markers``, the shot starts from the cameras: the
    ``track-footage`` task writes ``bundles`` (and its 2D tracks table) first, with ``helmet`` dots if given.
    """
    tracking = None
    if footage:
        if not (calib and markers):
            raise ValueError("a shot from footage needs calib and markers")
        tracking = track_footage(footage, calib, markers, bundles, helmet=helmet)
        create_table_artifact(table=[{k: v for k, v in tracking.items() if not isinstance(v, (list, dict))}],
                              key="shot-tracking", description="footage to bundles: tracking summary")
    n = shot_frames(bundles)
    bounds = [(lo, min(lo + chunk_size, n)) for lo in range(0, n, chunk_size)]
    work = Path(out).parent / f".{Path(out).name}.chunks"
    progress = create_progress_artifact(progress=0.0, description=f"chunks of {chunk_size} frames solved")
    futures = solve_chunk.map(unmapped(index_dir), unmapped(bundles), [b[0] for b in bounds],
                              [b[1] for b in bounds], [str(work / f"chunk_{lo:06d}.npz") for lo, _ in bounds],
                              unmapped(temporal_weight), unmapped(spatial_weight), unmapped(max_gap),
                              unmapped(noise), unmapped(method))
    chunks = []
    for k, fut in enumerate(futures):
        chunks.append(fut.result())
        update_progress_artifact(progress, progress=100.0 * (k + 1) / len(futures))
    summary = finish_shot(index_dir, bundles, chunks, out, smooth, jaw_smooth, max_gap, temporal_weight,
                          spatial_weight, usd, noise, method)
    for c in chunks:
        Path(c).unlink(missing_ok=True)
    if work.is_dir() and not any(work.iterdir()):
        work.rmdir()
    d = pd.read_csv(Path(out) / "diagnostics.csv")
    per_marker = d.groupby("marker").agg(
        contained=("status", lambda s: round(float((s == "contained").mean()), 3)),
        projected=("status", lambda s: int((s == "projected").sum())),
        neighbour=("status", lambda s: int((s == "neighbour").sum())),
        missing=("status", lambda s: int(s.isin(["missing", "bridged"]).sum())),
        median_projection_mm=("projection_mm", "median")).reset_index()
    create_table_artifact(table=per_marker.to_dict(orient="records"), key="shot-markers",
                          description="per marker: share of frames contained in the data; frames projected, "
                                      "taking a neighbour's blend, missing")
    png = (Path(out) / "per_frame.png").resolve()
    create_markdown_artifact(key="shot-report", markdown=(
        f"# Shot reconstruction\n\n{summary['frames']} frames x {summary['markers']} markers -> `{summary['out']}`\n\n"
        "| contained | projected | neighbour's blend | missing or bridged | max bundle residual |\n"
        "|---|---|---|---|---|\n"
        f"| {summary['contained_share']:.1%} | {summary['projected_share']:.1%} | {summary['neighbour_share']:.1%} "
        f"| {summary['missing_share']:.1%} | {summary['max_residual_mm']:.2e} mm |\n\n"
        f"Per-frame plot: [per_frame.png](file://{png})  \nDiagnostics: `diagnostics.csv`, `per_frame.csv`\n"))
    print(f"shot: {summary['frames']} frames -> {summary['out']}")
    if tracking:
        summary["tracking"] = tracking
    return summary


if __name__ == "__main__":
    reconstruct_shot(sys.argv[1], sys.argv[2], sys.argv[3])
