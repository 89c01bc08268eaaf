"""Per-shot reconstruction stages as Prefect tasks: thin wrappers over :mod:`lgi.pipeline`."""

from __future__ import annotations

from prefect import task
from prefect.cache_policies import NO_CACHE

from lgi import pipeline

_T = {"cache_policy": NO_CACHE, "persist_result": False}


@task(name="track-footage", **_T)
def track_footage(footage: str, calib: str, markers: str, bundles: str, dataset: str | None = None,
                  units: str = "cm", helmet: str | None = None, labels: str | None = None, reference: int = 0) -> dict:
    """Stereo footage to the bundles file and the 2D tracks table (see :func:`lgi.footage.track_to_files`)."""
    from lgi.footage import track_to_files

    _, summary = track_to_files(footage, calib, markers, bundles, dataset=dataset, units=units, labels=labels,
                                reference=reference, helmet=helmet)
    return summary


@task(name="solve-chunk", **_T)
def solve_chunk(index_dir: str, bundles: str, lo: int, hi: int, out: str, temporal_weight: float = 0.02,
                spatial_weight: float = 1e-3, max_gap: int = 0, noise: float | str = "auto",
                method: str = "local") -> str:
    """Choose shapes and weights for frames lo:hi (see :func:`lgi.pipeline.select_chunk`)."""
    return pipeline.select_chunk(index_dir, bundles, lo, hi, out, temporal_weight, spatial_weight, max_gap, noise,
                                 method)


@task(name="finish-shot", **_T)
def finish_shot(index_dir: str, bundles: str, chunks: list[str], out: str, smooth: int = 1,
                jaw_smooth: int | None = None, max_gap: int = 0, temporal_weight: float = 0.02,
                spatial_weight: float = 1e-3, usd: bool = False, noise: float | str = "auto",
                method: str = "local") -> dict:
    """Smooth, blend, correct and write the shot (see :func:`lgi.pipeline.finish_shot`)."""
    return pipeline.finish_shot(index_dir, bundles, chunks, out, smooth, jaw_smooth, max_gap, temporal_weight,
                                spatial_weight, usd, noise, method)
