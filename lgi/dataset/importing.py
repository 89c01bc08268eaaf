"""Import folders of OBJ shapes into a :class:`~lgi.dataset.shapes.ShapeDataset`.

Two kinds of folder are read:

* full-mesh shapes (:func:`import_obj_folder`): every OBJ is a complete deformed mesh with the
  neutral's vertex order and polygon list (the ICT FaceKit layout);
* delta shapes (``deltas=True``): every OBJ but the neutral holds per-vertex displacements in its
  ``v`` lines; its polygon list, when present, must match the neutral's.

Files whose names match the identity pattern (``identity*`` by default) are identity modes, not
expressions: they are recorded in the dataset info and can be blended into the neutral with
``identity_weights`` (see :func:`blend_identity`).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lgi.dataset.meshcheck import check_mesh
from lgi.dataset.shapes import ShapeDataset, ShapeMeta, _match
from lgi.dataset.stabilise import find_rigid_vertices, stabilise
from lgi.errors import InputError
from lgi.io.obj import PolyMesh, _lines, _parse_floats, read_obj, read_obj_positions
from lgi.progress import progress
from lgi.units import check_units


def _load_npy_indices(path: Path) -> np.ndarray:
    """A ``.npy`` of vertex indices, never unpickled: an array of Python objects (a list saved as
    ``dtype=object``) is refused with the file's name, instead of numpy's advice to allow pickles."""
    try:
        return np.load(path, allow_pickle=False)
    except ValueError as exc:
        if "allow_pickle" in str(exc):
            raise InputError("the .npy array holds Python objects (dtype object), not integers: save the vertex "
                             "indices as an integer array, e.g. np.save(path, np.asarray(indices, dtype=np.int64))",
                             path=path) from None
        raise InputError(f"not a readable .npy array of vertex indices ({exc})", path=path) from None


def load_vertex_indices(path: str | os.PathLike[str], n_vertices: int | None = None) -> np.ndarray:
    """Read a vertex index set.

    Accepted forms: a JSON list of ints; a JSON object with exactly one key containing ``rigid`` and ``vert``
    whose value is such a list (ICT's ``vertex_indices.json`` has ``idx_to_rigid_verts``); a text file
    with whitespace- or comma-separated ints; a ``.npy`` array.

    Returns
    -------
    (K,) int64, 0-based
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("vertex index file not found", path=path)
    if path.suffix == ".npy":
        idx = _load_npy_indices(path)
    elif path.suffix == ".json":
        try:
            obj = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise InputError(f"invalid JSON: {exc.msg}", path=path, line=exc.lineno) from None
        if isinstance(obj, dict):
            keys = [k for k in obj if "rigid" in k.lower() and "vert" in k.lower() and "lap" not in k.lower()]
            if len(keys) != 1:
                raise InputError(f"expected one key naming the rigid vertices, found {keys or list(obj)}",
                                 path=path)
            obj = obj[keys[0]]
        idx = np.asarray(obj)
    else:
        text = path.read_text().replace(",", " ").split()
        try:
            idx = np.asarray([int(t) for t in text])
        except ValueError as exc:
            raise InputError(f"non-integer vertex index: {exc}", path=path) from None
    if idx.ndim != 1 or idx.size < 3 or not np.issubdtype(idx.dtype, np.integer):
        raise InputError(f"expected at least 3 integer vertex indices, got shape {idx.shape} {idx.dtype}", path=path)
    if n_vertices is not None and (idx.min() < 0 or idx.max() >= n_vertices):
        raise InputError(f"vertex index out of range [0, {n_vertices}): min {idx.min()}, max {idx.max()}", path=path)
    return np.unique(idx.astype(np.int64))


def neutral_mesh(folder: str | os.PathLike[str], neutral: str | None = None) -> PolyMesh:
    """The neutral OBJ of a shapes folder (the one named ``*neutral*``, or ``neutral``), read alone: what a marker
    layout is checked against before a rebuild reads every shape."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("shape folder not found or not a directory", path=folder)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".obj" and p.is_file())
    if not files:
        raise InputError("no OBJ files in folder", path=folder)
    return read_obj(_find_neutral(files, folder, neutral))


def _one_file_per_shape(files: list[Path], folder: Path) -> None:
    """A shape is named by its file's stem, so two files with one stem (``jawOpen.obj`` and ``jawOpen.OBJ``)
    would be two shapes of one name: refused here, naming the files, before any is read."""
    by_stem: dict[str, list[str]] = {}
    for f in files:
        by_stem.setdefault(f.stem, []).append(f.name)
    clashes = {stem: names for stem, names in by_stem.items() if len(names) > 1}
    if clashes:
        which = "; ".join(f"{stem!r} from {' and '.join(names)}" for stem, names in sorted(clashes.items()))
        raise InputError(f"several files give one shape name: {which} (rename or remove all but one)", path=folder)


def _find_neutral(files: list[Path], folder: Path, neutral: str | None) -> Path:
    if neutral is not None:
        for f in files:
            if f.stem == neutral or f.name == neutral:
                return f
        raise InputError(f"neutral {neutral!r} not found among {len(files)} OBJ files", path=folder)
    cands = [f for f in files if "neutral" in f.stem.lower()]
    if len(cands) == 1:
        return cands[0]
    if not cands:
        raise InputError("no neutral found: no OBJ file has 'neutral' in its name (pass --neutral NAME)",
                         path=folder)
    raise InputError(f"several neutral candidates {[c.name for c in cands]}: pass --neutral NAME", path=folder)


@dataclass
class RawShapes:
    """Shapes as read from a folder, before stabilisation.

    Attributes
    ----------
    mesh : PolyMesh
        The neutral's topology (positions replaced by the actor's neutral when identities are blended).
    neutral : (V, 3) float64
    positions : (S, V, 3) float64
        Full positions of each shape, possibly with head motion.
    names : list of str; sources : list of str
    info : dict
        Import details recorded in the dataset.
    """

    mesh: PolyMesh
    neutral: np.ndarray
    positions: np.ndarray
    names: list[str]
    sources: list[str]
    info: dict


def read_shape_folder(
    folder: str | os.PathLike[str],
    *,
    neutral: str | None = None,
    include: str | None = None,
    exclude: str | None = None,
    units: str = "cm",
    deltas: bool = False,
    identity_pattern: str = "identity*",
    identity_weights: dict[str, float] | None = None,
    show_progress: bool = True,
) -> RawShapes:
    """Read a folder of OBJ shapes sharing one topology (parameters as :func:`import_obj_folder`)."""
    folder = Path(folder)
    to_cm = check_units(units)
    if not folder.is_dir():
        raise InputError("shape folder not found or not a directory", path=folder)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".obj" and p.is_file())
    if not files:
        raise InputError("no OBJ files in folder", path=folder)
    neutral_path = _find_neutral(files, folder, neutral)
    # lgi's reader, not pymeshlab's: it keeps quads, UV seams and the vertex order every shape shares (pymeshlab
    # triangulates and splits seam vertices) and names the line of a bad value; pymeshlab checks the result.
    mesh = read_obj(neutral_path)

    mesh_check = check_mesh(mesh, neutral_path)  # before the shapes are read: a mesh the index cannot use is refused
    ident_files = [f for f in files if f != neutral_path and fnmatch.fnmatchcase(f.stem, identity_pattern)]
    shape_files = [
        f for f in files
        if f != neutral_path and f not in ident_files
        and _match(f.stem, include, True) and not _match(f.stem, exclude, False)
    ]
    if not shape_files:
        raise InputError(f"no shapes selected (include={include!r}, exclude={exclude!r})", path=folder)
    _one_file_per_shape(shape_files, folder)

    x0 = mesh.vertices
    identity_used: dict[str, float] = {}
    if identity_weights:
        by_stem = {f.stem: f for f in ident_files}
        modes = {}
        for name, w in identity_weights.items():
            if name not in by_stem:
                raise InputError(f"identity mode {name!r} not found (have {sorted(by_stem)})", path=folder)
            modes[name] = read_obj_positions(by_stem[name], mesh)
            identity_used[name] = float(w)
        x0 = blend_identity(mesh.vertices, modes, identity_used)

    positions = np.empty((len(shape_files), mesh.n_vertices, 3), np.float64)
    for k, f in enumerate(progress(shape_files, desc="reading shapes", disable=not show_progress)):
        if deltas:
            positions[k] = _read_delta_obj(f, mesh) + mesh.vertices
        else:
            positions[k] = read_obj_positions(f, mesh)
    # Expression displacements are measured on the source neutral; with an identity blend they are
    # carried over unchanged (the additive model ICT itself uses), so re-base them on the new neutral.
    positions += (x0 - mesh.vertices)[None]
    if to_cm != 1.0:
        # The library computes in cm (its tolerances and the reports' mm assume it): convert once, here.
        x0 = x0 * to_cm
        positions *= to_cm
        mesh = dataclasses.replace(mesh, vertices=(mesh.vertices * to_cm).astype(mesh.vertices.dtype))
    info = {
        "name": folder.name,
        "imported_from": str(folder),
        "neutral_source": neutral_path.name,
        "delta_files": deltas,
        "identity_modes": [f.stem for f in ident_files],
        "identity_weights": identity_used,
        "mtllib": mesh.mtllib,
        "units": "cm",
        "source_units": units,
        "mesh_check": mesh_check,
    }
    return RawShapes(mesh, x0, positions, [f.stem for f in shape_files], [f.name for f in shape_files], info)


def stabilise_raw(
    raw: RawShapes, rigid_vertices: str | os.PathLike[str] | np.ndarray | None = "auto"
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Remove rigid head motion from read shapes.

    Parameters
    ----------
    raw
        From :func:`read_shape_folder`.
    rigid_vertices
        A vertex index file (see :func:`load_vertex_indices`), an index array, ``"auto"`` to find the
        most rigidly moving vertices, or ``None``/``"none"`` to keep the shapes as they are.

    Returns
    -------
    deltas : (S, V, 3) float32
    transforms : (S, 4, 4) float64
        Removed motion per shape (identity when none).
    info : dict
        Method, vertex count and indices, worst fit RMS.
    """
    n = len(raw.names)
    if isinstance(rigid_vertices, str) and rigid_vertices.lower() == "none":
        rigid_vertices = None
    if rigid_vertices is None:
        eye = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
        return (raw.positions - raw.neutral[None]).astype(np.float32), eye, {"method": "none"}
    if isinstance(rigid_vertices, str) and rigid_vertices == "auto":
        idx = find_rigid_vertices(raw.neutral, raw.positions)
        info: dict = {"method": "auto"}
    elif isinstance(rigid_vertices, np.ndarray):
        idx = np.unique(rigid_vertices.astype(np.int64))
        info = {"method": "given"}
    else:
        idx = load_vertex_indices(rigid_vertices, raw.mesh.n_vertices)
        info = {"method": "file", "file": str(rigid_vertices)}
    d, transforms, rms = stabilise(raw.neutral, raw.positions, idx)
    info.update(count=int(idx.size), fit_rms_max=float(rms.max()), vertices=idx.tolist())
    return d, transforms, info


def assemble_dataset(raw: RawShapes, deltas: np.ndarray, transforms: np.ndarray, stab_info: dict) -> ShapeDataset:
    """The :class:`ShapeDataset` of read and stabilised shapes."""
    meta = [
        ShapeMeta(source=src, rigid_transform=transforms[k], tags=_side_tags(name))
        for k, (name, src) in enumerate(zip(raw.names, raw.sources, strict=True))
    ]
    m = raw.mesh
    return ShapeDataset(
        neutral=raw.neutral, deltas=deltas, names=list(raw.names), face_vertices=m.face_vertices,
        face_offsets=m.face_offsets, uvs=m.uvs, face_uvs=m.face_uvs, units=raw.info["units"], shape_meta=meta,
        face_material=m.face_material, materials=m.materials, info={**raw.info, "stabilisation": stab_info},
    )


def import_obj_folder(
    folder: str | os.PathLike[str],
    *,
    neutral: str | None = None,
    include: str | None = None,
    exclude: str | None = None,
    units: str = "cm",
    rigid_vertices: str | os.PathLike[str] | np.ndarray | None = "auto",
    deltas: bool = False,
    identity_pattern: str = "identity*",
    identity_weights: dict[str, float] | None = None,
    show_progress: bool = True,
) -> ShapeDataset:
    """Import a folder of OBJ shapes sharing one topology.

    Parameters
    ----------
    folder
        Directory of ``*.obj`` files.
    neutral
        File stem of the neutral; by default the one file with ``neutral`` in its name.
    include, exclude
        Shell patterns on file stems (comma-separated for several) selecting the shapes.
    units
        Units of the files (``mm``, ``cm``, ``m``, ``in``); positions are converted to cm (the dataset records
        ``cm`` and, in its info, ``source_units``).
    rigid_vertices
        Stabilisation, see :func:`stabilise_raw`.
    deltas
        The non-neutral files hold displacements instead of full positions.
    identity_pattern
        Stems matching this are identity modes, not shapes.
    identity_weights
        Blend these identity modes into the neutral (an actor): ``{stem: weight}``.
    show_progress
        Draw a progress bar on standard error.

    Returns
    -------
    ShapeDataset
        Shapes in alphabetical order of file stem; vertex order exactly as in the files.
    """
    raw = read_shape_folder(
        folder, neutral=neutral, include=include, exclude=exclude, units=units, deltas=deltas,
        identity_pattern=identity_pattern, identity_weights=identity_weights, show_progress=show_progress,
    )
    return assemble_dataset(raw, *stabilise_raw(raw, rigid_vertices))


def _read_delta_obj(path: Path, mesh: PolyMesh) -> np.ndarray:
    """Displacements from a delta OBJ; its faces, if any, must match the neutral's."""
    raw = path.read_bytes()
    if b"\nf " in raw or raw.startswith(b"f "):
        return read_obj_positions(path, mesh)
    lines = _lines(path)
    v_no = [i for i, ln in enumerate(lines) if ln[:2] == b"v "]
    if len(v_no) != mesh.n_vertices:
        raise InputError(f"vertex count {len(v_no)} differs from the neutral's {mesh.n_vertices}", path=path)
    return _parse_floats(path, lines, v_no, b"v ", 3)


def _side_tags(name: str) -> list[str]:
    low = name.lower()
    if low.endswith(("_l", "left")):
        return ["left"]
    if low.endswith(("_r", "right")):
        return ["right"]
    return []


def blend_identity(neutral: np.ndarray, modes: dict[str, np.ndarray], weights: dict[str, float]) -> np.ndarray:
    """An actor's neutral: ``x0 + sum_i w_i (mode_i - x0)``.

    Parameters
    ----------
    neutral : (V, 3) float
    modes : dict of (V, 3) float
        Full positions of each identity mode (neutral plus the mode at weight 1).
    weights : dict of float
        Weight of each mode used (ICT's modes are PCA directions; weights of a few units are typical).

    Returns
    -------
    (V, 3) float64
    """
    x = np.asarray(neutral, np.float64).copy()
    for name, w in weights.items():
        x += w * (np.asarray(modes[name], np.float64) - neutral)
    return x
