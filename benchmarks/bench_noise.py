"""Bundle noise at every level real capture has: LGI's default against the rigged fit, smoothed or not.

    python benchmarks/bench_noise.py [--sets synthetic,session_400] [--sigmas 0,0.01,...] [--doc docs/accuracy.md]
        [--plot docs/images/noise.png]

Each set's clean bundles (its frames are never dataset shapes) get Gaussian noise of sigma mm, either the same on
every axis ("isotropic") or "stereo": sigma along z (depth, the cameras' rays) and a quarter of it along x and y,
as two cameras a few centimetres apart triangulate; then 5 % of marker-frames are lost in runs of 1-6 frames
(:func:`lgi.evaluation.benchsets.tracking_noise`). Every method is given the same dataset, rig and frames:

* ``LGI (default)``: ``lgi reconstruct``'s defaults (the noise estimated from the shot, per axis);
* ``LGI, true sigma``: the same told the true noise per axis (``--noise`` per axis);
* ``fit``: the bounded blendshape fit with the jaw rig, frame by frame (no smoothing);
* ``fit, smoothed``: the same fit of the bundles smoothed exactly as LGI smooths them (its estimate);
* ``fit, smoothed (true sigma)``: the same, the smoothing told the true noise per axis.

Columns: RMS and p95 of the vertex error over the set's measured vertices (mm), LGI's ratio to the best of the
three fits, and the noise LGI estimated per axis beside the true one. Sets: the names of
:data:`lgi.evaluation.benchsets.SET_NAMES` (ICT sets need the ICT data).
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np
from common import log, write_marked

from lgi.evaluation.accuracy import build_set_index
from lgi.evaluation.baselines import RiggedBlendshapeSolver
from lgi.evaluation.benchsets import load_sets, tracking_noise
from lgi.evaluation.metrics import vertex_errors
from lgi.solve.solver import LGISolver
from lgi.units import MM_PER_CM

SIGMAS = (0.0, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.3)
STEREO_ACROSS = 0.25  # x and y noise as a share of the depth noise


def noisy_bundles(bundles: np.ndarray, sigma_mm: float, kind: str, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Bundles (F, M, 3) cm with noise of ``sigma_mm`` ("iso" or "stereo") and 5 % missing; the true sigma (3,)."""
    axes = np.full(3, sigma_mm) if kind == "iso" else np.array([STEREO_ACROSS, STEREO_ACROSS, 1.0]) * sigma_mm
    gaps = tracking_noise(bundles, seed, 0.0)
    rng = np.random.default_rng([seed, 31])
    out = bundles + rng.normal(size=bundles.shape) * axes / MM_PER_CM
    out[~np.isfinite(gaps)] = np.nan
    return out, axes


def errors(vertices: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    e = vertex_errors(vertices, truth)[:, mask]  # mm
    return float(np.sqrt(np.mean(e**2))), float(np.percentile(e, 95))


def run_one(bs, index, pos: np.ndarray, axes: np.ndarray) -> dict:
    """The four reconstructions of one noisy shot."""
    row: dict = {}
    t = time.perf_counter()
    solver = LGISolver(index)  # lgi reconstruct's defaults
    # solve_sequence's steps, to keep the noise they resolve
    prep = solver.prepare_shot(pos)
    fit_pos, noise = solver.denoise(prep.positions, prep.noise)
    res = solver.with_noise(noise).solve_prepared(prep.positions, prep.frames, prep.bridged, fit_pos)
    row["lgi_s"] = time.perf_counter() - t
    row["lgi"] = errors(res.vertices, bs.truth, bs.mask)
    est = noise.estimate
    row["estimate"] = np.full(3, np.nan) if est is None else est.axis_mm
    row["noise_used"] = noise.axes
    told_res = LGISolver(index, noise=axes).solve_sequence(pos, noise=None)
    row["lgi_true"] = errors(told_res.vertices, bs.truth, bs.mask)
    fit = RiggedBlendshapeSolver(index)
    row["fit"] = errors(fit.solve_sequence(pos), bs.truth, bs.mask)
    smooth = LGISolver(index)
    row["fit_smoothed"] = errors(fit.solve_sequence(smooth.denoise(pos, smooth.resolve_noise(pos, "auto"))[0]),
                                 bs.truth, bs.mask)
    row["fit_true"] = errors(fit.solve_sequence(LGISolver(index, noise=axes).denoise(pos)[0]), bs.truth, bs.mask)
    return row


def table(rows: list[dict]) -> str:
    head = ("| set | noise | sigma mm | LGI RMS / p95 | fit | fit, smoothed | fit, smoothed (true sigma) "
            "| LGI / best RMS | LGI / best p95 | estimated sigma x / y / z mm | LGI, true sigma | estimated / true "
            "sigma, LGI RMS |\n" + "|---" * 12 + "|")
    lines = [head]
    for r in rows:
        base = [r["fit"], r["fit_smoothed"], r["fit_true"]]
        best_rms = min(b[0] for b in base)
        best_p95 = min(b[1] for b in base)
        est = " / ".join(f"{v:.4f}" for v in r["estimate"]) if np.isfinite(r["estimate"]).all() else "exact"
        lines.append(f"| {r['set']} | {r['kind']} | {r['sigma']:g} | {r['lgi'][0]:.4f} / {r['lgi'][1]:.4f} | "
                     + " | ".join(f"{b[0]:.4f} / {b[1]:.4f}" for b in base)
                     + f" | {r['lgi'][0] / best_rms:.2f} | {r['lgi'][1] / best_p95:.2f} | {est} "
                     f"| {r['lgi_true'][0]:.4f} / {r['lgi_true'][1]:.4f} | {r['lgi'][0] / r['lgi_true'][0]:.3f} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = sorted({r["set"] for r in rows})
    kinds = ["iso", "stereo"]
    fig, axs = plt.subplots(len(sets), 2, figsize=(10, 3.6 * len(sets)), squeeze=False)
    for i, name in enumerate(sets):
        for j, kind in enumerate(kinds):
            ax = axs[i][j]
            sub = [r for r in rows if r["set"] == name and r["kind"] == kind]
            if not sub:
                ax.set_visible(False)
                continue
            x = [max(r["sigma"], 1e-3) for r in sub]
            for key, label in (("lgi", "LGI (default)"), ("fit", "fit + rig"), ("fit_smoothed", "fit + rig, smoothed"),
                               ("fit_true", "fit + rig, smoothed (true sigma)")):
                ax.plot(x, [r[key][0] for r in sub], marker="o", label=label)
            ax.set_xscale("log")
            ax.set_xlabel("bundle noise sigma, mm (0 drawn at 0.001)")
            ax.set_ylabel("vertex RMS error, mm")
            ax.set_title(f"{name}, {'isotropic' if kind == 'iso' else 'stereo (depth sigma, x/y a quarter)'}")
            ax.grid(True, alpha=0.3)
    axs[0][0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=70)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", default="synthetic", help="comma-separated set names (default: synthetic)")
    ap.add_argument("--sigmas", default=",".join(f"{s:g}" for s in SIGMAS), help="mm, comma-separated")
    ap.add_argument("--kinds", default="iso,stereo")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--doc", type=Path, help="write the table into this Markdown file (<!-- table:noise -->)")
    ap.add_argument("--plot", type=Path, help="write the plot (PNG) here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    sigmas = [float(s) for s in args.sigmas.split(",")]
    rows: list[dict] = []
    sets = load_sets(args.sets.split(","))
    for name, bs in sets.items():
        log(f"{name}: building the index")
        index = build_set_index(bs)
        for kind in args.kinds.split(","):
            for sigma in sigmas:
                if kind == "stereo" and sigma == 0:
                    continue
                pos, axes = noisy_bundles(bs.bundles, sigma, kind, args.seed)
                row = {"set": name, "kind": kind, "sigma": sigma, **run_one(bs, index, pos, axes)}
                rows.append(row)
                log(f"{name} {kind} {sigma:g}: LGI {row['lgi'][0]:.4f}, fits {row['fit'][0]:.4f} "
                    f"{row['fit_smoothed'][0]:.4f} {row['fit_true'][0]:.4f}, estimate {row['estimate']}")
    frames = " ".join(f"{n}: {bs.description}" for n, bs in sets.items())
    text = table(rows)
    print(text)
    if args.doc:
        intro = (f"Frames (never dataset shapes): {frames} Noise as named, 5 % of marker-frames missing in runs; "
                 f"seed {args.seed}. RMS / p95 mm over the measured vertices.\n\n")
        write_marked(args.doc, "noise", intro + text)
    if args.plot:
        plot(rows, args.plot)


if __name__ == "__main__":
    main()
