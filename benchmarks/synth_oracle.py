"""What a blend of the synthetic actor's dataset shapes can reach when the whole true surface is known.

    python benchmarks/synth_oracle.py [--step 5]

On the accuracy benchmark's synthetic set (:func:`lgi.evaluation.benchsets.synthetic_set`, every ``--step``-th of its
300 frames), with the true jaw, in the skinned space (``x = A_v(theta) (x0 + sum_k w_k d_k) + t_v``), fitted
to every true vertex rather than to the bundles:

- ``cell bounded``: weights in [0, 1] fitted per natural-neighbour cell of the bundles (the vertices whose
  nearest bundle is the same), the best any per-bundle choice of [0, 1] weights can do;
- ``cell free``: the same without bounds (extrapolating the shapes);
- ``global bounded``: one set of [0, 1] weights for the whole mesh.

Then LGI (default options) and the rigged blendshape fit from the bundles, on the same frames. Errors in
mm over every vertex. No timing; nothing asserted. It shows that a 0.5x target on this set lies below what
bounded dataset weights can represent.
"""

from __future__ import annotations

import argparse

import numpy as np
from common import synthetic_set
from scipy.optimize import lsq_linear

from lgi.evaluation.accuracy import build_set_index
from lgi.evaluation.baselines import RiggedBlendshapeSolver
from lgi.solve.solver import LGISolver


def _stats(errors: list[np.ndarray]) -> str:
    e = np.concatenate(errors)
    return f"RMS {np.sqrt(np.mean(e**2)):.4f}  p95 {np.percentile(e, 95):.4f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--step", type=int, default=5)
    args = ap.parse_args()
    bs = synthetic_set()
    index = build_set_index(bs)
    rig = index.jaw_rig()
    x0 = index.arrays["neutral"].astype(np.float64)
    deltas = np.asarray(index.deltas[1:], np.float64)  # (S, V, 3) unskinned
    owner = index.arrays["nn_owner"]
    frames = np.arange(0, bs.n_frames, args.step)
    out: dict[str, list[np.ndarray]] = {"cell bounded": [], "cell free": [], "global bounded": []}
    for f in frames:
        maps = rig.blend_matrices(bs.true_jaw[f])
        a_all = np.einsum("vij,kvj->vik", maps[:, :, :3], deltas)  # (V, 3, S)
        b_all = bs.truth[f] - np.einsum("vij,vj->vi", maps[:, :, :3], x0) - maps[:, :, 3]
        w = lsq_linear(a_all.reshape(-1, len(deltas)), b_all.ravel(), bounds=(0, 1), method="bvls").x
        out["global bounded"].append(10 * np.linalg.norm(a_all @ w - b_all, axis=1))
        eb = np.zeros(len(x0))
        ef = np.zeros(len(x0))
        for o in np.unique(owner):
            m = owner == o
            a, b = a_all[m].reshape(-1, len(deltas)), b_all[m].ravel()
            w = lsq_linear(a, b, bounds=(0, 1), method="bvls").x
            eb[m] = 10 * np.linalg.norm((a @ w - b).reshape(-1, 3), axis=1)
            w = np.linalg.lstsq(a, b, rcond=None)[0]
            ef[m] = 10 * np.linalg.norm((a @ w - b).reshape(-1, 3), axis=1)
        out["cell bounded"].append(eb)
        out["cell free"].append(ef)
    print(f"synthetic set, {len(frames)} frames (every {args.step}th), errors over every vertex, mm")
    print("fitted to the true surface (true jaw):")
    for k, v in out.items():
        print(f"  {k:15s} {_stats(v)}")
    lgi_sol = LGISolver(index)  # lgi reconstruct's defaults
    res = lgi_sol.solve_sequence(bs.bundles, noise="auto")
    rigged = RiggedBlendshapeSolver(index).solve_sequence(bs.bundles)
    print("fitted to the bundles (jaw estimated), the same frames:")
    for name, verts in (("LGI (default)", res.vertices), ("rigged blendshape fit", rigged)):
        e = [10 * np.linalg.norm(verts[f] - bs.truth[f], axis=1) for f in frames]
        print(f"  {name:22s} {_stats(e)}")


if __name__ == "__main__":
    main()
