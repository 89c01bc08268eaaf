"""Temporal coherence on noisy bundles: jitter, error and bundle residual with and without smoothing.

    python benchmarks/bench_temporal.py [--frames 300] [--seed 1]

The synthetic actor's held-out performance, indexed with its jaw rig. Bundles get Gaussian noise
(0.3 mm per coordinate) plus a systematic 1 mm depth (z) error on the actor's left side (x > 0), as
limited parallax between two cameras gives. Jitter: mean squared second difference of vertex positions
over time (mm^2); the truth's own value is printed. Residual before correction: how far the smoothed
surface is from the (noisy) bundles before the smooth correction takes it through them, i.e. the
effect of smoothing on interpolation (the paper reports it negligible).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from common import synthetic_actor

from lgi.evaluation.metrics import jitter, vertex_errors
from lgi.index.build import build_index
from lgi.solve.solver import LGISolver
from lgi.solve.temporal import bilateral_filter
from lgi.synthetic import actor as synth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    actor, ds, layout = synthetic_actor()
    index, _ = build_index(ds, layout, show_progress=False, jaw_rig=synth.jaw_rig(actor))
    truth = actor.evaluate_many(synth.random_performance(args.frames, seed=args.seed)).astype(np.float64)
    clean = layout.evaluate(truth)
    rng = np.random.default_rng(args.seed)
    noisy = clean + rng.normal(scale=0.03, size=clean.shape)
    noisy[:, layout.evaluate(actor.neutral)[:, 0] > 0, 2] += 0.1
    print(f"synthetic actor with jaw rig, {args.frames} frames; noise 0.3 mm + 1 mm depth error on the left side")
    print(f"truth's own jitter {jitter(truth):.4f} mm^2; error of the noisy bundles themselves: RMS "
          f"{np.sqrt(np.mean(np.sum((noisy - clean) ** 2, -1))) * 10:.3f} mm")
    print(f"{'configuration':<44}{'jitter':>9}{'RMS':>8}{'p95':>8}{'max':>7}{'resid before':>14}{'resid':>10}"
          f"{'fr/s':>6}")
    configs = [
        ("no smoothing, no previous-frame preference", dict(temporal_weight=0.0), 1, None),
        ("previous-frame preference 0.02 mm", dict(temporal_weight=0.02), 1, None),
        ("previous-frame preference 0.1 mm", dict(temporal_weight=0.1), 1, None),
        ("previous-frame preference 0.3 mm", dict(temporal_weight=0.3), 1, None),
        ("weights window 5 (+ pref 0.1)", dict(temporal_weight=0.1), 5, None),
        ("weights window 9 (+ pref 0.1)", dict(temporal_weight=0.1), 9, None),
        ("bilateral 1.5 fr / 0.5 mm + window 5", dict(temporal_weight=0.1), 5, (1.5, 0.05)),
        ("bilateral 1.5 fr / 0.5 mm / 10 mm space + w 5", dict(temporal_weight=0.1), 5, (1.5, 0.05, 1.0)),
        ("clean bundles, window 5 (reference)", dict(temporal_weight=0.1), 5, "clean"),
    ]
    for label, kw, window, bil in configs:
        rest = layout.evaluate(actor.neutral)
        if bil == "clean":
            b = clean
        elif bil is None:
            b = noisy
        else:
            b = bilateral_filter(noisy, bil[0], bil[1], rest, bil[2] if len(bil) > 2 else None)
        sol = LGISolver(index, **kw)
        t = time.perf_counter()
        res = sol.solve_sequence(b, smooth=window)
        dt = time.perf_counter() - t
        e = vertex_errors(res.vertices, truth)
        d = res.diagnostics
        print(f"{label:<44}{jitter(res.vertices):>9.4f}{np.sqrt(np.mean(e**2)):>8.3f}{np.percentile(e, 95):>8.3f}"
              f"{e.max():>7.2f}{d.residual_before_mm.median():>8.4f}/{d.residual_before_mm.max():<6.3f}"
              f"{d.residual_mm.max():>9.1e}{args.frames / dt:>6.0f}")
    print("(resid before: median/max mm; resid: after the correction, mm)")


if __name__ == "__main__":
    main()
