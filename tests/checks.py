"""Checks computed from the outputs alone, not from what the solver says about them.

"The surface passes through every bundle" is measured here from the mesh and the marker layout: each marker's
point is the barycentric combination of its triangle's three vertices, which the layout file spells out
(``v0..v2``, ``w0..w2``), so a solver that wrote the mesh before its correction through the bundles, or reported
a residual it did not reach, is caught.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

#: The largest distance (mm) between a marker's point on a float32 mesh and its bundle that still counts as
#: "through the bundle": float32 holds coordinates of up to 16 cm to 1e-6 cm (its 2^-24 relative spacing), so
#: three rounded vertices blended put the point within about 2e-5 mm of the exact one; 1e-4 mm leaves 5x for the
#: solver's own float64 rounding. A surface not corrected through the bundles misses them by 1e-3 to 1 mm.
THROUGH_MM = 1e-4


def marker_points(vertices: np.ndarray, tri_vertices: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(..., M, 3): each marker's point on meshes ``vertices`` (..., V, 3), from its triangle's vertex indices
    (M, 3) and barycentric weights (M, 3)."""
    v = np.asarray(vertices, np.float64)
    return np.einsum("...mkc,mk->...mc", v[..., np.asarray(tri_vertices), :], np.asarray(weights, np.float64))


def layout_points(vertices: np.ndarray, layout) -> np.ndarray:
    """:func:`marker_points` for a :class:`lgi.dataset.markers.MarkerLayout` (its stored triangles and weights;
    not its own ``evaluate``)."""
    return marker_points(vertices, layout.vertices, layout.weights)


def read_markers(markers_csv: str | Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Names, triangle vertex indices (M, 3) and barycentric weights (M, 3) of a layout CSV, read with pandas."""
    m = pd.read_csv(markers_csv)
    return list(m["name"]), m[["v0", "v1", "v2"]].to_numpy(np.int64), m[["w0", "w1", "w2"]].to_numpy(np.float64)


def bundle_gaps_mm(meshes_npz: str | Path, markers_csv: str | Path, bundles: str | Path | pd.DataFrame) -> np.ndarray:
    """Distance (mm) from each bundle of a bundles table (cm) to its marker's point on the mesh of its frame in
    ``meshes.npz``: one value per bundle row with coordinates (rows without, hidden markers, are left out)."""
    z = np.load(meshes_npz)
    names, tri, w = read_markers(markers_csv)
    pts = marker_points(z["vertices"], tri, w)  # (F, M, 3) cm
    b = bundles if isinstance(bundles, pd.DataFrame) else pd.read_csv(bundles)
    b = b.dropna(subset=["x", "y", "z"])
    frame_row = {int(f): i for i, f in enumerate(z["frames"])}
    col = {n: j for j, n in enumerate(names)}
    fi = np.array([frame_row[int(f)] for f in b["frame"]])
    mj = np.array([col[n] for n in b["marker"]])
    return np.linalg.norm(pts[fi, mj] - b[["x", "y", "z"]].to_numpy(np.float64), axis=1) * 10.0


def gaps_mm(vertices: np.ndarray, layout, bundles: np.ndarray) -> np.ndarray:
    """Distance (mm) from bundles (F, M, 3) cm (NaN where hidden) to their markers' points on ``vertices``
    (F, V, 3): the seen ones only, flattened."""
    d = np.linalg.norm(layout_points(vertices, layout) - np.asarray(bundles, np.float64), axis=-1) * 10.0
    return d[np.isfinite(d)]


# Linux keeps the high-water mark of the address space a child was forked from across exec, so a command started
# straight from the test process would report at least the test process's own peak; a small launcher in between
# starts it afresh and passes on its own figure.
_LAUNCHER = """
import json, os, subprocess, sys
p = subprocess.Popen(sys.argv[2:], stdout=subprocess.DEVNULL, stderr=open(sys.argv[1] + ".err", "wb"))
_, status, usage = os.wait4(p.pid, 0)
json.dump({"code": os.waitstatus_to_exitcode(status), "peak_kib": usage.ru_maxrss}, open(sys.argv[1], "w"))
"""


def peak_memory_run(argv: list[str], scratch: Path) -> tuple[int, float, str]:
    """Run ``argv`` as its own process: its exit status, its peak resident memory (MiB) and its standard error."""
    import json
    import subprocess
    import sys

    figures = scratch / "figures.json"
    subprocess.run([sys.executable, "-c", _LAUNCHER, str(figures), *argv], check=True)
    f = json.loads(figures.read_text())
    return f["code"], f["peak_kib"] / 1024, Path(f"{figures}.err").read_text(errors="replace")
