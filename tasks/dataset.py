"""Dataset and index stages as Prefect tasks: thin wrappers over :mod:`lgi.pipeline`.

Caching is content-addressed and file-based (:mod:`lgi.cache`), not Prefect's pickled results: each
task returns the path of its result directory and whether it was already there.
"""

from __future__ import annotations

from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from lgi import pipeline
from lgi.cache import StageCache
from lgi.index import IndexOptions

_T = {"cache_policy": NO_CACHE, "persist_result": False}


@task(name="read-shapes", **_T)
def read_shapes(cache_dir: str, shapes_dir: str, neutral: str | None = None, include: str | None = None,
                exclude: str | None = None, units: str = "cm", deltas: bool = False) -> tuple[str, bool]:
    """Read a folder of OBJ shapes (see :func:`lgi.pipeline.read_stage`)."""
    path, hit = pipeline.read_stage(StageCache(cache_dir), shapes_dir, neutral, include, exclude, units, deltas)
    return str(path), hit


@task(name="stabilise", **_T)
def stabilise(cache_dir: str, raw_dir: str, rigid_vertices: str | None = "auto") -> tuple[str, bool]:
    """Remove head motion and save the dataset (see :func:`lgi.pipeline.stabilise_stage`)."""
    path, hit = pipeline.stabilise_stage(StageCache(cache_dir), Path(raw_dir), rigid_vertices)
    return str(path), hit


@task(name="augment", **_T)
def augment(cache_dir: str, dataset_dir: str, params: dict, jaw_rig: str | None = None) -> tuple[str, bool]:
    """Linear and/or simulated in-betweens (see :func:`lgi.pipeline.augment_stage`)."""
    path, hit = pipeline.augment_stage(StageCache(cache_dir), Path(dataset_dir), params, jaw_rig)
    return str(path), hit


@task(name="natural-neighbours", **_T)
def natural_neighbours(cache_dir: str, dataset_dir: str, markers: str, options: dict) -> tuple[str, bool]:
    """Geodesic Voronoi, Sibson weights and the correction basis."""
    path, hit = pipeline.natural_stage_cached(StageCache(cache_dir), Path(dataset_dir), markers,
                                              IndexOptions.from_json(options))
    return str(path), hit


@task(name="point-clouds-and-simplices", **_T)
def point_clouds(cache_dir: str, dataset_dir: str, markers: str, natural_dir: str, options: dict,
                 jaw_rig: str | None = None) -> tuple[str, bool]:
    """Per-bundle point clouds (pruned), overlapping simplices and grids."""
    path, hit = pipeline.clouds_stage_cached(StageCache(cache_dir), Path(dataset_dir), markers, Path(natural_dir),
                                             IndexOptions.from_json(options), jaw_rig)
    return str(path), hit


@task(name="assemble-index", **_T)
def assemble(cache_dir: str, dataset_dir: str, markers: str, natural_dir: str, clouds_dir: str, options: dict,
             jaw_rig: str | None = None) -> tuple[str, bool]:
    """The index directory from the stages above."""
    path, hit = pipeline.index_stage(StageCache(cache_dir), Path(dataset_dir), markers, Path(natural_dir),
                                     Path(clouds_dir), IndexOptions.from_json(options), jaw_rig)
    return str(path), hit


@task(name="verify", **_T)
def verify(cache_dir: str, index_dir: str, tolerance: float = 0.01) -> tuple[str, bool]:
    """Every dataset shape reconstructed from its own bundles."""
    path, hit = pipeline.verify_stage(StageCache(cache_dir), Path(index_dir), tolerance)
    return str(path), hit


@task(name="publish", **_T)
def publish(src: str, dest: str) -> str:
    """Copy a cached result to its user-facing place, atomically."""
    return str(pipeline.publish(Path(src), dest))
