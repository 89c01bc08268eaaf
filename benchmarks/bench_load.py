"""Jobs on a busy node: the time per frame of ``lgi reconstruct``, ``rig-solve``, ``compare`` and ``track`` on a quiet
machine and beside busy processes, as lgi sets its threads and with every thread count at 1.

    python benchmarks/bench_load.py [--work DIR] [--frames 120] [--repeat 3] [--busy 2] [--doc docs/benchmarks.md]

Material, built once in ``--work`` through the command line: the synthetic actor at 20,000 vertices with a
``--frames`` performance and its head-mounted camera footage (``lgi synth --hmc``), the cameras calibrated from its
board views (``lgi calibrate``), its index with the jaw rig, the shot reconstructed, the actor's rig from
``lgi synth --template``'s template (``lgi rig-generate --correctives auto``), and one scan (the shot's middle frame
as OBJ, mm).

Each job is a whole process; its time per frame is the process's wall time over the frames it handles (one for
``compare``'s single scan), so the start-up is in it, under load as it is quiet. Four conditions: quiet or
``--busy`` CPU-bound Python processes beside it (as a farm node's other work), each with lgi's own thread settings
(``default``) or with ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS`` and ``NUMBA_NUM_THREADS``
all 1 (``all 1``). Medians of ``--repeat`` runs, the four conditions of a job run one after another. The table
gives each, and the ratio of the busy node's default to its ``all 1`` (the target is at most 1.2).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from common import REPO_ROOT, lgi_timed, log, write_marked

ALL_ONE = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}
BUSY = "while True:\n    pass\n"


def build(work: Path, frames: int) -> dict[str, Path]:
    """The material (reused when there)."""
    s = work / "s"
    if not (s / "hmc" / "cam0").is_dir():
        lgi_timed("synth", "--out", str(s), "--vertices", "20000", "--frames", str(frames), "--hmc", "--template",
                  "-q")
    m = {"s": s, "calib": work / "calib.json", "idx": work / "idx", "rec": work / "rec", "rig": work / "rig",
         "scan": work / "scan.obj"}
    if not m["calib"].is_file():
        lgi_timed("calibrate", str(s / "hmc" / "calib"), "--board", "chessboard:9x6:12", "--fisheye", "--out",
                  str(m["calib"]))
    if not m["idx"].is_dir():
        lgi_timed("build", str(s / "dataset"), "--markers", str(s / "markers.csv"), "--jaw-rig",
                  str(s / "jaw_rig.npz"), "--out", str(m["idx"]), "-q")
    if not m["rec"].is_dir():
        lgi_timed("reconstruct", str(m["idx"]), "--bundles", str(s / "bundles.csv"), "--out", str(m["rec"]), "-q")
    if not m["rig"].is_dir():
        lgi_timed("rig-generate", "--template", str(s / "template"), "--index", str(m["idx"]), "--out",
                  str(m["rig"]), "--correctives", "auto", "-q")
    if not m["scan"].is_file():
        from lgi.index.build import LGIIndex
        from lgi.io.obj import write_obj

        a = LGIIndex.load(m["idx"]).arrays
        v = np.load(m["rec"] / "meshes.npz")["vertices"]
        write_obj(m["scan"], np.asarray(v[len(v) // 2]) * 10.0, a["face_vertices"], a["face_offsets"])
    return m


def jobs(m: dict[str, Path], out: Path, frames: int) -> dict[str, tuple[list[str], int]]:
    """Each job's arguments and the frames it handles."""
    s = m["s"]
    return {
        "reconstruct": (["reconstruct", str(m["idx"]), "--bundles", str(s / "bundles.csv"), "--out",
                         str(out / "rec"), "-q"], frames),
        "rig-solve": (["rig-solve", str(m["rec"]), "--rig", str(m["rig"]), "--out", str(out / "rs"), "-q"], frames),
        "compare": (["compare", str(m["rec"]), "--index", str(m["idx"]), "--frame", str(frames // 2), "--scan",
                     str(m["scan"]), "--units", "mm", "--out", str(out / "cmp")], 1),
        "track": (["track", str(s / "hmc"), "--calib", str(m["calib"]), "--markers", str(s / "markers.csv"),
                   "--helmet", str(s / "hmc" / "helmet.csv"), "--out", str(out / "tracked.csv")], frames),
    }


def busy(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(n)]


def measure(argv: list[str], n_frames: int, env: dict[str, str], repeat: int) -> float:
    """Median wall time per frame (ms) of ``lgi ARGV`` over ``repeat`` runs."""
    times = []
    for _ in range(repeat):
        times.append(1000.0 * lgi_timed(*argv, env=env).wall_s / n_frames)
    return float(np.median(times))


def table(rows: list[dict]) -> str:
    lines = ["| job | quiet, default | quiet, all 1 | busy, default | busy, all 1 | busy default / busy all 1 |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['job']} | {r['quiet default']:.1f} | {r['quiet all 1']:.1f} | {r['busy default']:.1f} | "
                     f"{r['busy all 1']:.1f} | {r['busy default'] / r['busy all 1']:.2f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=None, help="material folder, kept and reused (default: temporary)")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--busy", type=int, default=2, help="CPU-bound processes beside the job when busy")
    ap.add_argument("--doc", type=Path, default=None, help="write the table into this file (table:load)")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="lgi-load-"))
    work.mkdir(parents=True, exist_ok=True)
    m = build(work, args.frames)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for job, (argv, n) in jobs(m, Path(tmp), args.frames).items():
            row = {"job": job}
            for load in ("quiet", "busy"):
                hogs = busy(args.busy) if load == "busy" else []
                try:
                    time.sleep(1.0 if hogs else 0.0)
                    for name, extra in (("default", {}), ("all 1", ALL_ONE)):
                        env = {k: v for k, v in os.environ.items() if k not in ALL_ONE}
                        row[f"{load} {name}"] = measure(argv, n, {**env, **extra}, args.repeat)
                        log(f"{job}, {load}, {name}: {row[f'{load} {name}']:.1f} ms per frame")
                finally:
                    for h in hogs:
                        h.kill()
                        h.wait()
            rows.append(row)
    print(f"ms per frame (whole processes, median of {args.repeat}; {os.cpu_count()} CPUs, busy = {args.busy} "
          "CPU-bound processes beside the job):")
    print(table(rows))
    if args.doc:
        write_marked(args.doc if args.doc.is_absolute() else REPO_ROOT / args.doc, "load", table(rows))


if __name__ == "__main__":
    main()
