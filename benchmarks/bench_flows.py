"""The reconstruct job: frames/s of the plain command and of the reconstruct-shot flow with the thread runner and
with Dask (1 and 2 workers); all give the same files.

    python benchmarks/bench_flows.py [--frames 300] [--chunk 60]

The synthetic actor (20k vertices, jaw-free index), its performance as the shot. Times are whole flow
runs (index loading in every chunk task, Prefect and Dask start-up included), after one warm-up run.
"""

from __future__ import annotations

import argparse
import functools
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--chunk", type=int, default=60)
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
        for n in (1, 2):
            runs.append((f"Dask LocalCluster, {n} worker{'s' if n > 1 else ''}",
                         functools.partial(reconstruct_shot, dask_address=f"local:{n}")))
        print(f"reconstruct job, {args.frames} frames of the synthetic actor, chunks of {args.chunk}:")
        from lgi.jobs.reconstruct import reconstruct

        t0 = time.perf_counter()
        reconstruct(common["index_dir"], common["bundles"], str(t / "plain"))
        dt = time.perf_counter() - t0
        print(f"  {'plain (lgi reconstruct, in-process)':<36} {dt:6.1f} s  {args.frames / dt:6.1f} frames/s")
        for label, fl in runs:
            t0 = time.perf_counter()
            fl(out=str(t / label.replace(" ", "_").replace(",", "")), **common)
            dt = time.perf_counter() - t0
            print(f"  {'flow, ' + label:<36} {dt:6.1f} s  {args.frames / dt:6.1f} frames/s")


if __name__ == "__main__":
    main()
