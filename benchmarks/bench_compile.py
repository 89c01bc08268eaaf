"""The first run after an install: how long numba takes to compile the solver's kernels, per checkout.

Usage::

    python benchmarks/bench_compile.py [--work DIR] [--checkout DIR ...] [--repeat 3] [--doc docs/benchmarks.md]

For each checkout (default: this one) and each kind of shot (exact and noisy bundles), ``--repeat`` whole
processes run ``lgi reconstruct`` on the first 100 frames of ``bench_long.py``'s ICT shot (500 shapes, jaw rig) with
``NUMBA_CACHE_DIR`` set to a new, empty directory: every kernel the run reaches is compiled. numba's compile
events are recorded in the process: the time of each outermost compilation (a kernel with every helper it
compiles on the way) is credited to that kernel. Checkouts alternate run by run (A, B, A, B, ...), so that a
change of the machine's load falls on both; the figures are medians.

Needs ICT FaceKit (``../shared/data/ict-facekit``); prints why and exits 0 without it. ``--work`` keeps the
material (shared with ``bench_long.py``) between runs.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_long import BASE_FRAMES, NOISE_MM
from bench_speed import Records, build_material
from common import ICT_DIR, has_ict, log, write_marked

SHAPES = 500
FRAMES = 100
#: Runs in the child: records numba's compile events around one ``lgi reconstruct``, prints them as JSON.
CHILD = r"""
import json, sys, time
from numba.core import event

starts, depth, spent = [], [0], {}

class Outermost(event.Listener):
    def on_start(self, ev):
        depth[0] += 1
        if depth[0] == 1:
            starts.append(time.perf_counter())

    def on_end(self, ev):
        depth[0] -= 1
        if depth[0] == 0:
            name = ev.data["dispatcher"].py_func.__qualname__
            spent[name] = spent.get(name, 0.0) + time.perf_counter() - starts.pop()

event.register("numba:compile", Outermost())
t0 = time.perf_counter()
from lgi.cli import main
code = main(sys.argv[1:])
print(json.dumps({"code": code, "wall": time.perf_counter() - t0, "compile": spent}))
"""


def one_run(checkout: Path, argv: list[str], scratch: Path) -> dict:
    """One process of ``lgi`` ``argv`` from ``checkout`` with an empty numba cache: its wall time (s), and the
    seconds of each outermost compilation by kernel."""
    cache = Path(tempfile.mkdtemp(prefix="numba-empty-", dir=scratch))
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONPATH": str(checkout)}
    try:
        t0 = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", CHILD, *argv], env=env, capture_output=True, text=True,
                              cwd=scratch)
        wall = time.perf_counter() - t0
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    if done.returncode:
        raise SystemExit(f"{checkout}: lgi {' '.join(argv)} failed:\n{done.stderr[-3000:]}")
    got = json.loads(done.stdout.strip().splitlines()[-1])
    return {"wall": wall, "compile": got["compile"]}


def label(checkout: Path) -> str:
    """A checkout's name and its commit (when it is a git work tree)."""
    done = subprocess.run(["git", "-C", str(checkout), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return f"{checkout.name} ({done.stdout.strip()})" if done.returncode == 0 else checkout.name


def table(results: dict[tuple[str, str], list[dict]], top: int = 3) -> str:
    """Markdown: per checkout and shot, the median process time, the median compile time, and the kernels
    taking most of it."""
    lines = ["| checkout | bundles | process (s) | compiling (s) | of it, the largest trees (s) |",
             "|---|---|---|---|---|"]
    for (name, kind), runs in results.items():
        wall = statistics.median(r["wall"] for r in runs)
        total = statistics.median(sum(r["compile"].values()) for r in runs)
        kernels = sorted({k for r in runs for k in r["compile"]},
                         key=lambda k: -statistics.median(r["compile"].get(k, 0.0) for r in runs))
        largest = ", ".join(f"`{k}` {statistics.median(r['compile'].get(k, 0.0) for r in runs):.1f}"
                            for k in kernels[:top])
        lines.append(f"| {name} | {kind} | {wall:.1f} | {total:.1f} | {largest} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, help="material folder (default: a temporary one, removed at the end)")
    ap.add_argument("--checkout", type=Path, action="append", default=[],
                    help="a source tree to measure (repeat for an A/B pair; default: this one)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--kinds", default="clean,noisy")
    ap.add_argument("--doc", type=Path, action="append", default=[], help="write the table into this file")
    args = ap.parse_args()
    if not has_ict(ICT_DIR):
        print(f"ICT FaceKit not found in {ICT_DIR}: nothing to measure")
        return 0
    checkouts = [c.resolve() for c in args.checkout] or [Path(__file__).resolve().parents[1]]
    kinds = args.kinds.split(",")
    work = args.work or Path(tempfile.mkdtemp(prefix="lgi-bench-compile-"))
    work.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix="compile-", dir=work))
    try:
        # The material of bench_long.py (its first FRAMES frames are run here), so that one --work serves both.
        mat = build_material(work, ICT_DIR, [SHAPES], BASE_FRAMES, FRAMES, kinds, NOISE_MM,
                             Records(work / "records.json"), stereo=True)
        index = mat.indexes[(SHAPES, True)]
        results: dict[tuple[str, str], list[dict]] = {}
        for rep in range(args.repeat):
            for kind in kinds:
                for checkout in checkouts:
                    out = scratch / "recon"
                    argv = ["reconstruct", str(index), "--bundles", str(mat.files[(kind, FRAMES)]), "--out", str(out),
                            "-q"]
                    log(f"{checkout.name}, {kind}, run {rep + 1} of {args.repeat}")
                    results.setdefault((label(checkout), kind), []).append(one_run(checkout, argv, scratch))
                    shutil.rmtree(out, ignore_errors=True)
        load = os.getloadavg()
        text = (f"First run after an install: `lgi reconstruct` of the first {FRAMES} frames of bench_long.py's "
                f"ICT shot (held-out 2-3 shape mixes, not dataset shapes, eased into each other; clean, and "
                f"{NOISE_MM:g} mm stereo noise; {SHAPES} shapes, jaw rig, the jaw estimated) with an empty numba "
                f"cache, median of {args.repeat} whole processes per row, checkouts alternating (1-minute load "
                f"average {load[0]:.2f} at the end; {os.cpu_count()} cores). Compiling: the outermost compilations "
                "numba reported, each kernel with the helpers it compiled.\n\n"
                + table(results))
        print(text)
        for doc in args.doc:
            write_marked(doc, "compile", text)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
