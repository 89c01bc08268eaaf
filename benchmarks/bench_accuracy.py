"""LGI against the baselines on realistic input, every method on the same frames in one run.

    python benchmarks/bench_accuracy.py [--sets synthetic,ict_jaw,ict_heldout,ict_combination] [--frames F]
                                        [--out DIR]

Sets (lgi/evaluation/benchsets.py), each with clean bundles and with tracking noise (0.3 mm per coordinate, 5 % of
marker-frames missing in runs of 1-6 frames): (a) the synthetic actor's 300-frame held-out performance;
(b) an ICT actor whose jaw rotates about a fitted hinge (200 frames of 1-4 expressions, linear blends);
(c) held-out ICT shapes and mixes involving them (66 independent poses, dataset built without them);
(d) the jaw actor with combination shapes whose correctives grow with the product of their weights
(120 frames). The ICT sets are skipped, with the reason, when ../shared/data/ict-facekit is absent.

Prints one table per set and bundles kind and writes ``accuracy.csv`` (long form) into ``--out``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small bounded fits: threaded BLAS is 40x slower here


def main() -> int:
    from lgi.evaluation import benchsets
    from lgi.evaluation.accuracy import accuracy_benchmark

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default="synthetic,ict_jaw,ict_heldout,ict_combination")
    ap.add_argument("--frames", type=int, default=None, help="first F frames of each set (default: all)")
    ap.add_argument("--out", default="bench-accuracy")
    args = ap.parse_args()
    names = [n for n in args.sets.split(",") if n]
    ict = benchsets.ict_dir_or_none()
    if ict is None:
        dropped = [n for n in names if n.startswith("ict")]
        if dropped:
            print(f"ICT FaceKit not found (../shared/data/ict-facekit or $LGI_SHARED_DATA): {', '.join(dropped)} "
                  "skipped")
        names = [n for n in names if not n.startswith("ict")]
    t0 = time.perf_counter()
    sets = benchsets.load_sets(names, ict)
    table, _ = accuracy_benchmark(sets, args.frames, log=lambda s: print(s, flush=True))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "accuracy.csv", index=False, float_format="%.6g")
    lgi = table[table.method == "LGI (default)"].set_index(["set", "bundles"])
    print("\nLGI (default) against the best baseline (RMS and p95 ratios; <= 1 means at least as accurate):")
    for (s, b), r in lgi.iterrows():
        print(f"  {s:16s} {b:5s}  RMS x{r.rms_vs_best_baseline:.2f}  p95 x{r.p95_vs_best_baseline:.2f}")
    print(f"({time.perf_counter() - t0:.0f} s; {out.resolve() / 'accuracy.csv'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
