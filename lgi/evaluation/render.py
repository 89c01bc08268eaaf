"""Pictures a person would rather look at than read: per-vertex values painted on the face."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lgi.io.atomic import atomic_file


def heatmap_row(
    path: str | os.PathLike[str],
    vertices: np.ndarray,
    triangles: np.ndarray,
    values: dict[str, np.ndarray],
    vmax: float | None = None,
    mask: np.ndarray | None = None,
    label: str = "error (mm)",
    title: str | None = None,
) -> Path:
    """One row of front views (x right, y up), one per entry of ``values``, on one colour scale.

    Parameters
    ----------
    path
        PNG written atomically.
    vertices : (V, 3) float
        The surface drawn (e.g. the neutral).
    triangles : (T, 3) int
    values : dict name -> (V,) float
        Per-vertex values, one panel each.
    vmax
        Top of the colour scale (default: the 99th percentile over all panels).
    mask : (V,) bool, optional
        Draw only triangles whose vertices are all in the mask (e.g. the face area).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    tris = np.asarray(triangles)
    if mask is not None:
        tris = tris[np.all(mask[tris], axis=1)]
    # Back-facing triangles (normal pointing away from the viewer) would paint over the front.
    v = np.asarray(vertices, np.float64)
    n = np.cross(v[tris[:, 1]] - v[tris[:, 0]], v[tris[:, 2]] - v[tris[:, 0]])
    tris = tris[n[:, 2] > 0]
    tri = Triangulation(v[:, 0], v[:, 1], tris)
    if vmax is None:
        vmax = float(np.percentile(np.concatenate([np.asarray(x)[np.unique(tris)] for x in values.values()]), 99))
    fig, axes = plt.subplots(1, len(values), figsize=(3.2 * len(values), 4.2), squeeze=False)
    for ax, (name, val) in zip(axes[0], values.items(), strict=True):
        im = ax.tripcolor(tri, np.asarray(val, np.float64), shading="gouraud", cmap="inferno", vmin=0, vmax=vmax)
        ax.set_title(name, fontsize=11)
        ax.set_aspect("equal")
        ax.axis("off")
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label=label)
    if title:
        fig.suptitle(title, fontsize=11)
    path = Path(path)
    with atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)
    return path
