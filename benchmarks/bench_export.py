"""USD export of a 200-frame ICT performance, read back with pxr; and displacement maps.

    python benchmarks/bench_export.py [--frames 200] [--ict ../shared/data/ict-facekit]

Frames: a smooth walk through random mixes of the ICT shapes (linear, so the truth is known); they are
reconstructed by LGI (ICT + 450 combinations), written as one animated USD mesh, read back, and compared.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from common import ICT_DIR, ICT_MARKERS, has_ict


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--ict", type=Path, default=ICT_DIR)
    args = ap.parse_args()
    if not has_ict(args.ict):
        print(f"skipped: ICT FaceKit not found at {args.ict}")
        return
    from pxr import Usd, UsdGeom

    from lgi.augment.combinations import linear_combinations
    from lgi.dataset.importing import import_obj_folder
    from lgi.dataset.markers import read_layout
    from lgi.export.formats import displacement_map, write_exr, write_usd
    from lgi.index.build import build_index
    from lgi.solve.solver import LGISolver

    ds = import_obj_folder(args.ict, rigid_vertices="none", show_progress=False)
    layout = read_layout(ICT_MARKERS, ds.triangles)
    index, _ = build_index(linear_combinations(ds, 450, seed=0), layout, show_progress=False)
    rng = np.random.default_rng(0)
    keys = rng.uniform(0, 0.6, (args.frames // 20 + 2, ds.n_shapes)) * (rng.random((args.frames // 20 + 2,
                                                                                     ds.n_shapes)) < 0.1)
    t = np.linspace(0, len(keys) - 1, args.frames)
    w = np.stack([np.interp(t, np.arange(len(keys)), keys[:, k]) for k in range(ds.n_shapes)], 1)
    truth = ds.neutral[None] + np.tensordot(w, np.asarray(ds.deltas, np.float64), axes=1)
    res = LGISolver(index).solve_sequence(layout.evaluate(truth))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ict_perf.usdc"
        t0 = time.perf_counter()
        write_usd(path, res.vertices, ds.face_vertices, ds.face_offsets, ds.uvs, ds.face_uvs, res.frames)
        dt_w = time.perf_counter() - t0
        t0 = time.perf_counter()
        stage = Usd.Stage.Open(str(path))
        pts = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/mesh")).GetPointsAttr()
        samples = pts.GetTimeSamples()
        back = np.stack([np.asarray(pts.Get(s)) for s in samples])
        dt_r = time.perf_counter() - t0
        print(f"USD: {len(samples)} time samples x {back.shape[1]} vertices, {path.stat().st_size / 2**20:.1f} MiB, "
              f"written in {dt_w:.2f} s, read back in {dt_r:.2f} s; max difference from the reconstruction "
              f"{np.abs(back - res.vertices).max():.1e} cm")
        t0 = time.perf_counter()
        img, mask = displacement_map(res.vertices[0] - ds.neutral, ds.face_vertices, ds.face_offsets, ds.uvs,
                                     ds.face_uvs, 1024)
        write_exr(Path(tmp) / "d.exr", img)
        print(f"displacement map 1024^2 (tile 0,0): {mask.mean() * 100:.0f} % covered, "
              f"{time.perf_counter() - t0:.2f} s per frame")
    err = np.linalg.norm(res.vertices[:, :9409] - truth[:, :9409], axis=2) * 10
    print(f"reconstruction of the walk (face area): RMS {np.sqrt(np.mean(err**2)):.3f} mm")


if __name__ == "__main__":
    main()
