"""The shape dataset: a neutral mesh plus named facial shapes stored as displacements.

On disk a dataset is a directory (format described in ``docs/dataset-format.md``)::

    manifest.json   format version, units, shape names and per-shape metadata, content hash
    mesh.npz        neutral positions and topology (polygons as given, UVs with their seams)
    deltas.npy      (S, V, 3) float32 displacements from the neutral, memory-mappable

The content hash covers everything that defines the data (arrays, names, units, metadata) and
nothing incidental (creation time, the path), so it serves as a cache key.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from lgi.dataset.mesh import triangulate
from lgi.errors import InputError
from lgi.io.atomic import atomic_dir
from lgi.io.npz import save_npz

FORMAT = "lgi-shape-dataset"
FORMAT_VERSION = 1
#: What a dataset directory holds (with the augment job's report): a folder holding anything else is not
#: replaced by a dataset.
ENTRIES = ("manifest.json", "mesh.npz", "deltas.npy", "augmentation.csv")


@dataclass
class ShapeMeta:
    """Metadata of one shape.

    Attributes
    ----------
    source
        Where it came from (a file name, or a description such as ``synthetic:jaw_open=1``).
    rigid_transform : (4, 4) float64
        The rigid head motion removed by stabilisation, mapping the stabilised shape onto the source
        (identity when nothing was removed).
    tags
        Free-form labels, for example ``extreme``, ``inbetween``, ``left``.
    extra
        Anything else worth keeping (activations of a synthetic shape, jaw parameters, ...); must be
        JSON-serialisable.
    """

    source: str = ""
    rigid_transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    tags: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "rigid_transform": np.asarray(self.rigid_transform, np.float64).round(12).tolist(),
            "tags": list(self.tags),
            "extra": self.extra,
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ShapeMeta:
        return cls(
            source=d.get("source", ""),
            rigid_transform=np.asarray(d.get("rigid_transform", np.eye(4)), np.float64),
            tags=list(d.get("tags", [])),
            extra=dict(d.get("extra", {})),
        )


@dataclass
class ShapeDataset:
    """A neutral mesh and named facial shapes.

    Attributes
    ----------
    neutral : (V, 3) float64
        Neutral positions, in ``units``.
    deltas : (S, V, 3) float32
        Displacement of every shape from the neutral, in ``units``.
    names : list of str
        Shape names, unique, in the order of ``deltas``.
    face_vertices, face_offsets
        Polygons as given (see :class:`lgi.io.obj.PolyMesh`).
    uvs : (T, 2) float32 or None
    face_uvs : (N,) int32 or None
        Texture coordinates per polygon corner; a UV seam is where one vertex has several.
    units
        Length unit of positions and deltas (``"cm"`` unless told otherwise).
    shape_meta : list of ShapeMeta
        One per shape.
    face_material : (F,) int16, optional; materials : list of str
        Material groups of the source mesh (kept for export and region selection).
    info
        Dataset-level metadata (name, where it was imported from, the rigid vertices used).
    jaw_pivot : (3,) float64, cm, optional; jaw_weights : (V,) float64 in [0, 1], optional
        The jaw rig (:class:`lgi.solve.jaw.JawRig`) the shapes are unskinned with, when they are (an actor's
        rig from ``lgi rig-generate`` on a jaw-rigged index): the displacements are then in the jaw-closed
        space and a pose skins them with its jaw parameters.
    """

    neutral: np.ndarray
    deltas: np.ndarray
    names: list[str]
    face_vertices: np.ndarray
    face_offsets: np.ndarray
    uvs: np.ndarray | None = None
    face_uvs: np.ndarray | None = None
    units: str = "cm"
    shape_meta: list[ShapeMeta] = field(default_factory=list)
    face_material: np.ndarray | None = None
    materials: list[str] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    jaw_pivot: np.ndarray | None = None
    jaw_weights: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.neutral = np.asarray(self.neutral, np.float64)
        if (self.jaw_pivot is None) != (self.jaw_weights is None):
            raise InputError("a jaw rig needs both its pivot and its weights")
        if self.jaw_pivot is not None:
            self.jaw_pivot = np.asarray(self.jaw_pivot, np.float64).reshape(3)
            self.jaw_weights = np.asarray(self.jaw_weights, np.float64)
            if self.jaw_weights.shape != (len(self.neutral),):
                raise InputError(f"jaw weights {self.jaw_weights.shape} for {len(self.neutral)} vertices")
        if self.deltas.dtype != np.float32:
            self.deltas = np.asarray(self.deltas, np.float32)
        if self.deltas.ndim != 3 or self.deltas.shape[1:] != self.neutral.shape:
            raise InputError(f"deltas shape {self.deltas.shape} does not match neutral {self.neutral.shape}")
        if len(self.names) != self.deltas.shape[0]:
            raise InputError(f"{len(self.names)} names for {self.deltas.shape[0]} shapes")
        if len(set(self.names)) != len(self.names):
            dup = sorted({n for n in self.names if self.names.count(n) > 1})
            raise InputError(f"duplicate shape names: {dup}")
        if not self.shape_meta:
            self.shape_meta = [ShapeMeta() for _ in self.names]
        if len(self.shape_meta) != len(self.names):
            raise InputError("one ShapeMeta per shape is needed")

    # ------------------------------------------------------------------ access
    @property
    def n_shapes(self) -> int:
        return len(self.names)

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    @cached_property
    def triangles(self) -> np.ndarray:
        """(T, 3) int32: the canonical fan triangulation (see :func:`lgi.dataset.mesh.triangulate`)."""
        return triangulate(self.face_vertices, self.face_offsets)[0]

    def index(self, name: str) -> int:
        """Position of shape ``name``; raises ``KeyError`` naming the known shapes if absent."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no shape {name!r} in dataset (has {len(self.names)}: {self.names[:8]}...)") from None

    def shape(self, which: int | str) -> np.ndarray:
        """(V, 3) float64 positions of one shape (neutral plus its displacement)."""
        i = self.index(which) if isinstance(which, str) else which
        return self.neutral + self.deltas[i]

    def select(self, include: str | None = None, exclude: str | None = None) -> ShapeDataset:
        """A dataset with the shapes whose names match ``include`` and not ``exclude``.

        Patterns are shell-style (``mouth*``); several may be given separated by commas.
        """
        keep = [i for i, n in enumerate(self.names) if _match(n, include, True) and not _match(n, exclude, False)]
        return self.take(keep)

    def take(self, indices: list[int] | np.ndarray) -> ShapeDataset:
        """A dataset with the shapes at ``indices``, in that order."""
        idx = [int(i) for i in indices]
        return ShapeDataset(
            neutral=self.neutral, deltas=np.asarray(self.deltas[idx]), names=[self.names[i] for i in idx],
            face_vertices=self.face_vertices, face_offsets=self.face_offsets, uvs=self.uvs,
            face_uvs=self.face_uvs, units=self.units, shape_meta=[self.shape_meta[i] for i in idx],
            face_material=self.face_material, materials=list(self.materials), info=dict(self.info),
            jaw_pivot=self.jaw_pivot, jaw_weights=self.jaw_weights,
        )

    # ------------------------------------------------------------------ hashing
    def content_hash(self) -> str:
        """SHA-256 (hex) of everything that defines the dataset; stable across save and load."""
        h = hashlib.sha256()
        h.update(f"{FORMAT}/{FORMAT_VERSION}".encode())
        for arr in (self.neutral, self.face_vertices, self.face_offsets, self.uvs, self.face_uvs):
            _hash_array(h, arr)
        _hash_array(h, np.asarray(self.deltas))
        if self.jaw_pivot is not None:  # unskinned shapes mean another surface with another rig
            _hash_array(h, self.jaw_pivot)
            _hash_array(h, self.jaw_weights)
        h.update(json.dumps(self._identity_json(), sort_keys=True).encode())
        return h.hexdigest()

    def _identity_json(self) -> dict[str, Any]:
        return {
            "units": self.units,
            "names": self.names,
            "shape_meta": [m.to_json() for m in self.shape_meta],
        }

    # ------------------------------------------------------------------ disk
    def save(self, directory: str | os.PathLike[str]) -> Path:
        """Write the dataset directory atomically (an existing one is replaced whole).

        Returns
        -------
        Path
            ``directory``.
        """
        directory = Path(directory)
        digest = self.content_hash()
        with atomic_dir(directory, ENTRIES, "lgi dataset") as tmp:
            arrays = {
                "neutral": self.neutral,
                "face_vertices": np.asarray(self.face_vertices, np.int32),
                "face_offsets": np.asarray(self.face_offsets, np.int64),
            }
            if self.uvs is not None:
                arrays["uvs"] = np.asarray(self.uvs, np.float32)
                arrays["face_uvs"] = np.asarray(self.face_uvs, np.int32)
            if self.face_material is not None:
                arrays["face_material"] = np.asarray(self.face_material, np.int16)
            if self.jaw_pivot is not None:
                arrays["jaw_pivot"] = self.jaw_pivot
                arrays["jaw_weights"] = self.jaw_weights
            save_npz(tmp / "mesh.npz", **arrays)
            np.save(tmp / "deltas.npy", np.ascontiguousarray(self.deltas, np.float32))
            manifest = {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "content_hash": digest,
                "n_vertices": self.n_vertices,
                "n_faces": int(len(self.face_offsets) - 1),
                "n_shapes": self.n_shapes,
                "units": self.units,
                "materials": self.materials,
                "info": self.info,
                "shapes": [{"name": n, **m.to_json()} for n, m in zip(self.names, self.shape_meta, strict=True)],
            }
            (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1))
        return directory

    @classmethod
    def load(cls, directory: str | os.PathLike[str], mmap: bool = False, verify: bool = False) -> ShapeDataset:
        """Read a dataset directory.

        Parameters
        ----------
        directory
            Written by :meth:`save`.
        mmap
            Memory-map the displacements instead of reading them (large datasets).
        verify
            Recompute the content hash and fail if it differs from the manifest's.
        """
        from lgi.io.manifest import read_manifest

        directory = Path(directory)
        mpath = directory / "manifest.json"
        manifest = read_manifest(directory, FORMAT, FORMAT_VERSION, "shape dataset")
        if manifest.get("units", "cm") != "cm":
            raise InputError(f"dataset in {manifest['units']!r}: datasets are stored in cm (lgi import converts); "
                             f"re-import it with lgi import --units {manifest['units']}", path=mpath)
        from lgi.io.npz import load_npy, load_npz

        missing = [k for k in ("shapes", "n_vertices") if k not in manifest]
        if missing:
            raise InputError(f"manifest lacks {missing} (a damaged dataset: re-import it)", path=mpath)
        arrays = load_npz(directory / "mesh.npz", required=("neutral", "face_vertices", "face_offsets"))
        from lgi.io.arrays import check_kind, check_mesh

        check_kind(arrays, directory / "mesh.npz", ints=("face_material",), floats=("neutral",))
        if arrays["neutral"].shape != (manifest["n_vertices"], 3):
            raise InputError(f"neutral has shape {arrays['neutral'].shape}, the manifest says "
                             f"({manifest['n_vertices']}, 3) (a damaged dataset: re-import it)",
                             path=directory / "mesh.npz")
        check_mesh(arrays, manifest["n_vertices"], directory / "mesh.npz")
        jaw = _jaw_arrays(arrays, manifest["n_vertices"], directory / "mesh.npz")
        deltas = load_npy(directory / "deltas.npy", mmap)
        if not np.all(np.isfinite(arrays["neutral"])) or not np.all(np.isfinite(deltas)):
            raise InputError("non-finite positions or displacements (a damaged dataset: re-import it)",
                             path=directory)
        shapes = manifest["shapes"]
        if deltas.shape != (len(shapes), manifest["n_vertices"], 3):
            raise InputError(f"deltas.npy has shape {deltas.shape}, manifest says "
                             f"({len(shapes)}, {manifest['n_vertices']}, 3)", path=directory / "deltas.npy")
        ds = cls(
            neutral=arrays["neutral"], deltas=deltas, names=[s["name"] for s in shapes],
            face_vertices=arrays["face_vertices"], face_offsets=arrays["face_offsets"],
            uvs=arrays.get("uvs"), face_uvs=arrays.get("face_uvs"), units=manifest.get("units", "cm"),
            shape_meta=[ShapeMeta.from_json(s) for s in shapes], face_material=arrays.get("face_material"),
            materials=list(manifest.get("materials", [])), info=dict(manifest.get("info", {})),
            jaw_pivot=jaw[0], jaw_weights=jaw[1],
        )
        if verify and ds.content_hash() != manifest.get("content_hash"):
            raise InputError("content hash does not match the manifest (files changed or corrupt)", path=directory)
        return ds


def read_content_hash(directory: str | os.PathLike[str]) -> str:
    """The content hash recorded in a dataset directory's manifest, without loading the arrays."""
    path = Path(directory) / "manifest.json"
    try:
        return json.loads(path.read_text())["content_hash"]
    except (OSError, KeyError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read the dataset's content hash: {exc}", path=path) from None


def _jaw_arrays(arrays: Any, n_vertices: int, path: Path) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The optional jaw rig of ``mesh.npz``: ``jaw_pivot`` (3,) and ``jaw_weights`` (V,) in [0, 1], both or
    neither, finite."""
    have = [k for k in ("jaw_pivot", "jaw_weights") if k in arrays]
    if not have:
        return None, None
    if len(have) == 1:
        raise InputError(f"holds {have[0]} without its pair (a jaw rig is jaw_pivot and jaw_weights)", path=path)
    pivot = np.asarray(arrays["jaw_pivot"], np.float64)
    w = np.asarray(arrays["jaw_weights"], np.float64)
    if pivot.size != 3 or w.shape != (n_vertices,):
        raise InputError(f"jaw_pivot {pivot.shape} and jaw_weights {w.shape}: expected (3,) and ({n_vertices},)",
                         path=path)
    if not (np.all(np.isfinite(pivot)) and np.all((w >= 0) & (w <= 1))):
        raise InputError("jaw_pivot is not finite or jaw_weights are outside [0, 1]", path=path)
    return pivot.reshape(3), w


def _hash_array(h: Any, arr: np.ndarray | None) -> None:
    if arr is None:
        h.update(b"none")
        return
    a = np.ascontiguousarray(arr)
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(memoryview(a).cast("B"))


def _match(name: str, patterns: str | None, default: bool) -> bool:
    if not patterns:
        return default
    return any(fnmatch.fnmatchcase(name, p.strip()) for p in patterns.split(",") if p.strip())
