"""The dataset rebuild as cached stages (plain functions; the Prefect tasks in ``tasks/`` wrap them).

Each stage is keyed by what it depends on and nothing else (see :mod:`lgi.cache`):

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
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .cache import StageCache, hash_file, hash_tree
from .dataset import ShapeDataset
from .importers import RawShapes, assemble_dataset, read_shape_folder, stabilise_raw
from .index import IndexOptions, LGIIndex, assemble_index, clouds_stage, natural_stage
from .markers import read_layout
from .npz import save_npz
from .obj import PolyMesh


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def read_stage(cache: StageCache, shapes_dir: str, neutral: str | None = None, include: str | None = None,
               exclude: str | None = None, units: str = "cm", deltas: bool = False) -> tuple[Path, bool]:
    """Read a folder of OBJ shapes; result: ``raw.npz`` + ``raw.json``."""
    inputs = {"objs": hash_tree(shapes_dir, "*.obj"), "neutral": neutral, "include": include, "exclude": exclude,
              "units": units, "deltas": deltas}

    def make(out: Path) -> None:
        raw = read_shape_folder(shapes_dir, neutral=neutral, include=include, exclude=exclude, units=units,
                                deltas=deltas, show_progress=False)
        m = raw.mesh
        arrays = {"neutral": raw.neutral, "positions": raw.positions, "vertices": m.vertices,
                  "face_vertices": m.face_vertices, "face_offsets": m.face_offsets, "face_material": m.face_material}
        if m.uvs is not None:
            arrays.update(uvs=m.uvs, face_uvs=m.face_uvs)
        save_npz(out / "raw.npz", **arrays)
        (out / "raw.json").write_text(json.dumps({"names": raw.names, "sources": raw.sources, "info": raw.info,
                                                  "materials": m.materials, "mtllib": m.mtllib}, indent=1))

    return cache.run("read", inputs, make)


def _load_raw(path: Path) -> RawShapes:
    a = _load_npz(path / "raw.npz")
    meta = json.loads((path / "raw.json").read_text())
    mesh = PolyMesh(a["vertices"], a["face_vertices"], a["face_offsets"], a.get("uvs"), a.get("face_uvs"),
                    a["face_material"], meta["materials"], meta["mtllib"])
    return RawShapes(mesh, a["neutral"], a["positions"], meta["names"], meta["sources"], meta["info"])


def stabilise_stage(cache: StageCache, raw_dir: Path, rigid_vertices: str | None = "auto") -> tuple[Path, bool]:
    """Remove head motion; result: a dataset directory."""
    rigid = "none" if rigid_vertices in (None, "none") else rigid_vertices
    rigid_id = rigid if rigid in ("auto", "none") else hash_file(rigid)
    inputs = {"raw": raw_dir.name, "rigid_vertices": rigid_id}

    def make(out: Path) -> None:
        raw = _load_raw(raw_dir)
        assemble_dataset(raw, *stabilise_raw(raw, None if rigid == "none" else rigid)).save(out / "dataset")

    return cache.run("stabilise", inputs, make)


def augment_stage(cache: StageCache, dataset_dir: Path, params: dict[str, Any],
                  jaw_rig: str | None = None) -> tuple[Path, bool]:
    """In-betweens (:mod:`lgi.augment`); result: a dataset directory with the captured shapes first.

    ``params``: ``linear`` and/or ``simulate`` (bool), ``budget`` (combinations per method), ``levels``,
    ``orders``, ``seed``, ``thickness`` and ``iterations`` (simulation).
    """
    from .augment import linear_combinations, pick_combinations, simulated_combinations
    from .flesh import FleshOptions

    p = {"linear": False, "simulate": False, "budget": 200, "levels": [0.25, 0.5, 0.75, 1.0], "orders": [2, 3],
         "seed": 0, "thickness": 0.8, "iterations": 60, **params}
    inputs = {"dataset": [hash_file(dataset_dir / f) for f in ("manifest.json", "mesh.npz", "deltas.npy")],
              "params": p, "jaw_rig": hash_file(jaw_rig) if jaw_rig else None}

    def make(out: Path) -> None:
        ds = ShapeDataset.load(dataset_dir)
        picks = pick_combinations(ds.names, int(p["budget"]), tuple(p["levels"]), tuple(p["orders"]), int(p["seed"]))
        aug = ds
        if p["linear"]:
            aug = linear_combinations(aug, 0, picks=picks)
        if p["simulate"]:
            rig = None
            if jaw_rig:
                from .jaw import JawRig

                rig = JawRig.load(jaw_rig, ds.n_vertices)
            aug = simulated_combinations(aug, 0, rig=rig, picks=picks,
                                         options=FleshOptions(thickness=p["thickness"], iterations=p["iterations"]))
        aug.save(out / "dataset")

    return cache.run("augment", inputs, make)


def natural_stage_cached(cache: StageCache, dataset_dir: Path, markers: str,
                         opts: IndexOptions) -> tuple[Path, bool]:
    """Natural-neighbour weights and the correction basis; result: ``natural.npz``."""
    inputs = {"mesh": hash_file(dataset_dir / "mesh.npz"), "markers": hash_file(markers),
              "region_radius": opts.region_radius, "nn_subdivisions": opts.nn_subdivisions, "ks": opts.ks,
              "kb": opts.kb}

    def make(out: Path) -> None:
        ds = ShapeDataset.load(dataset_dir, mmap=True)
        save_npz(out / "natural.npz", **natural_stage(ds, read_layout(markers, ds.triangles), opts))

    return cache.run("natural", inputs, make)


def clouds_stage_cached(cache: StageCache, dataset_dir: Path, markers: str, natural_dir: Path, opts: IndexOptions,
                        jaw_rig: str | None = None) -> tuple[Path, bool]:
    """Point clouds, pruning, simplices, grids; result: ``clouds.npz``, ``pruning.csv``, ``bundles.csv``."""
    opt = {k: v for k, v in opts.to_json().items() if k not in ("region_radius", "nn_subdivisions", "ks", "kb")}
    inputs = {"dataset": json.loads((dataset_dir / "manifest.json").read_text())["content_hash"],
              "markers": hash_file(markers), "natural": natural_dir.name, "options": opt,
              "jaw_rig": None if not jaw_rig else hash_file(jaw_rig)}

    def make(out: Path) -> None:
        from .jaw import JawRig

        ds = ShapeDataset.load(dataset_dir, mmap=True)
        rig = JawRig.load(jaw_rig, ds.n_vertices) if jaw_rig else None
        arrays, reports = clouds_stage(ds, read_layout(markers, ds.triangles), opts,
                                       _load_npz(natural_dir / "natural.npz"), rig)
        save_npz(out / "clouds.npz", **arrays)
        for name, df in reports.items():
            df.to_csv(out / name, index=False, float_format="%.6g")

    return cache.run("clouds", inputs, make)


def index_stage(cache: StageCache, dataset_dir: Path, markers: str, natural_dir: Path, clouds_dir: Path,
                opts: IndexOptions, jaw_rig: str | None = None) -> tuple[Path, bool]:
    """Assemble the index; result: ``index/`` (an index directory)."""
    inputs = {"natural": natural_dir.name, "clouds": clouds_dir.name, "options": opts.to_json(),
              "dataset": json.loads((dataset_dir / "manifest.json").read_text())["content_hash"],
              "markers": hash_file(markers), "jaw_rig": None if not jaw_rig else hash_file(jaw_rig)}

    def make(out: Path) -> None:
        from .jaw import JawRig

        ds = ShapeDataset.load(dataset_dir, mmap=True)
        rig = JawRig.load(jaw_rig, ds.n_vertices) if jaw_rig else None
        index = assemble_index(ds, read_layout(markers, ds.triangles), opts, _load_npz(natural_dir / "natural.npz"),
                               _load_npz(clouds_dir / "clouds.npz"), rig)
        reports = {name: pd.read_csv(clouds_dir / name) for name in ("pruning.csv", "bundles.csv")}
        index.save(out / "index", reports)

    return cache.run("index", inputs, make)


def verify_stage(cache: StageCache, index_dir: Path, tolerance: float = 0.01) -> tuple[Path, bool]:
    """The paper's verification; result: ``verification.csv`` and ``summary.json``."""
    inputs = {"index": index_dir.name, "tolerance": tolerance}

    def make(out: Path) -> None:
        from .verify import verify_index

        table = verify_index(LGIIndex.load(index_dir / "index"))
        table.to_csv(out / "verification.csv", index=False, float_format="%.6g")
        summary = {"shapes": len(table), "worst_rms_mm": float(table.rms_mm.max()),
                   "worst_shape": str(table["shape"].iloc[int(table.rms_mm.argmax())]),
                   "worst_max_mm": float(table.max_mm.max()), "tolerance_mm": tolerance,
                   "passed": bool((table.rms_mm <= tolerance).all())}
        (out / "summary.json").write_text(json.dumps(summary, indent=1))

    return cache.run("verify", inputs, make)


def options_from(params: dict[str, Any] | None) -> IndexOptions:
    """IndexOptions from a flat dict (cloud options and index options mixed, unknown keys refused)."""
    from .cloud import CloudOptions

    params = dict(params or {})
    cloud_keys = set(asdict(CloudOptions()))
    cloud = CloudOptions(**{k: params.pop(k) for k in list(params) if k in cloud_keys})
    return IndexOptions(cloud=cloud, **params)


def publish(src: Path, dest: str | os.PathLike[str]) -> Path:
    """Copy a cached result directory to its user-facing place, atomically."""
    import shutil

    from .atomic import atomic_dir

    dest = Path(dest)
    with atomic_dir(dest) as tmp:
        shutil.copytree(src, tmp, dirs_exist_ok=True)
    return dest
