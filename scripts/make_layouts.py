"""Regenerate the marker layouts shipped in data/ (see data/README.md).

    python scripts/make_layouts.py [--ict ../shared/data/ict-facekit]

The synthetic layout is made from the built-in actor; the ICT layout needs the ICT FaceKit folder
and is skipped without it. Both are deterministic (seed 0).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from matplotlib.path import Path as Polygon2D

from lgi.dataset.markers import write_layout
from lgi.dataset.mesh import triangulate, vertex_normals
from lgi.synthetic import actor as synth
from lgi.synthetic.layout_design import design_layout, region_namer

ROOT = Path(__file__).resolve().parents[1]
N_MARKERS = 110


def density(p: np.ndarray, mouth: np.ndarray, eyes: np.ndarray) -> np.ndarray:
    """Relative dot density: 4.5x at the mouth, 2.5x at the eyes, 1 elsewhere (smooth)."""
    dm = np.linalg.norm(p - mouth, axis=1)
    de = np.min([np.linalg.norm(p - e, axis=1) for e in eyes], axis=0)
    return 1.0 + 3.5 * np.exp(-(dm**2) / (2 * 2.0**2)) + 1.5 * np.exp(-(de**2) / (2 * 1.5**2))


def synthetic_layout() -> None:
    actor = synth.make_actor()
    v = actor.neutral
    x, y = v[:, 0], v[:, 1]
    eye_d = np.min([np.hypot(x - ex, (y - ey) * 1.4) for ex, ey in synth.EYE_CENTERS], axis=0)
    ok = (
        (np.abs(x) < 7.0) & (y < 9.5) & (y > -9.5)
        & (eye_d > 1.3)  # eyes: no dots on the lids' margin or the eye itself
        & ~((np.abs(y - synth.MOUTH_Y) < 0.25) & (np.abs(x) < synth.MOUTH_HALF_WIDTH + 0.2))  # inner lips
    )
    cand = np.flatnonzero(ok)
    z_of = synth.face_depth
    mouth = np.array([0.0, synth.MOUTH_Y, float(z_of(np.array(0.0), np.array(synth.MOUTH_Y)))])
    eyes = [np.array([ex, ey, float(z_of(np.array(ex), np.array(ey)))]) for ex, ey in synth.EYE_CENTERS]
    anchors = {
        "forehead": np.array([[0, 7.5, 4.0], [3, 7.5, 4.0], [-3, 7.5, 4.0]]),
        "brow": np.array([[2.8, 4.5, 4.5], [-2.8, 4.5, 4.5], [0, 4.3, 4.8]]),
        "eye": np.array([[3.2, 1.3, 3.9], [-3.2, 1.3, 3.9], [4.8, 2.8, 3.0], [-4.8, 2.8, 3.0]]),
        "nose": np.array([[0, 0, 6.5], [0, 2.5, 5.5], [1.2, -1.6, 5.0], [-1.2, -1.6, 5.0]]),
        "cheek": np.array([[4.5, -1.5, 3.5], [-4.5, -1.5, 3.5], [5.5, 1.0, 2.5], [-5.5, 1.0, 2.5]]),
        "mouth": np.array([[0, synth.MOUTH_Y, 5.0], [2.0, synth.MOUTH_Y, 4.6], [-2.0, synth.MOUTH_Y, 4.6],
                           [0, -3.5, 5.2], [0, -5.5, 5.0]]),
        "chin": np.array([[0, -8.0, 4.5], [2.5, -8.5, 3.8], [-2.5, -8.5, 3.8]]),
        "jaw": np.array([[5.5, -6.0, 1.5], [-5.5, -6.0, 1.5]]),
    }
    layout = design_layout(v, actor.triangles, cand, density(v[cand], mouth, eyes), N_MARKERS, seed=0,
                           namer=region_namer(anchors))
    write_layout(ROOT / "data" / "markers_synth.csv", layout, neutral=v)
    print(f"synthetic: {len(layout)} markers -> data/markers_synth.csv")


def ict_layout(folder: Path) -> None:
    from lgi.io.obj import read_obj

    mesh = read_obj(folder / "generic_neutral_mesh.obj")
    v = mesh.vertices
    tris, _ = triangulate(mesh.face_vertices, mesh.face_offsets)
    lm = np.asarray(json.loads((folder / "vertex_indices.json").read_text())["idx_to_landmark_verts"])
    L = v[lm]
    n = vertex_normals(v, tris)
    narrow = np.zeros(len(v), bool)
    narrow[:6706] = True  # ICT's "narrow face area" (ABOUT.md)

    def inside(poly: np.ndarray, pts: np.ndarray, grow: float) -> np.ndarray:
        c = poly.mean(0)
        d = poly - c
        scale = 1 + grow / np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        return Polygon2D(c + d * scale[:, None]).contains_points(pts)

    xy = v[:, :2]
    eye_r, eye_l, inner_lip, outer_lip = L[36:42, :2], L[42:48, :2], L[60:68, :2], L[48:60, :2]
    ok = (
        narrow
        & (n[:, 2] > 0.3)  # facing the cameras; not the sides of the head
        & ~inside(eye_r, xy, 0.45) & ~inside(eye_l, xy, 0.45)
        & ~inside(inner_lip, xy, 0.3)
        & ~(inside(outer_lip, xy, 0.0) & (n[:, 2] < 0.6))  # lips rolling into the mouth
        & (v[:, 1] < L[19, 1] + 3.0) & (v[:, 1] > L[8, 1] - 0.5)  # forehead top, chin bottom
        & (np.abs(v[:, 0]) < 6.2)
    )
    cand = np.flatnonzero(ok)
    mouth = L[48:60].mean(0)
    eyes = [L[36:42].mean(0), L[42:48].mean(0)]
    anchors = {
        "forehead": L[[19, 24]] + [0, 2.5, -0.3],
        "brow": L[17:27],
        "eye": np.vstack([L[36:48] + [0, -0.8, 0], L[[36, 45]] + [[-1.0, 0, -1.0], [1.0, 0, -1.0]]]),
        "nose": L[27:36],
        "cheek": np.vstack([L[[2, 14]] + [[1.5, 0, 0.5], [-1.5, 0, 0.5]],
                            L[[1, 15]] + [[1.0, 1.5, 0], [-1.0, 1.5, 0]]]),
        "mouth": L[48:60],
        "chin": L[[7, 8, 9]] + [0, 0.8, 0],
        "jaw": L[[4, 5, 11, 12]],
    }
    layout = design_layout(v, tris, cand, density(v[cand], mouth, eyes), N_MARKERS, seed=0,
                           namer=region_namer(anchors))
    # Positions are left out on purpose: nothing derived from the ICT geometry is shipped, only our
    # choice of triangles and barycentric coordinates; they are evaluated on the mesh at run time.
    write_layout(ROOT / "data" / "markers_ict.csv", layout)
    print(f"ICT: {len(layout)} markers -> data/markers_ict.csv")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--ict", type=Path, default=ROOT.parent / "shared" / "data" / "ict-facekit")
    args = ap.parse_args()
    synthetic_layout()
    if (args.ict / "generic_neutral_mesh.obj").is_file():
        ict_layout(args.ict)
    else:
        print(f"ICT FaceKit not found at {args.ict}: ICT layout not regenerated")


if __name__ == "__main__":
    main()
