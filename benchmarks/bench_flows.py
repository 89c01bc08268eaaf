"""The reconstruct job: frames/s of the plain command and of the reconstruct-shot flow with the thread runner and
with Dask (1 and 2 workers); all give the same files.

    python benchmarks/bench_flows.py [--frames 300] [--chunk 60] [--dask 1 2] [--repeat 1]

The synthetic actor (20k vertices, jaw-free index), its performance as the shot. Times are whole flow
runs (the shot prepared once per process, Prefect and Dask start-up included), after one warm-up run;
the overhead is the flow run's time beyond the plain run's, as a share of it.
"""

from __future__ import annotations

import argparse
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
        reconstruct_shot(out=str(t / "warm"), **common)
        runs = [("thread runner", functools.partial(reconstruct_shot))]
        for n in args.dask:
            runs.append((f"Dask LocalCluster, {n} worker{'s' if n > 1 else ''}",
                         functools.partial(reconstruct_shot, dask_address=f"local:{n}")))
        print(f"reconstruct job, {args.frames} frames of the synthetic actor, chunks of {args.chunk}:")
        from lgi.jobs.reconstruct import reconstruct

        def timed(fn) -> float:
            times = []
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                fn()
                times.append(time.perf_counter() - t0)
            return float(np.median(times))

        plain = timed(lambda: reconstruct(common["index_dir"], common["bundles"], str(t / "plain")))
        print(f"  {'plain (lgi reconstruct, in-process)':<36} {plain:6.1f} s  {args.frames / plain:6.1f} frames/s")
        for label, fl in runs:
            dt = timed(lambda fl=fl, label=label: fl(out=str(t / label.replace(" ", "_").replace(",", "")),
                                                      **common))
            print(f"  {'flow, ' + label:<36} {dt:6.1f} s  {args.frames / dt:6.1f} frames/s  "
                  f"overhead {100 * (dt - plain) / plain:+.0f} % of the plain run")


if __name__ == "__main__":
    main()
