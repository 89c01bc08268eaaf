"""Marker layouts: named points on the neutral surface, as (triangle, barycentric coordinates).

A layout is stored as CSV with one row per marker::

    name,triangle,v0,v1,v2,w0,w1,w2[,x,y,z]

``triangle`` indexes the canonical fan triangulation of the dataset's polygons (see
:func:`lgi.dataset.mesh.triangulate`); ``v0..v2`` repeat that triangle's vertices so that a layout applied to
the wrong mesh is caught; ``w0..w2`` are the barycentric weights. ``x, y, z`` (optional) are the
marker's position on the neutral, informative only.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from lgi.dataset.mesh import ClosestPointQuery
from lgi.errors import InputError, cell_text
from lgi.io.atomic import atomic_file

COLUMNS = ["name", "triangle", "v0", "v1", "v2", "w0", "w1", "w2"]


@dataclass
class MarkerLayout:
    """Named markers on a triangle mesh.

    Attributes
    ----------
    names : list of str
        Unique marker names.
    triangles : (M,) int64
        Triangle of each marker in the canonical triangulation.
    vertices : (M, 3) int64
        That triangle's vertex indices.
    weights : (M, 3) float64
        Barycentric weights (non-negative, sum 1).
    """

    names: list[str]
    triangles: np.ndarray
    vertices: np.ndarray
    weights: np.ndarray

    def __post_init__(self) -> None:
        if len(set(self.names)) != len(self.names):
            dup = sorted({n for n in self.names if self.names.count(n) > 1})
            raise InputError(f"duplicate marker names: {dup}")
        self.triangles = np.asarray(self.triangles, np.int64)
        self.vertices = np.asarray(self.vertices, np.int64).reshape(-1, 3)
        self.weights = np.asarray(self.weights, np.float64).reshape(-1, 3)

    def __len__(self) -> int:
        return len(self.names)

    def evaluate(self, positions: np.ndarray) -> np.ndarray:
        """Marker positions on one or many shapes.

        Parameters
        ----------
        positions : (V, 3) or (S, V, 3) float
            Vertex positions (neutral plus displacement), or displacements: the map is linear.

        Returns
        -------
        (M, 3) or (S, M, 3) float64
        """
        p = np.asarray(positions)
        corners = p[..., self.vertices, :]  # (..., M, 3, 3)
        return np.einsum("...mkd,mk->...md", corners, self.weights)

    def check_mesh(self, triangles: np.ndarray, path: str | os.PathLike[str] | None = None) -> None:
        """Raise InputError if the layout does not belong to a mesh with these triangles."""
        t = np.asarray(triangles)
        for i, name in enumerate(self.names):
            ti = int(self.triangles[i])
            if not 0 <= ti < len(t):
                raise InputError(f"triangle {ti} out of range (mesh has {len(t)})", path=path, marker=name)
            if not np.array_equal(np.sort(t[ti]), np.sort(self.vertices[i])):
                raise InputError(
                    f"triangle {ti} has vertices {t[ti].tolist()}, layout says {self.vertices[i].tolist()}: "
                    "the layout was made for another mesh",
                    path=path, marker=name,
                )

    def index(self) -> dict[str, int]:
        """Marker name -> row."""
        return {n: i for i, n in enumerate(self.names)}

    def subset(self, names: list[str]) -> MarkerLayout:
        idx = [self.index()[n] for n in names]
        return MarkerLayout([self.names[i] for i in idx], self.triangles[idx], self.vertices[idx], self.weights[idx])


def layout_from_points(
    names: list[str], points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray
) -> tuple[MarkerLayout, np.ndarray]:
    """Attach 3D points to the closest point of a surface.

    Parameters
    ----------
    names : list of str, length M
    points : (M, 3) float
        Marker positions near the neutral surface, in mesh units.
    vertices : (V, 3) float; triangles : (T, 3) int
        The neutral mesh (canonical triangulation).

    Returns
    -------
    layout : MarkerLayout
    distance : (M,) float64
        How far each point was from the surface, in mesh units.
    """
    tri, bary, dist = ClosestPointQuery(vertices, triangles).query(points)
    return MarkerLayout(list(names), tri, np.asarray(triangles)[tri], bary), dist


def read_layout(path: str | os.PathLike[str], triangles: np.ndarray | None = None) -> MarkerLayout:
    """Read a layout CSV (see the module docstring); check it against ``triangles`` if given."""
    path = Path(path)
    if not path.is_file():
        raise InputError("marker layout file not found", path=path)
    try:
        df = pd.read_csv(path, dtype={"name": str}, encoding="utf-8-sig")
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot parse marker CSV: {exc}", path=path) from None
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        raise InputError(f"missing columns {missing} (need {COLUMNS})", path=path)
    if df.empty:
        raise InputError("marker layout has no rows", path=path)
    for col in COLUMNS[1:]:
        num = pd.to_numeric(df[col], errors="coerce")
        bad = num.isna() | ~np.isfinite(num.to_numpy(dtype=float, na_value=np.nan))
        if bad.any():
            r = int(np.flatnonzero(bad.to_numpy())[0])
            raise InputError(f"column {col!r} has a non-numeric or missing value {cell_text(df[col].iloc[r])}",
                             path=path, line=r + 2, marker=str(df["name"].iloc[r]))
        if col in ("triangle", "v0", "v1", "v2"):
            frac = (num != np.round(num)) | (num < 0)
            if frac.any():
                r = int(np.flatnonzero(frac.to_numpy())[0])
                bad = cell_text(df[col].iloc[r])
                raise InputError(f"column {col!r} must hold a non-negative whole number, not {bad}",
                                 path=path, line=r + 2, marker=str(df["name"].iloc[r]))
        df[col] = num
    names = df["name"]
    if names.isna().any() or (names.astype(str).str.strip() == "").any():
        r = int(np.flatnonzero((names.isna() | (names.astype(str).str.strip() == "")).to_numpy())[0])
        raise InputError("marker without a name", path=path, line=r + 2)
    dup = df["name"][df["name"].duplicated()]
    if len(dup):
        r = int(dup.index[0])
        raise InputError("duplicate marker name", path=path, line=r + 2, marker=str(df["name"].iloc[r]))
    w = df[["w0", "w1", "w2"]].to_numpy(float)
    bad = np.flatnonzero((w < -1e-6).any(1) | (np.abs(w.sum(1) - 1) > 1e-4))
    if bad.size:
        r = int(bad[0])
        raise InputError(f"barycentric weights {w[r].tolist()} are not convex (>= 0, summing to 1)",
                         path=path, line=r + 2, marker=str(df["name"].iloc[r]))
    layout = MarkerLayout(
        names=df["name"].astype(str).tolist(),
        triangles=df["triangle"].to_numpy(np.int64),
        vertices=df[["v0", "v1", "v2"]].to_numpy(np.int64),
        weights=w / w.sum(1, keepdims=True),
    )
    if triangles is not None:
        layout.check_mesh(triangles, path)
    return layout


def write_layout(path: str | os.PathLike[str], layout: MarkerLayout, neutral: np.ndarray | None = None) -> None:
    """Write a layout CSV atomically; with ``neutral`` (V, 3) the positions are added as x, y, z."""
    df = pd.DataFrame({
        "name": layout.names,
        "triangle": layout.triangles,
        "v0": layout.vertices[:, 0], "v1": layout.vertices[:, 1], "v2": layout.vertices[:, 2],
        "w0": layout.weights[:, 0], "w1": layout.weights[:, 1], "w2": layout.weights[:, 2],
    })
    if neutral is not None:
        xyz = layout.evaluate(neutral)
        df["x"], df["y"], df["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    with atomic_file(path) as tmp:
        df.to_csv(tmp, index=False, float_format="%.9g")
