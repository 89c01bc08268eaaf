"""LGI accuracy, speed and memory.

    python benchmarks/bench_lgi.py [--quick] [--ict ../shared/data/ict-facekit]

1. Synthetic held-out: the built-in actor's dataset (47 shapes) indexes a 300-frame random performance
   whose frames are not in the dataset; error against the truth (all vertices, and inside the markers'
   hull), bundle residual, frames/s.
2. ICT: verification of the 57 shapes (paper section 7.1), and a held-out check: 100 random 2-3 shape
   mixes at weights 0.3/0.6/0.9, not in the 507-shape dataset (ICT + 450 linear combinations) that
   indexes them; error over the face area (vertices 0-9408).
3. Scaling: build time and peak memory (fresh process each), and solve time per frame (median over
   in-between frames, after warm-up) for 100, 500 and 2000 shapes on the ICT mesh, and for the
   synthetic actor at 10k, 20k and 40k vertices with 500 shapes.

Every figure is printed; nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from common import ICT_DIR, ICT_MARKERS, has_ict, synthetic_actor

CHILD = r"""
import json, resource, sys, time
import numpy as np
cfg = json.loads(sys.argv[1])
from lgi.dataset.shapes import ShapeDataset
from lgi.augment.combinations import linear_combinations
from lgi.index.build import build_index
from lgi.dataset.markers import read_layout, layout_from_points
from lgi.solve.solver import LGISolver
from lgi.paths import shipped
from lgi.synthetic import actor as synth
if cfg["kind"] == "ict":
    from lgi.dataset.importing import import_obj_folder
    base = import_obj_folder(cfg["ict"], rigid_vertices="none", show_progress=False)
    layout = read_layout(shipped("markers_ict.csv"), base.triangles)
else:
    actor = synth.make_actor(cfg["vertices"])
    base = synth.make_dataset(actor)
    layout, _ = synth.default_layout(actor)
ds = linear_combinations(base, cfg["shapes"] - base.n_shapes, seed=0) if cfg["shapes"] > base.n_shapes else \
    base.take(range(cfg["shapes"]))
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
index, _ = build_index(ds, layout, show_progress=False)
build_s = time.perf_counter() - t
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
sol = LGISolver(index)
P = index.arrays["ptab"]
rng = np.random.default_rng(1)
ks = rng.choice(len(P), (cfg["frames"], 2))
w = rng.uniform(0.2, 0.8, cfg["frames"])[:, None, None]
frames = w * P[ks[:, 0]] + (1 - w) * P[ks[:, 1]]
prev = sol.solve_frame(frames[0])
runs = []
for _ in range(3):
    ts = []
    for f in frames:
        t = time.perf_counter(); prev = sol.solve_frame(f, prev); ts.append(time.perf_counter() - t)
    runs.append(float(np.median(ts)))
print(json.dumps({"build_s": build_s, "peak_rss_mib": peak / 1024, "before_build_mib": rss0 / 1024,
                  "solve_ms": float(np.median(runs)) * 1e3, "simplices": index.manifest["counts"]["simplices"],
                  "vertices": index.n_vertices, "shapes": ds.n_shapes}))
"""


def synthetic_heldout(frames: int) -> None:
    from scipy.spatial import Delaunay

    from lgi.evaluation.verify import verify_index
    from lgi.index.build import build_index
    from lgi.solve.solver import LGISolver
    from lgi.synthetic import actor as synth

    actor, ds, layout = synthetic_actor()
    t = time.perf_counter()
    index, _ = build_index(ds, layout, show_progress=False)
    build_s = time.perf_counter() - t
    table = verify_index(index)
    acts = synth.random_performance(frames, seed=1)
    truth = actor.evaluate_many(acts)
    sol = LGISolver(index)
    t = time.perf_counter()
    res = sol.solve_sequence(layout.evaluate(truth.astype(np.float64)))
    dt = time.perf_counter() - t
    err = np.linalg.norm(res.vertices - truth, axis=2) * 10
    inside = Delaunay(layout.evaluate(actor.neutral)[:, :2]).find_simplex(actor.neutral[:, :2]) >= 0
    print(f"\n== synthetic actor ({actor.n_vertices} vertices, {ds.n_shapes} shapes, {len(layout)} markers) ==")
    print(f"index built in {build_s:.1f} s; verification: worst RMS {table.rms_mm.max():.5f} mm, worst max "
          f"{table.max_mm.max():.4f} mm over {len(table)} shapes")
    print(f"held-out performance, {frames} frames (seed 1), {frames / dt:.0f} frames/s:")
    for name, e in (("all vertices", err), ("inside the markers' hull", err[:, inside]),
                    ("outside it (no marker)", err[:, ~inside])):
        print(f"  {name:<26} RMS {np.sqrt(np.mean(e**2)):.3f}  p95 {np.percentile(e, 95):.3f}  "
              f"p99 {np.percentile(e, 99):.3f}  max {e.max():.2f} mm")
    d = res.diagnostics
    print(f"  bundle residual: max {d.residual_mm.max():.2e} mm; bundles contained "
          f"{(d.status == 'contained').mean() * 100:.1f} %, took a neighbour's blend "
          f"{(d.status == 'neighbour').mean() * 100:.1f} %, projected {(d.status == 'projected').mean() * 100:.1f} %")


def ict_checks(ict: Path) -> None:
    from lgi.augment.combinations import linear_combinations
    from lgi.dataset.importing import import_obj_folder
    from lgi.dataset.markers import read_layout
    from lgi.evaluation.verify import verify_index
    from lgi.index.build import build_index
    from lgi.solve.solver import LGISolver

    base = import_obj_folder(ict, rigid_vertices="none", show_progress=False)
    layout = read_layout(ICT_MARKERS, base.triangles)
    index, _ = build_index(base, layout, show_progress=False)
    table = verify_index(index)
    print(f"\n== ICT FaceKit ({base.n_vertices} vertices, {len(layout)} markers) ==")
    print(f"verification, {len(table)} shapes: marked region worst RMS {table.rms_mm.max():.5f} mm "
          f"({table['shape'].iloc[int(table.rms_mm.argmax())]}), worst max {table.max_mm.max():.4f} mm; "
          f"whole mesh worst RMS {table.rms_all_mm.max():.4f} mm "
          f"({table['shape'].iloc[int(table.rms_all_mm.argmax())]}); bundle residual max "
          f"{table.residual_mm.max():.1e} mm")
    big = linear_combinations(base, 450, seed=0)
    test = linear_combinations(base, 100, seed=123, levels=(0.3, 0.6, 0.9)).take(range(57, 157))
    held = [n for n in test.names if n not in set(big.names)]
    index, _ = build_index(big, layout, show_progress=False)
    truth = base.neutral[None] + np.asarray(test.deltas, np.float64)
    sol = LGISolver(index)
    face = np.arange(9409)
    errs, res = [], []
    for t_, b in zip(truth, layout.evaluate(truth), strict=True):
        r = sol.solve_frame(b)
        errs.append(np.linalg.norm(r.vertices[face] - t_[face], axis=1) * 10)
        res.append(np.nanmax(r.residual) * 10)
    e = np.array(errs)
    print(f"held-out: {len(held)} mixes not in the {big.n_shapes}-shape dataset, face area: RMS "
          f"{np.sqrt(np.mean(e**2)):.3f}  p95 {np.percentile(e, 95):.3f}  p99 {np.percentile(e, 99):.3f}  "
          f"max {e.max():.2f} mm; bundle residual max {max(res):.1e} mm")


def scaling(ict: Path | None, quick: bool) -> None:
    configs = []
    if ict is not None:
        for s in ((100, 500) if quick else (100, 500, 2000)):
            configs.append({"kind": "ict", "ict": str(ict), "shapes": s, "frames": 100})
    for v in ((10000,) if quick else (10000, 20000, 40000)):
        configs.append({"kind": "synth", "vertices": v, "shapes": 500, "frames": 100})
    print("\n== scaling (fresh process per row; solve = median of 3 runs of per-frame medians) ==")
    print(f"{'mesh':<10}{'vertices':>9}{'shapes':>8}{'simplices':>11}{'build s':>9}{'peak MiB':>10}{'solve ms':>10}")
    for cfg in configs:
        out = subprocess.run([sys.executable, "-c", CHILD, json.dumps(cfg)], capture_output=True, text=True)
        if out.returncode != 0:
            print(f"{cfg}: failed\n{out.stderr[-2000:]}")
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{cfg['kind']:<10}{r['vertices']:>9}{r['shapes']:>8}{r['simplices']:>11}{r['build_s']:>9.1f}"
              f"{r['peak_rss_mib']:>10.0f}{r['solve_ms']:>10.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer frames and sizes")
    ap.add_argument("--ict", type=Path, default=ICT_DIR)
    args = ap.parse_args()
    ict = args.ict if has_ict(args.ict) else None
    synthetic_heldout(120 if args.quick else 300)
    if ict is None:
        print(f"\nICT FaceKit not found at {args.ict}: ICT checks and ICT scaling skipped")
    else:
        ict_checks(ict)
    with tempfile.TemporaryDirectory():
        scaling(ict, args.quick)


if __name__ == "__main__":
    main()
