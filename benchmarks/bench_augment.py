"""In-betweens: volume kept by simulated ones, their effect on LGI, and the simulation's speed on ICT.

    python benchmarks/bench_augment.py [--frames 150] [--seed 1] [--budget 100] [--ict DIR]

1. Volume: for 20 combinations of the synthetic actor's shapes, the relative change of the mouth and
   cheek flesh volume (the flesh model's soft region) from the neutral: the linear blend (skin held at the
   blend, the flesh relaxed behind it) against the simulated in-between. Also the simulated skin's
   distance from the blend, the lips' worst penetration, and how far each in-between is from the
   actor's true in-between (the actor evaluated at the combined activations), whose own flesh volume
   change is shown too: the synthetic actor is not built to keep volume.
2. Effect: on the synthetic actor's held-out performance (same frames, same run), LGI error with the 47
   dataset shapes alone, with `--budget` linear in-betweens and with the same combinations simulated;
   each indexed with and without the jaw rig; index size (simplices, MiB on disk) and build time.
3. Speed: one simulated in-between on the ICT face (model set-up once, then per in-between; median of 5).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from common import ICT_DIR, has_ict, synthetic_actor

from lgi.augment.combinations import Blender, linear_combinations, pick_combinations, simulated_combinations
from lgi.augment.flesh import FleshModel
from lgi.index.build import build_index
from lgi.solve.solver import LGISolver
from lgi.synthetic import actor as synth


def volume_table(actor, ds, rig) -> None:
    blender = Blender(ds, rig)
    model = FleshModel(ds.neutral, ds.triangles, blender.deltas, rig=rig, shape_jaw=blender.params)
    picks = pick_combinations(ds.names, 20, levels=(0.25, 0.5, 0.75, 1.0), seed=7)
    print(f"## Volume of the mouth and cheek flesh, 20 combinations ({model.n_outer} skin vertices, "
          f"{len(model.tets)} tetrahedra, {int(model.soft_tets.sum())} in the mouth/cheek region)")
    print("| combination | linear % | simulated % | true in-between % | skin from blend mm | "
          "lip penetration linear / simulated mm | from the true in-between: linear / simulated mm |")
    print("|---|---|---|---|---|---|---|")
    names, acts = synth.default_dataset_activations()
    activation = dict(zip(names, acts, strict=True))
    lo, hi = model.lip_pairs[:, 0], model.lip_pairs[:, 1]
    lin_all, sim_all, true_all, err_lin, err_sim, times = [], [], [], [], [], []
    linear = Blender(ds)
    for combo in picks:
        target, jaw = blender.target(combo)
        t = time.perf_counter()
        sim = model.solve(target, jaw)
        times.append(time.perf_counter() - t)
        lin = model.solve(target, jaw, hard_skin=True)
        truth = actor.evaluate(np.clip(sum(w * activation[k] for k, w in combo.items()), 0, 1))
        tv = model.solve(truth, jaw, hard_skin=True).volume_change
        lin_target = linear.target(combo)[0]
        pen = [10 * max(float(((x[model.verts[lo]] - x[model.verts[hi]]) @ model.up).max()), 0.0)
               for x in (lin_target, sim.positions)]
        el, es = (10 * float(np.sqrt(np.mean(np.sum((x - truth) ** 2, axis=1)))) for x in (lin_target, sim.positions))
        name = " + ".join(f"{k}*{w:g}" for k, w in combo.items())
        print(f"| {name} | {100 * lin.volume_change:+.2f} | {100 * sim.volume_change:+.2f} | {100 * tv:+.2f} | "
              f"{10 * sim.target_distance:.2f} | {pen[0]:.2f} / {pen[1]:.2f} | {el:.2f} / {es:.2f} |")
        lin_all.append(abs(lin.volume_change))
        sim_all.append(abs(sim.volume_change))
        true_all.append(abs(tv))
        err_lin.append(el)
        err_sim.append(es)
    lin_all, sim_all = np.array(lin_all), np.array(sim_all)
    print(f"\n|volume change|: linear median {100 * np.median(lin_all):.2f} %, max {100 * lin_all.max():.2f} %; "
          f"simulated median {100 * np.median(sim_all):.2f} %, max {100 * sim_all.max():.2f} %; "
          f"simulated within 2 %: {(sim_all < 0.02).sum()} of 20; the actor's true in-betweens median "
          f"{100 * np.median(true_all):.2f} %, max {100 * max(true_all):.2f} %; {np.median(times):.2f} s per "
          f"in-between (median)")
    print(f"distance from the true in-between (RMS over vertices, median of 20): linear {np.median(err_lin):.3f} mm, "
          f"simulated {np.median(err_sim):.3f} mm\n")


def effect_table(actor, ds, rig, layout, frames: int, seed: int, budget: int) -> None:
    truth = actor.evaluate_many(synth.random_performance(frames, seed=seed)).astype(np.float64)
    bundles = layout.evaluate(truth)
    picks = pick_combinations(ds.names, budget, levels=(0.25, 0.5, 0.75, 1.0), seed=0)
    t = time.perf_counter()
    sim = simulated_combinations(ds, 0, rig=rig, picks=picks)
    t_sim = time.perf_counter() - t
    lin = linear_combinations(ds, 0, picks=picks)
    print(f"## Effect on LGI: {frames} held-out frames (seed {seed}), {len(picks)} combinations "
          f"(simulated in {t_sim:.0f} s)")
    print("| dataset | jaw | RMS mm | p95 mm | max mm | simplices | index MiB | build s |")
    print("|---|---|---|---|---|---|---|---|")
    for label, d in (("47 shapes", ds), (f"+{len(picks)} linear", lin), (f"+{len(picks)} simulated", sim)):
        for jaw_label, r in (("none", None), ("rig", rig)):
            t = time.perf_counter()
            index, reports = build_index(d, layout, show_progress=False, jaw_rig=r)
            bt = time.perf_counter() - t
            with tempfile.TemporaryDirectory() as tmp:
                index.save(Path(tmp) / "idx", reports)
                mib = sum(p.stat().st_size for p in (Path(tmp) / "idx").rglob("*") if p.is_file()) / 2**20
            res = LGISolver(index).solve_sequence(bundles)
            e = np.linalg.norm(res.vertices - truth, axis=2) * 10
            print(f"| {label} | {jaw_label} | {np.sqrt(np.mean(e**2)):.4f} | {np.percentile(e, 95):.4f} | "
                  f"{e.max():.2f} | {index.manifest['counts']['simplices']} | {mib:.1f} | {bt:.1f} |")
    print()


def ict_speed(folder: Path) -> None:
    if not has_ict(folder):
        print(f"ICT speed: skipped, ICT FaceKit not found at {folder}")
        return
    from lgi.dataset.importing import import_obj_folder

    ds = import_obj_folder(folder, show_progress=False)
    t = time.perf_counter()
    model = FleshModel(ds.neutral, ds.triangles, np.asarray(ds.deltas))
    setup = time.perf_counter() - t
    blender = Blender(ds)
    picks = pick_combinations(ds.names, 6, levels=(0.5, 1.0), seed=2)
    model.solve(blender.target(picks[0])[0])  # compile the kernels
    times, dv = [], []
    for combo in picks[1:]:
        t = time.perf_counter()
        r = model.solve(blender.target(combo)[0])
        times.append(time.perf_counter() - t)
        dv.append(abs(r.volume_change))
    print(f"## ICT: {model.n_outer} skin vertices, {len(model.tets)} tetrahedra; model set-up {setup:.2f} s; "
          f"one in-between {np.median(times):.2f} s median (runs {', '.join(f'{x:.2f}' for x in times)}); "
          f"|volume change| max {100 * max(dv):.2f} %")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--budget", type=int, default=100)
    ap.add_argument("--ict", type=Path, default=ICT_DIR)
    ap.add_argument("--skip", default="", help="comma-separated sections to skip: volume,effect,ict")
    args = ap.parse_args()
    skip = set(args.skip.split(","))
    actor, ds, layout = synthetic_actor()
    rig = synth.jaw_rig(actor)
    if "ict" not in skip:
        ict_speed(args.ict)
    if "volume" not in skip:
        volume_table(actor, ds, rig)
    if "effect" not in skip:
        effect_table(actor, ds, rig, layout, args.frames, args.seed, args.budget)


if __name__ == "__main__":
    main()
