"""Effect of linear in-betweens on LGI: the synthetic held-out performance, same frames, same run.

    python benchmarks/bench_augment.py [--frames 150] [--seed 1]

Datasets: the actor's 47 shapes alone, plus 150, plus 450 linear in-betweens (`lgi augment --linear`),
each indexed with and without the jaw rig. Prints error (mm), index size and build time. Simulated
in-betweens are not implemented yet.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lgi import synth
from lgi.augment import linear_combinations
from lgi.index import build_index
from lgi.solver import LGISolver


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    actor = synth.make_actor()
    ds = synth.make_dataset(actor)
    layout, _ = synth.default_layout(actor)
    truth = actor.evaluate_many(synth.random_performance(args.frames, seed=args.seed)).astype(np.float64)
    bundles = layout.evaluate(truth)
    print(f"synthetic actor, {args.frames} held-out frames (seed {args.seed})")
    print(f"{'dataset':<24}{'jaw':<9}{'RMS':>8}{'p95':>8}{'max':>7}{'simplices':>11}{'build s':>9}")
    for label, n in (("47 shapes", 0), ("+150 linear in-betweens", 150), ("+450 linear in-betweens", 450)):
        d = ds if n == 0 else linear_combinations(ds, n, seed=0, levels=(0.25, 0.5, 0.75, 1.0))
        for jaw_label, rig in (("none", None), ("rig", synth.jaw_rig(actor))):
            t = time.perf_counter()
            index, _ = build_index(d, layout, show_progress=False, jaw_rig=rig)
            bt = time.perf_counter() - t
            res = LGISolver(index, temporal_weight=0.02).solve_sequence(bundles)
            e = np.linalg.norm(res.vertices - truth, axis=2) * 10
            print(f"{label:<24}{jaw_label:<9}{np.sqrt(np.mean(e**2)):>8.4f}{np.percentile(e, 95):>8.4f}"
                  f"{e.max():>7.2f}{index.manifest['counts']['simplices']:>11}{bt:>9.1f}")


if __name__ == "__main__":
    main()
