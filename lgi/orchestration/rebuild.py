"""The dataset rebuild as Prefect tasks and a flow: read, stabilise, (augment,) and with markers the index
stages and the verification; one task per stage of :mod:`lgi.jobs.rebuild`, each cached by content.

A re-run with nothing changed computes nothing; changing one option recomputes only the stages that depend
on it. The stages run the job layer's functions (:mod:`lgi.jobs.dataset`, :mod:`lgi.jobs.rig`,
:mod:`lgi.jobs.verify`) with the same options objects as ``lgi import`` / ``lgi augment`` / ``lgi verify``.
"""

from __future__ import annotations

import functools
import json
import re
import shutil
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import pandas as pd
from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact, create_table_artifact
from prefect.cache_policies import NO_CACHE
from prefect.states import Completed, State

from lgi.errors import InputError
from lgi.index.build import IndexOptions
from lgi.io.cache import StageCache
from lgi.jobs import rebuild
from lgi.jobs.dataset import REBUILD_OUTPUTS, AugmentOptions, ImportOptions, check_rebuild
from lgi.jobs.rig import RigOptions
from lgi.jobs.verify import VerifyOptions
from lgi.options import Subset, flow_parameters, take
from lgi.orchestration import artifact_key, capture_library_logs, embedded_png, transient_only
from lgi.orchestration.deploy import run_paths
from lgi.orchestration.params import described

# Stage results are files in the stage cache, never Prefect results (no pickles); I/O may be retried; the
# timeouts are generous bounds that stop a hung run from holding the deployment's concurrency slot forever.
_T = {"cache_policy": NO_CACHE, "persist_result": False, "retries": 2, "retry_delay_seconds": 10,
      "retry_condition_fn": transient_only}


def _hours(h: float) -> dict:
    return {**_T, "timeout_seconds": h * 3600}


def _done(path: Path, hit: bool) -> tuple[str, bool] | State:
    """A stage's result; a cache hit ends in a state named Cached, as Prefect's own cache hits do in the UI."""
    value = (str(path), hit)
    return Completed(data=value, name="Cached", message="stage result reused from the cache") if hit else value


def _call(stage, *args):
    """Run a stage task and return its value (a Cached state's too); a failed stage raises its error."""
    return stage(*args, return_state=True).result()


@task(name="read-shapes", **_hours(1))
def read_shapes(cache_dir: str, shapes_dir: str, options: dict) -> tuple[str, bool] | State:
    """Read a folder of OBJ shapes (see :func:`lgi.jobs.rebuild.read_stage`)."""
    path, hit = rebuild.read_stage(StageCache(cache_dir), shapes_dir, ImportOptions.from_json(options))
    return _done(path, hit)


@task(name="stabilise", **_hours(1))
def stabilise(cache_dir: str, raw_dir: str, options: dict) -> tuple[str, bool] | State:
    """Remove head motion and save the dataset (see :func:`lgi.jobs.rebuild.stabilise_stage`)."""
    path, hit = rebuild.stabilise_stage(StageCache(cache_dir), Path(raw_dir), ImportOptions.from_json(options))
    return _done(path, hit)


@task(name="augment", **_hours(12))
def augment(cache_dir: str, dataset_dir: str, options: dict, jaw_rig: str | None = None) -> tuple[str, bool] | State:
    """Linear and/or simulated in-betweens (see :func:`lgi.jobs.rebuild.augment_stage`)."""
    path, hit = rebuild.augment_stage(StageCache(cache_dir), Path(dataset_dir), AugmentOptions.from_json(options),
                                       jaw_rig)
    return _done(path, hit)


@task(name="natural-neighbours", **_hours(2))
def natural_neighbours(cache_dir: str, dataset_dir: str, markers: str, options: dict) -> tuple[str, bool] | State:
    """Geodesic Voronoi, Sibson weights and the correction basis."""
    path, hit = rebuild.natural_stage_cached(StageCache(cache_dir), Path(dataset_dir), markers,
                                              IndexOptions.from_json(options))
    return _done(path, hit)


@task(name="point-clouds-and-simplices", **_hours(12))
def point_clouds(cache_dir: str, dataset_dir: str, markers: str, natural_dir: str, options: dict,
                 jaw_rig: str | None = None) -> tuple[str, bool] | State:
    """Per-bundle point clouds (pruned), overlapping simplices and grids."""
    path, hit = rebuild.clouds_stage_cached(StageCache(cache_dir), Path(dataset_dir), markers, Path(natural_dir),
                                             IndexOptions.from_json(options), jaw_rig)
    return _done(path, hit)


@task(name="assemble-index", **_hours(2))
def assemble(cache_dir: str, dataset_dir: str, markers: str, natural_dir: str, clouds_dir: str, options: dict,
             jaw_rig: str | None = None) -> tuple[str, bool] | State:
    """The index directory from the stages above."""
    path, hit = rebuild.index_stage(StageCache(cache_dir), Path(dataset_dir), markers, Path(natural_dir),
                                     Path(clouds_dir), IndexOptions.from_json(options), jaw_rig)
    return _done(path, hit)


@task(name="fit-jaw-rig", **_hours(1))
def fit_rig(cache_dir: str, dataset_dir: str, options: dict) -> tuple[str, bool] | State:
    """The jaw rig from the dataset's jaw shapes (see :func:`lgi.jobs.rebuild.rig_stage`)."""
    path, hit = rebuild.rig_stage(StageCache(cache_dir), Path(dataset_dir), RigOptions(**options))
    return _done(path, hit)


@task(name="verify", **_hours(6))
def verify(cache_dir: str, index_dir: str, options: dict) -> tuple[str, bool] | State:
    """Every dataset shape reconstructed from its own bundles (see :func:`lgi.jobs.verify.verify`)."""
    path, hit = rebuild.verify_stage(StageCache(cache_dir), Path(index_dir), VerifyOptions(**options))
    return _done(path, hit)


@task(name="publish", **_hours(1))
def publish(src: str, dest: str, kind: str) -> str:
    """Copy a cached result of ``kind`` ("dataset", "index", "verification") to its user-facing place,
    atomically."""
    return str(rebuild.publish(Path(src), dest, kind))


#: The verification options the rebuild takes: ``tolerance`` and ``verify_shapes``.
REBUILD_VERIFY = (Subset(VerifyOptions, only=("tolerance",), help_prefix="verification: "),
                  Subset(VerifyOptions, "verify_", ("shapes",), "verification: "))


@flow(name="rebuild-dataset")
@described(ImportOptions, *REBUILD_VERIFY, shapes_dir="Folder of OBJ shapes (the neutral and one file per expression).",
           out="Output folder: dataset/, and with markers index/ and verification/ (dataset_augmented/ with "
               "augmentation); the stage cache in out/.cache unless cache_dir is given.",
           markers="Marker layout CSV: also build the index and verify it (lgi build, lgi verify).",
           index_options="Options of lgi build as a flat object (cloud and index options; unknown keys refused).",
           jaw_rig="Jaw rig npz (lgi rig): the shapes are unskinned before indexing.",
           rig="Fit the jaw rig here instead (a cached stage, published as rig/): the options of lgi rig, e.g. "
               '{"jaw_vertices": "jaw_vertices.txt", "shapes": "jaw*"}; excludes jaw_rig.',
           cache_dir="Stage cache folder (default out/.cache); lgi cache ls / prune list and trim it.",
           augmentation="In-betweens before indexing, the options of lgi augment as an object, e.g. "
                        '{"simulate": true, "budget": 100} (unknown keys refused; null: none).')
@flow_parameters(ImportOptions, *REBUILD_VERIFY, after=2)
def rebuild_dataset(
    shapes_dir: str,
    out: str,
    markers: str | None = None,
    index_options: dict | None = None,
    jaw_rig: str | None = None,
    rig: RigOptions | None = None,
    cache_dir: str | None = None,
    augmentation: AugmentOptions | None = None,
    **options: Any,
) -> dict:
    """Build ``OUT/dataset`` and, with ``markers``, ``OUT/index`` and ``OUT/verification/``.

    The import options are those of ``lgi import`` (:class:`~lgi.jobs.dataset.ImportOptions`);
    ``augmentation`` those of ``lgi augment`` (:class:`~lgi.jobs.dataset.AugmentOptions`, e.g. ``{"simulate":
    true, "budget": 100}``; unknown keys are refused), which adds ``OUT/dataset_augmented`` and builds the index
    from it; ``index_options`` those of ``lgi build`` (:class:`~lgi.index.build.IndexOptions`, cloud options
    flat); ``tolerance`` and ``verify_shapes`` those of ``lgi verify``.

    Returns a summary: paths, the dataset's content hash, counts, verification figures, and which stages
    were cache hits (``stages``: name -> true if nothing was computed).
    """
    capture_library_logs()
    at = run_paths()  # a deployment run's relative paths go under the data root, never the worker's cwd
    shapes_dir, out, markers = at(shapes_dir, "shapes_dir"), at(out, "out", output=True), at(markers, "markers")
    options["rigid_vertices"] = at(options.get("rigid_vertices", "auto"), "rigid_vertices", ("auto", "none"))
    jaw_rig, cache_dir = at(jaw_rig, "jaw_rig"), at(cache_dir, "cache_dir", output=True)
    if rig is not None:
        rig = rig if isinstance(rig, RigOptions) else RigOptions(**rig)
        if not re.fullmatch(r"\s*\d+\s*:\s*\d+\s*", rig.jaw_vertices):  # an index file, not FIRST:LAST
            rig = replace(rig, jaw_vertices=at(rig.jaw_vertices, "rig.jaw_vertices"))
    imp = ImportOptions(**take(ImportOptions, options))
    aug_opts = (augmentation if isinstance(augmentation, AugmentOptions) or augmentation is None
                else AugmentOptions.from_json(augmentation))
    idx_opts = rebuild.options_from(index_options).to_json() if markers else None
    ver_opts = VerifyOptions(**{k: v for spec in REBUILD_VERIFY for k, v in take(spec, options).items()}).to_json()
    if rig is not None and jaw_rig:
        raise InputError("give either jaw_rig (a fitted rig) or rig (fit one), not both")
    check_rebuild(shapes_dir, out, imp, markers, jaw_rig, cache_dir)
    out_dir = Path(out)
    cache = cache_dir or str(out_dir / ".cache")
    stages: dict[str, bool] = {}
    raw, stages["read"] = _call(read_shapes, cache, shapes_dir, imp.to_json())
    staged, stages["stabilise"] = _call(stabilise, cache, raw, imp.to_json())
    dataset_dir = str(Path(staged) / "dataset")
    rig_summary = rig_dir = None
    if rig is not None:
        rig_opts = rig if isinstance(rig, RigOptions) else RigOptions(**rig)
        rig_dir, stages["rig"] = _call(fit_rig, cache, dataset_dir, asdict(rig_opts))
        jaw_rig = str(Path(rig_dir) / "jaw_rig.npz")
        rig_summary = json.loads((Path(rig_dir) / "rig.json").read_text())
        for w in rig_summary.get("warnings", []):
            get_run_logger().warning("jaw rig: %s", w)
    # Published only once every stage has succeeded: a run failing at the index leaves OUT as it was.
    outputs = {"dataset": (dataset_dir, "dataset")}
    if rig_dir is not None:
        outputs["rig"] = (rig_dir, "rig")
    manifest = json.loads((Path(dataset_dir) / "manifest.json").read_text())
    summary = {"path": str((out_dir / "dataset").resolve()), "content_hash": manifest["content_hash"],
               "n_shapes": manifest["n_shapes"], "n_vertices": manifest["n_vertices"],
               "stabilisation": manifest["info"].get("stabilisation", {}).get("method", "none"), "stages": stages}
    if rig_summary is not None:
        summary["rig"] = {"path": str((out_dir / "rig" / "jaw_rig.npz").resolve()),
                          **{k: rig_summary[k] for k in ("n_shapes", "jaw_vertices", "pivot", "warnings")}}
    if aug_opts is not None:
        aug, stages["augment"] = _call(augment, cache, dataset_dir, aug_opts.to_json(), jaw_rig)
        dataset_dir = str(Path(aug) / "dataset")
        outputs["dataset_augmented"] = (dataset_dir, "dataset")
        aug_manifest = json.loads((Path(dataset_dir) / "manifest.json").read_text())
        summary["augmented"] = {"path": str((out_dir / "dataset_augmented").resolve()),
                                "n_shapes": aug_manifest["n_shapes"], **aug_manifest["info"].get("augmented", {})}
    if markers:
        nat, stages["natural"] = _call(natural_neighbours, cache, dataset_dir, markers, idx_opts)
        clouds, stages["clouds"] = _call(point_clouds, cache, dataset_dir, markers, nat, idx_opts, jaw_rig)
        idx, stages["index"] = _call(assemble, cache, dataset_dir, markers, nat, clouds, idx_opts, jaw_rig)
        ver, stages["verify"] = _call(verify, cache, idx, ver_opts)
        outputs["index"] = (str(Path(idx) / "index"), "index")
        outputs["verification"] = (ver, "verification")
        summary["verification"] = json.loads((Path(ver) / "summary.json").read_text())
        summary["index"] = str((out_dir / "index").resolve())
    for name, (src, kind) in outputs.items():
        publish(src, str(out_dir / name), kind)
    for name in sorted(set(REBUILD_OUTPUTS) - set(outputs)):
        # An earlier run's index or augmented dataset that this run did not make (check_rebuild has checked
        # they hold only what lgi writes there) would be read as this run's.
        shutil.rmtree(out_dir / name, ignore_errors=True)
    _artifacts(summary, out_dir)
    logger = get_run_logger()
    for line in rebuild.rebuild_report(summary):
        logger.info(line)
    return summary


def _artifacts(summary: dict, out_dir: Path) -> None:
    """Table artifacts (shapes, bundles, verification) and the markdown report (:func:`lgi.jobs.rebuild.
    rebuild_markdown`) with absolute links."""
    manifest = json.loads((out_dir / "dataset" / "manifest.json").read_text())
    shapes = [{"shape": s["name"], "source": s["source"], "tags": ",".join(s["tags"]),
               "removed_translation": round(float(sum(r[3] ** 2 for r in s["rigid_transform"][:3]) ** 0.5), 6)}
              for s in manifest["shapes"]]
    key = functools.partial(artifact_key, path=out_dir)
    create_table_artifact(table=shapes, key=key("dataset-shapes"), description="shapes and the head motion removed")
    md, png = rebuild.rebuild_markdown(summary, out_dir)
    if "verification" in summary:
        bundles = pd.read_csv(out_dir / "index" / "bundles.csv")
        create_table_artifact(table=bundles.to_dict(orient="records"), key=key("index-bundles"),
                              description="per bundle: points before/after pruning, simplices by kind")
        table = pd.read_csv(out_dir / "verification" / "verification.csv")
        create_table_artifact(table=table.round(6).to_dict(orient="records"), key=key("verification"),
                              description="every shape from its own bundles: error in mm")
    absolute = md.replace("`dataset/`", f"`{summary['path']}`")
    if png is not None:
        absolute = absolute.replace("![verification error per shape](verification/errors.png)",
                                    embedded_png(png, "verification error per shape"))
    create_markdown_artifact(markdown=absolute, key=key("rebuild-report"),
                             description="the rebuild's report: stages computed or cached, verification and its chart")
