"""Jaw handling: LGI with and without linear-blend-skinned jaw articulation, same frames, same run.

    python benchmarks/bench_jaw.py [--frames 300] [--seed 2]

The synthetic actor's jaw truly rotates (22 degrees at full opening, with a forward slide). The
performance is the usual random one with extra jaw-opening events (peaks 0.6-1.0), so many frames open
the jaw more than 15 degrees. "with jaw" builds the index from unskinned shapes with the actor's rig
(`lgi synth` writes it as jaw_rig.npz) and estimates each frame's jaw from the bundles; "without" indexes
the shapes as they are. Errors in mm against the truth.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from common import synthetic_actor

from lgi.evaluation.metrics import vertex_errors
from lgi.index.build import build_index
from lgi.solve.solver import LGISolver
from lgi.synthetic import actor as synth


def jaw_performance(frames: int, seed: int) -> np.ndarray:
    """(F, C) random activations with added jaw-opening events."""
    acts = synth.random_performance(frames, seed=seed)
    rng = np.random.default_rng(seed + 100)
    t = np.arange(frames)
    jaw = np.zeros(frames)
    for _ in range(max(2, frames // 45)):
        c, half, peak = rng.uniform(0, frames), rng.uniform(10, 30), rng.uniform(0.6, 1.0)
        u = np.clip((t - c) / half, -1, 1)
        jaw = np.maximum(jaw, peak * 0.5 * (1 + np.cos(np.pi * u)))
    acts[:, synth.C["jaw_open"]] = np.clip(np.maximum(acts[:, synth.C["jaw_open"]], jaw), 0, 1)
    return acts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=2)
    args = ap.parse_args()
    actor, ds, layout = synthetic_actor()
    acts = jaw_performance(args.frames, args.seed)
    truth = actor.evaluate_many(acts).astype(np.float64)
    bundles = layout.evaluate(truth)
    true_jaw = actor.jaw_parameters(acts)
    open_ = true_jaw[:, 0] > 15.0
    print(f"synthetic actor, {args.frames} frames (seed {args.seed}); {open_.sum()} frames with the jaw open "
          f"more than 15 degrees (max {true_jaw[:, 0].max():.1f})")
    print(f"{'method':<34}{'RMS all':>9}{'RMS open':>10}{'p95 open':>10}{'max open':>10}{'jaw err deg':>13}"
          f"{'frames/s':>10}")
    for label, rig in (("LGI without jaw handling", None), ("LGI with jaw (rig, estimated jaw)", synth.jaw_rig(actor))):
        index, _ = build_index(ds, layout, show_progress=False, jaw_rig=rig)
        sol = LGISolver(index)
        t = time.perf_counter()
        prev, out, jaws = None, [], []
        for b in bundles:
            prev = sol.solve_frame(b, prev)
            out.append(prev.vertices)
            jaws.append(prev.jaw if prev.jaw is not None else np.full(4, np.nan))
        dt = time.perf_counter() - t
        err = vertex_errors(np.stack(out), truth)
        jerr = np.nanmax(np.abs(np.array(jaws)[:, 0] - true_jaw[:, 0])) if rig is not None else float("nan")
        eo = err[open_]
        print(f"{label:<34}{np.sqrt(np.mean(err**2)):>9.3f}{np.sqrt(np.mean(eo**2)):>10.3f}"
              f"{np.percentile(eo, 95):>10.3f}{eo.max():>10.2f}{jerr:>13.3f}{args.frames / dt:>10.0f}")


if __name__ == "__main__":
    main()
