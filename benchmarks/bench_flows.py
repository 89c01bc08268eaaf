"""The reconstruct job: frames/s of the plain command and of the reconstruct-shot flow with the thread runner and
with Dask (1 and 2 workers); all give the same files.

    python benchmarks/bench_flows.py [--frames 300] [--chunk 60] [--dask 1 2] [--repeat 1]

The synthetic actor (20k vertices, jaw-free index), its performance as the shot (exact bundles). Times are
whole runs after one warm-up run of each: every run prepares the shot again (the flow's tasks share one
prepared shot per process, which is dropped before each run), Prefect and Dask start-up included; the
overhead is the flow run's time beyond the plain run's, as a share of it. The runs alternate, plain then
each flow, so slow spells of the machine fall on all of them.
"""

from __future__ import annotations

import argparse
import filecmp
import functools
import os
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--chunk", type=int, default=60)
    ap.add_argument("--dask", type=int, nargs="*", default=[1, 2], metavar="N",
                    help="Dask LocalCluster sizes to run (none: the thread runner only)")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each schedule (the median is printed)")
    args = ap.parse_args()
    from lgi.cli import main as lgi
    from lgi.orchestration.reconstruct import reconstruct_shot

    with tempfile.TemporaryDirectory() as t:
        t = Path(t)
        lgi(["synth", "--out", str(t / "s"), "--frames", str(args.frames), "-q"])
        lgi(["build", str(t / "s" / "dataset"), "--markers", str(t / "s" / "markers.csv"), "--out", str(t / "idx"),
             "-q"])
        common = dict(index_dir=str(t / "idx"), bundles=str(t / "s" / "bundles.csv"), chunk_size=args.chunk)
        from lgi.jobs.reconstruct import forget_shots, reconstruct

        runs = [("plain (lgi reconstruct, in-process)",
                 lambda out: reconstruct(common["index_dir"], common["bundles"], out)),
                ("flow, thread runner", functools.partial(reconstruct_shot, **common))]
        for n in args.dask:
            runs.append((f"flow, Dask LocalCluster, {n} worker{'s' if n > 1 else ''}",
                         functools.partial(reconstruct_shot, dask_address=f"local:{n}", **common)))
        for k, (_, fn) in enumerate(runs):  # warm-up: imports, numba caches, Dask's first start
            fn(out=str(t / f"warm{k}"))
        times: list[list[float]] = [[] for _ in runs]
        for _ in range(args.repeat):
            for k, (_, fn) in enumerate(runs):
                forget_shots()
                t0 = time.perf_counter()
                fn(out=str(t / f"run{k}"))
                times[k].append(time.perf_counter() - t0)
        same = all(filecmp.cmp(t / "run0" / f, t / f"run{k}" / f, shallow=False)
                   for k in range(1, len(runs)) for f in ("meshes.npz", "diagnostics.csv", "per_frame.csv"))
        print(f"reconstruct job, {args.frames} frames of the synthetic actor, chunks of {args.chunk}, "
              f"medians of {args.repeat} (runs alternating); outputs identical: {same}")
        plain = float(np.median(times[0]))
        for (label, _), ts in zip(runs, times, strict=True):
            dt = float(np.median(ts))
            extra = f"  overhead {100 * (dt - plain) / plain:+.0f} % of the plain run" if ts is not times[0] else ""
            print(f"  {label:<40} {dt:6.1f} s  {args.frames / dt:6.1f} frames/s  "
                  f"(runs {', '.join(f'{x:.1f}' for x in ts)}){extra}")


if __name__ == "__main__":
    main()
