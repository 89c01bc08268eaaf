"""Import time and peak memory of `lgi import` on the ICT FaceKit (target: under 10 s).

    python benchmarks/bench_import.py [--runs 5] [--ict ../shared/data/ict-facekit]

Each run is a fresh process (cold imports of numpy etc. included in "process" time, not in "import");
peak memory is that process's maximum resident set size.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from common import ICT_DIR, has_ict

CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
from lgi.dataset.importing import import_obj_folder
t1 = time.perf_counter()
ds = import_obj_folder(sys.argv[1], rigid_vertices=sys.argv[3], show_progress=False)
ds.save(sys.argv[2])
t2 = time.perf_counter()
print(json.dumps({"import_s": t2 - t1, "startup_s": t1 - t0, "shapes": ds.n_shapes,
                  "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--ict", type=Path, default=ICT_DIR)
    args = ap.parse_args()
    if not has_ict(args.ict):
        print(f"skipped: ICT FaceKit not found at {args.ict}")
        return
    rigid_file = str(args.ict / "vertex_indices.json")
    print(f"lgi import {args.ict} ({args.runs} runs each, fresh process per run)")
    print(f"{'stabilisation':<22}{'median s':>10}{'min s':>8}{'max s':>8}{'peak RSS MiB':>14}")
    for label, rigid in (("ICT rigid vertex set", rigid_file), ("auto rigid vertices", "auto"), ("none", "none")):
        res = []
        with tempfile.TemporaryDirectory() as tmp:
            for i in range(args.runs):
                out = subprocess.run([sys.executable, "-c", CHILD, str(args.ict), f"{tmp}/d{i}", rigid],
                                     capture_output=True, text=True, check=True)
                res.append(json.loads(out.stdout.strip().splitlines()[-1]))
        t = [r["import_s"] for r in res]
        print(f"{label:<22}{statistics.median(t):>10.2f}{min(t):>8.2f}{max(t):>8.2f}"
              f"{statistics.median(r['peak_rss_mib'] for r in res):>14.0f}")
    print(f"shapes imported: {res[0]['shapes']}; python+numpy start-up per process: "
          f"{statistics.median(r['startup_s'] for r in res):.2f} s (not included)")


if __name__ == "__main__":
    main()
