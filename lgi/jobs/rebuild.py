"""The dataset rebuild as cached stages (plain functions; the rebuild-dataset flow's tasks wrap them).

Each stage is keyed by what it depends on and nothing else (see :mod:`lgi.io.cache`):

============  ===========================================================================
read          the OBJ files' bytes; neutral, include/exclude patterns, units, delta mode
stabilise     read's result; the rigid-vertex file's bytes (or ``auto``/``none``)
natural       the dataset's mesh (neutral, topology, UVs); the marker file; region, stiffness
clouds        the dataset's content hash; the marker file; natural's result; pruning/simplex
              options; the jaw rig's bytes
index         natural's and clouds' results; the dataset
verify        the index; the tolerance
============  ===========================================================================

So a re-run with nothing changed computes nothing, and changing one option recomputes only the stages
downstream of it. Every result is a directory of npz/JSON/CSV files, written atomically.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.dataset.importing import RawShapes
from lgi.dataset.markers import read_layout
from lgi.dataset.shapes import ShapeDataset
from lgi.errors import InputError
from lgi.index.build import NATURAL_FIELDS, IndexOptions, assemble_index, clouds_stage, natural_stage
from lgi.index.cloud import CloudOptions
from lgi.io.atomic import atomic_dir
from lgi.io.cache import StageCache, hash_file, hash_tree, locked
from lgi.io.npz import save_npz
from lgi.io.obj import PolyMesh
from lgi.jobs.dataset import AugmentOptions, ImportOptions, augment, published, read_shapes, stabilise_shapes
from lgi.jobs.rig import RigOptions, fit_jaw_rig
from lgi.jobs.verify import VerifyOptions, verify
from lgi.solve.jaw import JawRig

# The modules whose source (with every lgi module they import) keys each stage's results, besides the stage's
# own make function: the code that computes them, not the whole package.
_DATASET = ("lgi.jobs.dataset",)
_INDEX = ("lgi.index.build",)
_VERIFY = ("lgi.jobs.verify",)


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def read_stage(cache: StageCache, shapes_dir: str, options: ImportOptions) -> tuple[Path, bool]:
    """Read a folder of OBJ shapes (:func:`lgi.jobs.dataset.read_shapes`); result: ``raw.npz`` + ``raw.json``."""
    inputs = {"objs": hash_tree(shapes_dir, "*.obj"),
              "options": {k: v for k, v in options.to_json().items() if k != "rigid_vertices"}}

    def make(out: Path) -> None:
        raw = read_shapes(shapes_dir, options)
        m = raw.mesh
        arrays = {"neutral": raw.neutral, "positions": raw.positions, "vertices": m.vertices,
                  "face_vertices": m.face_vertices, "face_offsets": m.face_offsets, "face_material": m.face_material}
        if m.uvs is not None:
            arrays.update(uvs=m.uvs, face_uvs=m.face_uvs)
        save_npz(out / "raw.npz", **arrays)
        (out / "raw.json").write_text(json.dumps({"names": raw.names, "sources": raw.sources, "info": raw.info,
                                                  "materials": m.materials, "mtllib": m.mtllib}, indent=1))

    return cache.run("read", inputs, make, _DATASET)


def _load_raw(path: Path) -> RawShapes:
    a = _load_npz(path / "raw.npz")
    meta = json.loads((path / "raw.json").read_text())
    mesh = PolyMesh(a["vertices"], a["face_vertices"], a["face_offsets"], a.get("uvs"), a.get("face_uvs"),
                    a["face_material"], meta["materials"], meta["mtllib"])
    return RawShapes(mesh, a["neutral"], a["positions"], meta["names"], meta["sources"], meta["info"])


def stabilise_stage(cache: StageCache, raw_dir: Path, options: ImportOptions) -> tuple[Path, bool]:
    """Remove head motion (:func:`lgi.jobs.dataset.stabilise_shapes`); result: a dataset directory."""
    rigid = options.rigid_vertices
    rigid_id = rigid if rigid in (None, "auto", "none") else hash_file(rigid)
    inputs = {"raw": raw_dir.name, "rigid_vertices": rigid_id}

    def make(out: Path) -> None:
        stabilise_shapes(_load_raw(raw_dir), options).save(out / "dataset")

    return cache.run("stabilise", inputs, make, _DATASET)


def augment_stage(cache: StageCache, dataset_dir: Path, options: AugmentOptions,
                  jaw_rig: str | None = None) -> tuple[Path, bool]:
    """In-betweens (:func:`lgi.jobs.dataset.augment`); result: a dataset directory with the captured shapes
    first."""
    inputs = {"dataset": [hash_file(dataset_dir / f) for f in ("manifest.json", "mesh.npz", "deltas.npy")],
              "options": options.to_json(), "jaw_rig": hash_file(jaw_rig) if jaw_rig else None}

    def make(out: Path) -> None:
        ds = ShapeDataset.load(dataset_dir)
        rig = None
        if jaw_rig:
            from lgi.solve.jaw import JawRig

            rig = JawRig.load(jaw_rig, ds.n_vertices)
        augment(ds, options, rig).save(out / "dataset")

    return cache.run("augment", inputs, make, _DATASET)


def natural_stage_cached(cache: StageCache, dataset_dir: Path, markers: str,
                         opts: IndexOptions) -> tuple[Path, bool]:
    """Natural-neighbour weights and the correction basis; result: ``natural.npz``."""
    inputs = {"mesh": hash_file(dataset_dir / "mesh.npz"), "markers": hash_file(markers),
              "options": {k: getattr(opts, k) for k in NATURAL_FIELDS}}

    def make(out: Path) -> None:
        ds = ShapeDataset.load(dataset_dir, mmap=True)
        save_npz(out / "natural.npz", **natural_stage(ds, read_layout(markers, ds.triangles), opts))

    return cache.run("natural", inputs, make, _INDEX)


def clouds_stage_cached(cache: StageCache, dataset_dir: Path, markers: str, natural_dir: Path, opts: IndexOptions,
                        jaw_rig: str | None = None) -> tuple[Path, bool]:
    """Point clouds, pruning, simplices, grids; result: ``clouds.npz``, ``pruning.csv``, ``bundles.csv``."""
    opt = {k: v for k, v in opts.to_json().items() if k not in NATURAL_FIELDS}
    inputs = {"dataset": json.loads((dataset_dir / "manifest.json").read_text())["content_hash"],
              "markers": hash_file(markers), "natural": natural_dir.name, "options": opt,
              "jaw_rig": None if not jaw_rig else hash_file(jaw_rig)}

    def make(out: Path) -> None:
        ds = ShapeDataset.load(dataset_dir, mmap=True)
        rig = JawRig.load(jaw_rig, ds.n_vertices) if jaw_rig else None
        arrays, reports = clouds_stage(ds, read_layout(markers, ds.triangles), opts,
                                       _load_npz(natural_dir / "natural.npz"), rig)
        save_npz(out / "clouds.npz", **arrays)
        for name, df in reports.items():
            df.to_csv(out / name, index=False, float_format="%.6g")

    return cache.run("clouds", inputs, make, _INDEX)


def index_stage(cache: StageCache, dataset_dir: Path, markers: str, natural_dir: Path, clouds_dir: Path,
                opts: IndexOptions, jaw_rig: str | None = None) -> tuple[Path, bool]:
    """Assemble the index; result: ``index/`` (an index directory)."""
    inputs = {"natural": natural_dir.name, "clouds": clouds_dir.name, "options": opts.to_json(),
              "dataset": json.loads((dataset_dir / "manifest.json").read_text())["content_hash"],
              "markers": hash_file(markers), "jaw_rig": None if not jaw_rig else hash_file(jaw_rig)}

    def make(out: Path) -> None:
        ds = ShapeDataset.load(dataset_dir, mmap=True)
        rig = JawRig.load(jaw_rig, ds.n_vertices) if jaw_rig else None
        index = assemble_index(ds, read_layout(markers, ds.triangles), opts, _load_npz(natural_dir / "natural.npz"),
                               _load_npz(clouds_dir / "clouds.npz"), rig)
        reports = {name: pd.read_csv(clouds_dir / name) for name in ("pruning.csv", "bundles.csv")}
        index.save(out / "index", reports)

    return cache.run("index", inputs, make, _INDEX)


def rig_stage(cache: StageCache, dataset_dir: Path, options: RigOptions) -> tuple[Path, bool]:
    """The jaw rig fitted from the dataset's jaw shapes (:func:`lgi.jobs.rig.fit_jaw_rig`); result:
    ``jaw_rig.npz`` and the fit's report ``rig.json``."""
    spec = options.jaw_vertices
    inputs = {"dataset": json.loads((dataset_dir / "manifest.json").read_text())["content_hash"],
              "options": asdict(options), "jaw_vertices_file": hash_file(spec) if Path(spec).is_file() else None}

    def make(out: Path) -> None:
        summary = fit_jaw_rig(dataset_dir, out / "jaw_rig.npz", options)
        (out / "rig.json").write_text(json.dumps(summary, indent=1))

    return cache.run("rig", inputs, make, _VERIFY)


def verify_stage(cache: StageCache, index_dir: Path, options: VerifyOptions) -> tuple[Path, bool]:
    """The paper's verification (:func:`lgi.jobs.verify.verify`); result: ``verification.csv`` and
    ``summary.json``."""
    inputs = {"index": index_dir.name, "options": options.to_json()}

    def make(out: Path) -> None:
        table, summary = verify(index_dir / "index", options)
        table.to_csv(out / "verification.csv", index=False, float_format="%.6g")
        (out / "summary.json").write_text(json.dumps(summary, indent=1))
        verification_chart(table, options.tolerance, out / "errors.png")

    # This module too: the chart is drawn here.
    return cache.run("verify", inputs, make, (*_VERIFY, "lgi.jobs.rebuild"))


def options_from(params: dict[str, Any] | None) -> IndexOptions:
    """IndexOptions from a flat dict (cloud options and index options mixed, unknown keys refused)."""
    params = dict(params or {})
    cloud_keys = set(asdict(CloudOptions()))
    index_keys = set(IndexOptions.__dataclass_fields__) - {"cloud"}
    unknown = sorted(set(params) - cloud_keys - index_keys)
    if unknown:
        raise InputError(f"unknown index options {unknown}; known: {sorted(cloud_keys | index_keys)}")
    cloud = CloudOptions(**{k: params.pop(k) for k in list(params) if k in cloud_keys})
    return IndexOptions(cloud=cloud, **params)


def publish(src: Path, dest: str | os.PathLike[str], kind: str) -> Path:
    """Copy a cached result directory of ``kind`` (see :func:`published`) to its user-facing place,
    atomically."""

    dest = Path(dest)
    # Two rebuilds into one OUT publish in turn (each replaces the folder whole; without the lock one could
    # find the other's half-moved folder). The lock file lives in OUT/.cache, the pipeline's own folder, not
    # beside the published folders (a lock file cannot be removed after use without breaking the turn-taking).
    with locked(dest.parent / ".cache" / f".publish-{dest.name}.lock"), atomic_dir(dest, *published(kind)) as tmp:
        shutil.copytree(src, tmp, dirs_exist_ok=True, ignore=shutil.ignore_patterns(".complete", ".*.lock"))
    # Where earlier versions kept the lock: nothing takes it any more.
    (dest.parent / f".{dest.name}.lock").unlink(missing_ok=True)
    return dest


def rebuild_report(s: dict[str, Any]) -> list[str]:
    """The rebuild-dataset flow's summary as the lines ``lgi import --flow`` prints."""
    lines = [f"rebuild-dataset flow: {s['n_shapes']} shapes -> {s['path']}"]
    if "augmented" in s:
        lines.append(f"augmented: {s['augmented']['n_shapes']} shapes -> {s['augmented']['path']}")
    if "verification" in s:
        v = s["verification"]
        lines.append(f"index: {s['index']}; verification of {v['shapes']} shapes: worst RMS {v['worst_rms_mm']:.5f} mm "
                     f"({v['worst_shape']}), tolerance {v['tolerance_mm']} mm: {'passed' if v['passed'] else 'FAILED'}")
    lines.append(f"stages computed: {[k for k, hit in s['stages'].items() if not hit] or 'none (all cached)'}")
    return lines


def rebuild_markdown(summary: dict[str, Any], out_dir: Path) -> tuple[str, Path | None]:
    """The rebuild's markdown report (relative links; also written to ``OUT/report.md``) and, with an index, its
    picture: the per-shape verification error chart (``OUT/verification/errors.png``)."""
    lines = ["# Dataset rebuild\n", f"`dataset/`: {summary['n_shapes']} shapes, {summary['n_vertices']} "
             f"vertices, content hash `{summary['content_hash'][:16]}`, stabilisation: {summary['stabilisation']}.\n",
             "| stage | " + " | ".join(summary["stages"]) + " |", "|---|" + "---|" * len(summary["stages"]),
             "| cached | " + " | ".join("yes" if v else "computed" for v in summary["stages"].values()) + " |\n"]
    png = None
    if "verification" in summary:
        v = summary["verification"]
        bundles = pd.read_csv(out_dir / "index" / "bundles.csv")
        png = out_dir / "verification" / "errors.png"
        lines += [f"Verification of {v['shapes']} shapes: worst RMS {v['worst_rms_mm']:.5f} mm ({v['worst_shape']}), "
                  f"worst max {v['worst_max_mm']:.4f} mm; tolerance {v['tolerance_mm']} mm: "
                  f"{'passed' if v['passed'] else 'FAILED'}.\n",
                  f"Points per bundle after pruning: median {bundles.points_after.median():.0f} of "
                  f"{bundles.points_before.iloc[0]}; simplices: {bundles.simplices.sum()}.\n"]
        if png.is_file():
            lines.append("![verification error per shape](verification/errors.png)\n")
        else:  # a verification cached before the chart existed
            png = None
    md = "\n".join(lines)
    (out_dir / "report.md").write_text(md)
    return md, png


def verification_chart(table: pd.DataFrame, tolerance: float, path: Path, most: int = 40) -> Path:
    """Bar chart of the verification's per-shape error (RMS and max over the marked region, mm) on a log
    scale with the tolerance, the worst shapes on top (at most ``most`` of them: the title says how many of
    how many). A log scale because a passing verification spans orders of magnitude below the tolerance,
    where a linear one (or a colour map of the worst shape) shows nothing. Exact zeros are drawn at the
    axis' floor; a non-finite error as a red bar across the chart."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = table.assign(_key=np.nan_to_num(table.rms_mm.to_numpy(float), nan=np.inf)).sort_values("_key")
    t = t.iloc[-most:]
    rms, mx = t.rms_mm.to_numpy(float), t.max_mm.to_numpy(float)
    finite = np.concatenate([rms[np.isfinite(rms) & (rms > 0)], mx[np.isfinite(mx) & (mx > 0)], [tolerance]])
    lo = 10.0 ** np.floor(np.log10(finite.min())) / 10.0
    hi = 10.0 ** np.ceil(np.log10(finite.max() * 1.5))
    y = np.arange(len(t))
    fig, ax = plt.subplots(figsize=(8.0, 1.6 + 0.24 * len(t)), layout="constrained")
    for values, dy, colour, label in ((mx, 0.2, "#9ecae1", "max"), (rms, -0.2, "#08519c", "RMS")):
        bad = ~np.isfinite(values)
        shown = np.where(bad, hi, np.maximum(np.nan_to_num(values), lo))
        ax.barh(y + dy, shown - lo, left=lo, height=0.4, color=np.where(bad, "#d62728", colour), label=label)
    for k in range(len(t)):
        if not np.isfinite(rms[k]):
            ax.text(lo * 1.3, k - 0.2, "not finite", va="center", fontsize=7, color="white")
        elif rms[k] == 0:
            ax.text(lo * 1.3, k - 0.2, "exact (0)", va="center", fontsize=7)
    ax.axvline(tolerance, color="#d62728", linestyle="--", linewidth=1, label=f"tolerance on the RMS, {tolerance:g} mm")
    ax.set_xscale("log")
    ax.set_xlim(lo, hi)
    ax.set_yticks(y, t["shape"].astype(str).tolist(), fontsize=8)
    ax.set_ylim(-0.7, len(t) - 0.3)
    ax.set_xlabel("vertex error over the marked region (mm, log scale)")
    ax.grid(axis="x", which="major", alpha=0.3)
    fig.legend(loc="outside lower center", ncols=3, fontsize=8)  # below the axes: it never hides a bar
    shown_of = f"the {len(t)} worst of {len(table)} shapes" if len(t) < len(table) else f"{len(table)} shapes"
    ax.set_title(f"Verification: each shape from its own bundles, {shown_of}", fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
