"""How far the synthetic actor's truth is from a linear blend of its extreme shapes.

    python benchmarks/synth_nonlinearity.py [--frames 600] [--seed 0]

The linear blend uses each control's extreme shape (activation 1, alone):
``x0 + sum_k a_k (x(e_k) - x0)``. Printed in mm: per named combination, and over a random performance.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.optimize import lsq_linear

from lgi.synthetic import actor as synth


def best_blendshape_fit(actor: synth.SyntheticActor, truth: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """(V,) mm: residual of the best bounded ([0, 1]) least-squares fit of ``basis`` deltas (K, V, 3) to
    the whole true mesh (every vertex known: a best case no marker-driven fit can beat)."""
    a = basis.reshape(len(basis), -1).T
    w = lsq_linear(a, (truth - actor.neutral).ravel(), bounds=(0, 1)).x
    return 10 * np.linalg.norm(truth - actor.neutral - np.tensordot(w, basis, axes=1), axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--vertices", type=int, default=20000)
    args = ap.parse_args()
    actor = synth.make_actor(args.vertices)
    e = np.eye(len(synth.CONTROLS))
    C = synth.C
    combos = {
        "jaw_open 0.5": 0.5 * e[C["jaw_open"]],
        "jaw_open 1 + smile_L 1": e[C["jaw_open"]] + e[C["smile_L"]],
        "jaw_open 1 + pucker 1": e[C["jaw_open"]] + e[C["pucker"]],
        "jaw_open 1 + cheek_puff 1": e[C["jaw_open"]] + e[C["cheek_puff"]],
        "smile_L 1 + sneer_L 1": e[C["smile_L"]] + e[C["sneer_L"]],
        "smile_L+R 1": e[C["smile_L"]] + e[C["smile_R"]],
        "brow_raise_L+R 1": e[C["brow_raise_L"]] + e[C["brow_raise_R"]],
        "smile_L 0.5": 0.5 * e[C["smile_L"]],
        "jaw_open+smile+sneer (L) 1": e[C["jaw_open"]] + e[C["smile_L"]] + e[C["sneer_L"]],
        "all controls 0.5": 0.5 * np.ones(len(synth.CONTROLS)),
    }
    nl = synth.nonlinearity(actor, np.array(list(combos.values())))
    print(f"synthetic actor, {actor.n_vertices} vertices: truth vs linear blend of extremes (mm)")
    print(f"{'expression':<30}{'RMS':>8}{'max':>8}")
    for (name, _), (rms, mx) in zip(combos.items(), nl, strict=True):
        print(f"{name:<30}{rms:>8.2f}{mx:>8.2f}")
    acts = synth.random_performance(args.frames, seed=args.seed)
    perf = synth.nonlinearity(actor, acts)
    print(f"\nrandom performance, {args.frames} frames (seed {args.seed}), per-frame figures:")
    for label, col in (("RMS", 0), ("max", 1)):
        q = np.percentile(perf[:, col], [50, 95, 100])
        print(f"  {label}: median {q[0]:.2f}, 95th percentile {q[1]:.2f}, worst {q[2]:.2f}")

    # Best case for a linear blendshape system: weights fitted to every vertex of the truth, using the
    # whole synthetic dataset (extremes, in-betweens and combinations) as the basis.
    ds = synth.make_dataset(actor)
    basis = np.asarray(ds.deltas, np.float64)
    worst = np.argsort(perf[:, 1])[-20:]
    res = np.array([best_blendshape_fit(actor, actor.evaluate(acts[i]), basis) for i in worst])
    print(f"\nbest bounded least-squares fit of all {ds.n_shapes} dataset shapes to the full true mesh, on the "
          f"20 most nonlinear frames: RMS median {np.median(np.sqrt((res**2).mean(1))):.2f} mm, "
          f"max median {np.median(res.max(1)):.2f} mm, worst {res.max():.2f} mm")


if __name__ == "__main__":
    main()
