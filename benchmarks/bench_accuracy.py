"""LGI against the baselines on realistic input, every method on the same frames in one run.

    python benchmarks/bench_accuracy.py [--sets synthetic,ict_jaw,ict_heldout,ict_combination,session_0,session_150,
                                                session_400,ict_session] [--frames F] [--out DIR]

Sets (lgi/evaluation/benchsets.py), each with clean bundles and with tracking noise (0.3 mm per coordinate, 5 % of
marker-frames missing in runs of 1-6 frames): (a) the synthetic actor's 300-frame held-out performance;
(b) an ICT actor whose jaw rotates about a fitted hinge (200 frames of 1-4 expressions, linear blends);
(c) held-out ICT shapes and mixes involving them (66 independent poses, dataset built without them);
(d) the jaw actor with combination shapes whose correctives grow with the product of their weights
(120 frames); (e) a capture session: the synthetic actor's 47 shapes plus 0, 150 or 400 captured poses (its true
nonlinear face at frames of another performance), tested on a 160-frame held-out performance (``session_N``), and
the frames of (d) against the ICT jaw actor's 57 shapes plus 150 captured frames of another performance of the
same actor, correctives and jaw included (``ict_session``). On the session sets the plain blendshape fit gets the
best of four ridge weights chosen on the truth (which favours it). The ICT sets are skipped, with the reason, when
../shared/data/ict-facekit is absent.

Prints one table per set and bundles kind, then LGI's figures on the session sets per number of scans, and writes
``accuracy.csv`` (long form) into ``--out``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small bounded fits: threaded BLAS is 40x slower here

DEFAULT_SETS = ("synthetic,ict_jaw,ict_heldout,ict_combination,session_0,session_150,session_400,session_0_norig,"
                "session_150_norig,session_400_norig,ict_session")
RIG_FIT = "blendshape fit + rig"
RIG_FIT_SMOOTHED = "blendshape fit + rig, smoothed bundles"


def session_summary(table, sets: dict) -> str:
    """LGI (default) on the session sets as a Markdown table: RMS / p95 / max (mm) per set and bundles kind, the
    RMS ratio to the best baseline and, on noisy bundles, to the per-frame rigged fit and to the rigged fit of the
    smoothed bundles ("-" where a set has no such row)."""
    from lgi.evaluation.accuracy import SESSION_PREFIXES

    lines = ["| set | scans | bundles | RMS | p95 | max | RMS / best baseline | p95 / best baseline | "
             "max / lowest baseline max | RMS / rig fit | RMS / rig fit, smoothed bundles |", "|" + "---|" * 11]
    for name, bs in sets.items():
        if not name.startswith(SESSION_PREFIXES):
            continue
        for kind in ("clean", "noisy"):
            rows = table[(table.set == name) & (table.bundles == kind)].set_index("method")
            if "LGI (default)" not in rows.index:
                continue
            r = rows.loc["LGI (default)"]
            base_max = rows[rows.baseline.astype(bool)].max_mm.min()
            ratios = [f"{r.rms_vs_best_baseline:.2f}", f"{r.p95_vs_best_baseline:.2f}", f"{r.max_mm / base_max:.2f}"]
            for other in (RIG_FIT, RIG_FIT_SMOOTHED):
                ok = kind == "noisy" and other in rows.index
                ratios.append(f"{r.rms_mm / rows.loc[other, 'rms_mm']:.2f}" if ok else "-")
            lines.append(f"| {name} | {len(bs.info['scan_frames'])} | {kind} | {r.rms_mm:.4f} | {r.p95_mm:.4f} | "
                         f"{r.max_mm:.3f} | " + " | ".join(ratios) + " |")
    return "\n".join(lines) if len(lines) > 2 else ""


def main() -> int:
    from lgi.evaluation import benchsets
    from lgi.evaluation.accuracy import accuracy_benchmark

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default=DEFAULT_SETS)
    ap.add_argument("--frames", type=int, default=None, help="first F frames of each set (default: all)")
    ap.add_argument("--out", default="bench-accuracy")
    args = ap.parse_args()
    names = [n for n in args.sets.split(",") if n]
    ict = benchsets.ict_dir_or_none()
    if ict is None:
        dropped = [n for n in names if benchsets.needs_ict(n)]
        if dropped:
            print(f"ICT FaceKit not found (../shared/data/ict-facekit or $LGI_SHARED_DATA): {', '.join(dropped)} "
                  "skipped")
        names = [n for n in names if not benchsets.needs_ict(n)]
    t0 = time.perf_counter()
    sets = benchsets.load_sets(names, ict)
    table, _ = accuracy_benchmark(sets, args.frames, log=lambda s: print(s, flush=True))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "accuracy.csv", index=False, float_format="%.6g")
    summary = session_summary(table, sets)
    if summary:
        print("\nCapture sessions, LGI (default) per number of scans (mm; ratios of RMS, <= 1 means LGI is at least "
              "as accurate):")
        print(summary)
    lgi = table[table.method == "LGI (default)"].set_index(["set", "bundles"])
    print("\nLGI (default) against the best baseline (RMS and p95 ratios; <= 1 means at least as accurate):")
    for (s, b), r in lgi.iterrows():
        print(f"  {s:16s} {b:5s}  RMS x{r.rms_vs_best_baseline:.2f}  p95 x{r.p95_vs_best_baseline:.2f}")
    print(f"({time.perf_counter() - t0:.0f} s; {out.resolve() / 'accuracy.csv'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
