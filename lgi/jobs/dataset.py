"""The dataset jobs: import a folder of OBJ shapes, and augment a dataset with in-between shapes.

``lgi import`` / ``lgi augment`` and the rebuild-dataset flow's read, stabilise and augment stages call
these functions with the same options objects, so the flow's dataset is the command's, byte for byte.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lgi.errors import InputError
from lgi.jobs import options_from_dict
from lgi.options import declared, option


# --------------------------------------------------------------------------------------------- import
@declared
@dataclass(frozen=True)
class ImportOptions:
    """Options of ``lgi import`` and the rebuild-dataset flow (:mod:`lgi.options`)."""

    neutral: str | None = option(None, "file stem of the neutral (default: the file named *neutral*)",
                                 group="inputs", metavar="NAME")
    include: str | None = option(None, "shell patterns of shapes to import, comma-separated (default: all)",
                                 group="inputs", metavar="PATTERN")
    exclude: str | None = option(None, "shell patterns of shapes to leave out, comma-separated (default: none)",
                                 group="inputs", metavar="PATTERN")
    rigid_vertices: str | None = option(
        "auto", "vertex indices that move with the skull (JSON, text or .npy file), 'auto' to find them, 'none' to "
        "skip stabilisation (default %(default)s)", group="method", metavar="FILE|auto|none")
    units: str = option("cm", "length unit of the files' coordinates (default %(default)s)", group="inputs",
                        choices=("mm", "cm", "m", "in"))
    deltas: bool = option(False, "shape files hold displacements, not full meshes", group="inputs")
    identity: str | None = option(None, "blend identity modes (identity*.obj) into the neutral with these weights",
                                  group="inputs", metavar="NAME=W,...")

    def __post_init__(self) -> None:
        from lgi.units import check_units

        check_units(self.units, "--units")
        self.identity_weights()

    def identity_weights(self) -> dict[str, float] | None:
        """``{stem: weight}`` of ``identity``, or None."""
        if not self.identity:
            return None
        out = {}
        for part in self.identity.split(","):
            name, sep, w = part.partition("=")
            try:
                out[name.strip()] = float(w) if sep else 1.0
            except ValueError:
                raise InputError(f"--identity: weight {w!r} of {name!r} is not a number") from None
            if not math.isfinite(out[name.strip()]):
                raise InputError(f"--identity: weight of {name!r} must be finite")
        return out

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any] | None) -> ImportOptions:
        return options_from_dict(cls, d, "import")


def read_shapes(shapes_dir: str | Path, options: ImportOptions, show_progress: bool = False):
    """The import's first stage: the OBJ files read and converted to cm
    (a :class:`~lgi.dataset.importing.RawShapes`)."""
    from lgi.dataset.importing import read_shape_folder

    o = options
    return read_shape_folder(shapes_dir, neutral=o.neutral, include=o.include, exclude=o.exclude, units=o.units,
                             deltas=o.deltas, identity_weights=o.identity_weights(), show_progress=show_progress)


def stabilise_shapes(raw, options: ImportOptions):
    """The import's second stage: head motion removed; the dataset."""
    from lgi.dataset.importing import assemble_dataset, stabilise_raw

    rigid = None if options.rigid_vertices in (None, "none") else options.rigid_vertices
    return assemble_dataset(raw, *stabilise_raw(raw, rigid))


#: What ``lgi import`` reads in the shapes folder (no output may land on one of them).
SOURCES = ("*.obj", "*.OBJ", "*.mtl", "*.json")


def import_dataset(shapes_dir: str | Path, out: str | Path, options: ImportOptions | None = None,
                   show_progress: bool = False) -> dict[str, Any]:
    """``lgi import``: read, stabilise and save a dataset directory; returns a summary (:func:`import_report`)."""
    from lgi.dataset.shapes import ENTRIES
    from lgi.io.atomic import check_output, files_in

    options = options or ImportOptions()
    check_output(out, "dir", inputs=[shapes_dir, options.neutral, options.identity, *files_in(shapes_dir, SOURCES)],
                 owned=ENTRIES, what="lgi dataset")
    t0 = time.perf_counter()
    ds = stabilise_shapes(read_shapes(shapes_dir, options, show_progress), options)
    ds.save(out)
    return dataset_summary(ds, out, time.perf_counter() - t0)


#: The folders the rebuild publishes in its OUT, and their kinds (:func:`published`).
REBUILD_OUTPUTS = {"dataset": "dataset", "rig": "rig", "dataset_augmented": "dataset", "index": "index",
                   "verification": "verification"}


def published(kind: str) -> tuple[tuple[str, ...], str]:
    """What a published result of ``kind`` ("dataset", "index", "verification", "rig") holds, and its name: a folder
    holding anything else is not replaced (:func:`lgi.io.atomic.check_output`)."""
    from lgi.dataset.shapes import ENTRIES as DATASET
    from lgi.index.build import ENTRIES as INDEX

    return {"dataset": (DATASET, "lgi dataset"), "index": (INDEX, "lgi index"),
            "verification": (("verification.csv", "summary.json", "*.png", ".complete"), "lgi verification"),
            "rig": (("jaw_rig.npz", "rig.json", ".complete"), "lgi jaw rig")}[kind]


def check_rebuild(shapes_dir: str | Path, out: str | Path, options: ImportOptions, markers: str | Path | None = None,
                  jaw_rig: str | Path | None = None, cache_dir: str | Path | None = None) -> None:
    """The rebuild's checks before any work (the rebuild-dataset flow and ``lgi import --flow``): ``out`` and the
    folders it publishes there (``dataset``, ``dataset_augmented``, ``index``, ``verification``) can be written
    and replace none of the inputs, the marker file parses, and the stage cache (``cache_dir``, and
    ``out/.cache``, which holds the publishing locks) can be written."""
    from lgi.io.atomic import check_output, files_in

    inputs = [shapes_dir, options.neutral, options.identity, markers, jaw_rig, cache_dir]
    check_output(out, "dir")
    for name, kind in REBUILD_OUTPUTS.items():
        owned, what = published(kind)
        check_output(Path(out) / name, "dir", inputs=[*inputs, *files_in(shapes_dir, SOURCES)], owned=owned,
                     what=what)
    if markers:
        from lgi.dataset.importing import neutral_mesh
        from lgi.dataset.markers import read_layout
        from lgi.dataset.mesh import triangulate

        mesh = neutral_mesh(shapes_dir, options.neutral)
        read_layout(markers, triangulate(mesh.face_vertices, mesh.face_offsets)[0])
    # Last, so a refusal for anything above leaves no trace. The stage cache holds every stage's result and the
    # publishing locks (always in OUT/.cache): a cache that cannot be written is refused before any work, rather
    # than failing after hours of computing or silently recomputing every night.
    from lgi.io.atomic import check_writable

    for folder in dict.fromkeys(p for p in (cache_dir, Path(out) / ".cache") if p):
        check_writable(folder, "the stage cache", "give cache_dir (lgi import --flow: --cache-dir) on a writable "
                       "disk, or make this folder writable")


def dataset_summary(ds, out: str | Path, seconds: float | None = None) -> dict[str, Any]:
    """Counts, units, the stabilisation's figures and the content hash of a saved dataset."""
    st = ds.info.get("stabilisation", {"method": "none"})
    s: dict[str, Any] = {"path": str(Path(out).resolve()), "n_shapes": ds.n_shapes, "n_vertices": ds.n_vertices,
                         "n_faces": len(ds.face_offsets) - 1, "units": ds.units,
                         "source_units": ds.info.get("source_units", ds.units), "content_hash": ds.content_hash(),
                         "stabilisation": st, "seconds": seconds, "mesh_check": ds.info.get("mesh_check")}
    if st.get("method", "none") != "none":
        s["removed_max_deg"] = max(
            float(np.degrees(np.arccos(np.clip((np.trace(m.rigid_transform[:3, :3]) - 1) / 2, -1, 1))))
            for m in ds.shape_meta)
        s["removed_max_shift"] = max(float(np.linalg.norm(m.rigid_transform[:3, 3])) for m in ds.shape_meta)
    return s


def import_report(s: dict[str, Any]) -> list[str]:
    lines = [f"imported {s['n_shapes']} shapes, {s['n_vertices']} vertices, {s['n_faces']} faces "
             f"({s['units']}{'' if s['source_units'] == s['units'] else ', converted from ' + s['source_units']}) "
             f"in {s['seconds']:.1f} s"]
    st = s["stabilisation"]
    if st.get("method", "none") != "none":
        lines.append(f"stabilised on {st['count']} rigid vertices ({st['method']}): removed up to "
                     f"{s['removed_max_deg']:.3g} deg and {s['removed_max_shift']:.3g} {s['units']}; "
                     f"worst fit RMS {st['fit_rms_max']:.2g} {s['units']}")
    if s.get("mesh_check"):
        from lgi.dataset.meshcheck import check_report

        lines.append(check_report(s["mesh_check"]))
    lines.append(f"dataset: {s['path']}  (content hash {s['content_hash'][:16]})")
    return lines


# -------------------------------------------------------------------------------------------- augment
def _numbers(kind: type) -> Callable[[str], tuple]:
    """An argparse type: comma-separated numbers of ``kind`` as a tuple."""
    def parse(text: str) -> tuple:
        try:
            return tuple(kind(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"comma-separated numbers expected, not {text!r}") from None
    parse.__name__ = f"{kind.__name__} list"
    return parse


@declared
@dataclass(frozen=True)
class AugmentOptions:
    """Options of ``lgi augment`` (:mod:`lgi.options`); ``levels`` and ``orders`` as tuples (lists accepted).
    As a flow parameter (a JSON object), unknown keys are refused."""

    __pydantic_config__ = {"extra": "forbid"}  # flow parameters: a misspelt key is an error, not ignored

    linear: bool = option(False, "linear combinations of dataset shapes", group="method")
    simulate: bool = option(
        False, "physically simulated in-betweens (volumetric flesh, volume kept, lips kept apart)", group="method")
    budget: int = option(200, "combinations to add at most, per method (default %(default)s)", group="combinations",
                         metavar="N")
    levels: tuple[float, ...] = option((0.25, 0.5, 0.75, 1.0), "weights a source may take (default %(default)s)",
                                       group="combinations", metavar="W,...", parse=_numbers(float))
    orders: tuple[int, ...] = option((2, 3), "sources per combination (default %(default)s)", group="combinations",
                                     metavar="K,...", parse=_numbers(int))
    seed: int = option(0, "seed of the choice within the budget (default %(default)s)", group="combinations",
                       metavar="S")
    include: str | None = option(None, "only these source shapes (default: all)", group="combinations",
                                 metavar="PATTERN")
    requires: str | None = option(None, "shapes that appear only with a partner (default mouthClose=jawOpen)",
                                  group="combinations", metavar="SHAPE=PARTNER,...")
    thickness: float = option(0.8, "with --simulate: flesh thickness in dataset units, cm (default %(default)s)",
                              group="method", metavar="D", units="cm")
    iterations: int = option(60, "with --simulate: solver iterations (default %(default)s)", group="method",
                             metavar="N")

    def __post_init__(self) -> None:
        try:
            levels = tuple(float(v) for v in self.levels)
            orders = tuple(int(v) for v in self.orders)
        except (TypeError, ValueError):
            raise InputError(f"--levels/--orders: numbers expected ({self.levels!r}, {self.orders!r})") from None
        if not levels or not all(math.isfinite(v) and 0 < v <= 1 for v in levels):
            raise InputError(f"--levels must be weights in (0, 1], not {list(self.levels)}")
        if not orders or not all(k in (2, 3) for k in orders):
            raise InputError(f"--orders takes 2 and/or 3 sources per combination, not {list(self.orders)}")
        object.__setattr__(self, "levels", levels)
        object.__setattr__(self, "orders", orders)
        if not (self.linear or self.simulate):
            raise InputError("choose an augmentation: --linear and/or --simulate")
        for name, least, most in (("budget", 1, 100_000), ("iterations", 1, 10_000), ("seed", 0, 2**32 - 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not least <= v <= most:
                raise InputError(f"--{name} must be a whole number in [{least}, {most}], not {v!r}")
        if not isinstance(self.thickness, (int, float)) or not math.isfinite(self.thickness) or self.thickness <= 0:
            raise InputError(f"--thickness must be a positive length, not {self.thickness!r}")
        self.requires_map()

    def requires_map(self) -> dict[str, str] | None:
        if not self.requires:
            return None
        pairs = [p for p in self.requires.split(",") if p.strip()]
        if not all("=" in p for p in pairs):
            raise InputError(f"--requires takes SHAPE=PARTNER,..., not {self.requires!r}")
        return dict(p.split("=", 1) for p in pairs)

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["levels"], d["orders"] = list(self.levels), list(self.orders)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any] | None) -> AugmentOptions:
        return options_from_dict(cls, d, "augmentation")


def augment(ds, options: AugmentOptions, rig=None, show_progress: bool = False):
    """``ds`` plus the in-betweens ``options`` ask for (the captured shapes first, then linear, then simulated
    ones); ``rig`` (:class:`~lgi.solve.jaw.JawRig`) carries the flesh's jaw side in the simulation."""
    from lgi.augment.combinations import linear_combinations, pick_combinations, simulated_combinations

    o = options
    src = ds.select(include=o.include) if o.include else ds
    if src.n_shapes == 0:
        raise InputError(f"--include {o.include!r} matches no shape")
    requires = o.requires_map()
    unknown = sorted({n for pair in (requires or {}).items() for n in pair} - set(src.names))
    if unknown:
        raise InputError(f"--requires names shapes the dataset does not have: {unknown}")
    picks = pick_combinations(src.names, o.budget, o.levels, o.orders, o.seed, requires)
    aug = ds
    if o.linear:
        aug = linear_combinations(aug, 0, o.levels, o.orders, o.seed, picks=picks)
    if o.simulate:
        from lgi.augment.flesh import FleshOptions

        try:
            aug = simulated_combinations(aug, 0, o.levels, o.orders, o.seed, rig=rig, picks=picks,
                                         options=FleshOptions(thickness=o.thickness, iterations=o.iterations),
                                         show_progress=show_progress)
        except ValueError as e:  # e.g. a dataset in which nothing moves
            raise InputError(f"cannot simulate in-betweens: {e}") from e
    return aug


AUGMENT_REPORT = "augmentation.csv"


def augment_dataset(dataset_dir: str | Path, out: str | Path, options: AugmentOptions,
                    jaw_rig: str | Path | None = None, markers: str | Path | None = None,
                    show_progress: bool = False) -> dict[str, Any]:
    """``lgi augment``: the augmented dataset saved to ``out`` (with ``markers``, also the per-bundle
    report ``augmentation.csv`` in it); returns a summary (:func:`augment_report`)."""
    from lgi.dataset.shapes import ENTRIES, ShapeDataset
    from lgi.io.atomic import check_output, files_in

    check_output(out, "dir", inputs=[dataset_dir, jaw_rig, markers, *files_in(dataset_dir, ENTRIES)],
                 owned=ENTRIES, what="lgi dataset")
    ds = ShapeDataset.load(dataset_dir)
    rig = None
    if jaw_rig:
        from lgi.solve.jaw import JawRig

        rig = JawRig.load(jaw_rig, ds.n_vertices)
    t0 = time.perf_counter()
    aug = augment(ds, options, rig, show_progress)
    seconds = time.perf_counter() - t0
    rep = None
    if markers:
        from lgi.augment.combinations import augmentation_report
        from lgi.dataset.markers import read_layout

        rep = augmentation_report(ds, aug, read_layout(markers, ds.triangles))
    aug.save(out)
    if rep is not None:
        from lgi.io.atomic import atomic_file

        with atomic_file(Path(out) / AUGMENT_REPORT) as tmp:
            rep.to_csv(tmp, index=False)
    dv = [abs(m.extra["volume_change"]) for m in aug.shape_meta if m.extra.get("method") == "simulated"]
    info = aug.info.get("augmented", {})
    s: dict[str, Any] = {"path": str(Path(out).resolve()), "n_shapes": aug.n_shapes,
                         "added": aug.n_shapes - ds.n_shapes,
                         "combinations": int(max(info.get("linear_combinations", 0),
                                                 info.get("simulated_combinations", 0))),
                         "budget": options.budget, "seconds": seconds, "simulated": bool(dv), "jaw_rig": bool(rig)}
    if dv:
        s["volume_change_median_pct"] = 100 * float(np.median(dv))
        s["volume_change_max_pct"] = 100 * float(np.max(dv))
    if rep is not None:
        s["report"] = {"points_original_median": float(rep.points_original.median()),
                       "points_augmented_median": float(rep.points_augmented.median()),
                       "kept": int(rep.kept.sum()), "bundles": len(rep)}
    return s


def augment_report(s: dict[str, Any]) -> list[str]:
    lines = []
    if s["simulated"]:
        lines.append(f"{s['combinations']} simulated in-betweens in {s['seconds']:.1f} s; flesh volume change median "
                     f"{s['volume_change_median_pct']:.2f} %, max {s['volume_change_max_pct']:.2f} %"
                     + ("" if s["jaw_rig"] else " (no --jaw-rig: the jaw side is held at rest and the lips are not "
                        "kept apart)"))
    lines.append(f"{s['added']} in-betweens added ({s['combinations']} combinations, budget {s['budget']}) -> "
                 f"{s['n_shapes']} shapes in {s['path']}")
    if "report" in s:
        r = s["report"]
        lines.append(f"per bundle, points after pruning: {r['points_original_median']:.0f} -> "
                     f"{r['points_augmented_median']:.0f} (median); the in-betweens added {r['kept']} points over "
                     f"{r['bundles']} bundles ({AUGMENT_REPORT})")
    return lines


# -------------------------------------------------------------------------------------------- bundles
def dataset_bundles(dataset_dir: str | Path, markers: str | Path, out: str | Path,
                    shapes: str | None = None) -> dict[str, Any]:
    """``lgi bundles``: the markers evaluated on every (selected) dataset shape, one frame per shape, and
    ``OUT.shapes.csv`` mapping frames to shape names."""
    import pandas as pd

    from lgi.capture.bundles import Bundles, write_bundles
    from lgi.dataset.markers import read_layout
    from lgi.dataset.shapes import ENTRIES as DATASET_ENTRIES
    from lgi.dataset.shapes import ShapeDataset
    from lgi.io.atomic import atomic_file, check_output, files_in

    out = Path(out)
    for path in (out, out.with_name(out.stem + ".shapes.csv")):
        check_output(path, "file", inputs=[dataset_dir, markers, *files_in(dataset_dir, DATASET_ENTRIES)])
    ds = ShapeDataset.load(dataset_dir)
    if shapes:
        ds = ds.select(include=shapes)
        if ds.n_shapes == 0:
            raise InputError(f"no shape matches {shapes!r}", path=dataset_dir)
    layout = read_layout(markers, ds.triangles)
    pos = layout.evaluate(ds.neutral[None] + np.asarray(ds.deltas, np.float64))
    out = Path(out)
    side = out.with_name(out.stem + ".shapes.csv")
    write_bundles(out, Bundles(frames=np.arange(ds.n_shapes), markers=layout.names, positions=pos))
    with atomic_file(side) as tmp:
        pd.DataFrame({"frame": np.arange(ds.n_shapes), "shape": ds.names}).to_csv(tmp, index=False)
    return {"frames": ds.n_shapes, "markers": len(layout), "bundles": str(out), "shapes": str(side)}
