"""Long takes: peak memory, speed and output size of every path and reader against the shot's length, as whole
processes.

    python benchmarks/bench_long.py [--work DIR] [--shapes 500] [--frames 1000,9000,36000] [--kinds clean,noisy]
                                    [--paths plain,flow,dask] [--readers export,review,compare,rig-solve]
                                    [--doc docs/benchmarks.md] [--keep] [--again] [--rows FILE]

1. Test material, built in ``--work`` through the ``lgi`` command line as ``bench_speed.py`` builds it (and
   reused): ICT with ``--shapes`` shapes and the jaw rig, its index with the rig, a continuous 1,000-frame shot
   of held-out shape mixes eased into each other (holds and fast moves), and a copy with 0.1 mm of stereo-like
   noise (``noisy``: 0.1 mm along z, a quarter of it across). A shot of F frames is that shot played forwards
   and backwards until it has F frames ("looped": continuous motion, the same poses again).
2. For every F, kind and path (``plain``: ``lgi reconstruct``; ``flow``: with ``--flow``; ``dask``: with
   ``--flow --dask local:2``): the process's wall time, frames per second and peak resident memory
   (``os.wait4`` of the command's process, which is the largest of it and of the processes it waited for: with
   Dask, its local workers; not their sum), and the size of the output folder.
3. For every F and kind, the readers of the plain path's output, each a whole process: ``lgi export --usd``,
   ``lgi review``, ``lgi compare`` of one scan (the reconstruction's middle frame written as OBJ), and
   ``lgi rig-solve`` onto a rig made once by ``lgi rig-generate``: wall time, peak memory and output size.

Every figure is printed; nothing is asserted. With ``--work`` (or ``--rows FILE``) each measured row is kept in
``long-rows.json`` there (or FILE), with the commit it measured, and not measured again (``--again`` re-measures),
so the table can be filled by several runs of subsets, even on other machines (``docs/bench-long-rows.json``);
the table holds every kept row, and a second table gives, per row, the ratio of peak memory and of frames per
second to the 1,000-frame row. ``--doc FILE`` rewrites the tables between
``<!-- table:long -->`` and ``<!-- /table -->`` in FILE.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
from bench_speed import Records, build_material
from common import ICT_DIR, dir_mib, has_ict, lgi_timed, log, write_marked

NOISE_MM = 0.1
BASE_FRAMES = 1000
# The code a row measured: rows kept from several runs (``--rows``) may come from different commits.
COMMIT = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).parent, capture_output=True,
                        text=True).stdout.strip() or "unknown"


def looped(src: Path, dst: Path, n: int) -> None:
    """A bundles CSV of ``n`` frames: ``src``'s frames played forwards, then backwards, and so on."""
    df = pd.read_csv(src)
    frames = np.sort(df["frame"].unique())
    order = []
    k = 0
    while len(order) < n:
        order.extend(frames if k % 2 == 0 else frames[::-1][1:-1] if len(frames) > 2 else frames)
        k += 1
    groups = {f: g for f, g in df.groupby("frame")}
    parts = [groups[f].assign(frame=i) for i, f in enumerate(order[:n])]
    pd.concat(parts, ignore_index=True).to_csv(dst, index=False, float_format="%.7g")


def size_mib(path: Path) -> float:
    return dir_mib(path) if path.is_dir() else path.stat().st_size / 2**20


def row(what: str, frames: int, kind: str, run, *out: Path) -> dict:
    r = {"what": what, "frames": frames, "kind": kind, "wall_s": run.wall_s, "fps": frames / run.wall_s,
         "peak_mib": run.peak_mib, "out_mib": sum(size_mib(o) for o in out if o.exists()), "commit": COMMIT,
         "launcher": True}
    log(f"{what} {frames} {kind}: {r['wall_s']:.1f} s, {r['fps']:.0f} frames/s, peak {r['peak_mib']:.0f} MiB, "
        f"output {r['out_mib']:.0f} MiB")
    return r


def readers(recon: Path, index: Path, rig_dir: Path, frames: int, kind: str, which: list[str],
            scratch: Path, rows: Rows) -> None:
    from lgi.io.npz import load_meshes
    from lgi.io.obj import write_obj

    if "export" in which and not rows.has("export --usd", frames, kind):
        from lgi.export.clips import usd_clip_dir

        usd = scratch / "shot.usdc"
        # Over 1,000 frames the file is value clips: the layers in NAME.clips/ beside it are the output too.
        rows.add(row("export --usd", frames, kind, lgi_timed("export", str(recon), "--index", str(index), "--usd",
                                                             str(usd), "-q"), usd, usd_clip_dir(usd)))
        usd.unlink()
        shutil.rmtree(usd_clip_dir(usd), ignore_errors=True)
    if "review" in which and not rows.has("review", frames, kind):
        page = scratch / "review"
        rows.add(row("review", frames, kind, lgi_timed("review", str(recon), "--index", str(index), "--out",
                                                       str(page)), page))
        shutil.rmtree(page)
    if "compare" in which and not rows.has("compare (one scan)", frames, kind):
        m = load_meshes(recon / "meshes.npz", ("vertices", "frames"))
        mid = len(m["frames"]) // 2
        from lgi.index.build import LGIIndex

        a = LGIIndex.load(index).arrays
        scan = scratch / "scan.obj"
        write_obj(scan, np.asarray(m["vertices"][mid]) * 10.0, a["face_vertices"], a["face_offsets"])
        cmp_out = scratch / "compare"
        rows.add(row("compare (one scan)", frames, kind,
                     lgi_timed("compare", str(recon), "--index", str(index), "--frame", str(int(m["frames"][mid])),
                               "--scan", str(scan), "--units", "mm", "--out", str(cmp_out)), cmp_out))
    if "rig-solve" in which and not rows.has("rig-solve", frames, kind):
        solved = scratch / "solved"
        rows.add(row("rig-solve", frames, kind, lgi_timed("rig-solve", str(recon), "--rig", str(rig_dir), "--out",
                                                          str(solved), "-q"), solved))


def same_files(a: Path, b: Path) -> list[str]:
    """The files that differ between folders ``a`` and ``b`` (by bytes, or present in one only), run.json's timings
    and paths aside."""
    names = sorted({str(p.relative_to(a)) for p in a.rglob("*") if p.is_file()}
                   | {str(p.relative_to(b)) for p in b.rglob("*") if p.is_file()})
    differ = []
    for n in names:
        x, y = a / n, b / n
        if not (x.is_file() and y.is_file()):
            differ.append(n)
        elif n == "run.json":
            drop = ("seconds", "out", "resumed_from_frame")
            jx, jy = ({k: v for k, v in json.loads(p.read_text()).items() if k not in drop} for p in (x, y))
            if jx != jy:
                differ.append(n)
        elif x.read_bytes() != y.read_bytes():
            differ.append(n)
    return differ


def kill_and_resume(index: Path, bundles: Path, work: Path, path: str, frames: int, kind: str, seed: int) -> dict:
    """``lgi reconstruct`` (``path``: plain or flow) killed (SIGKILL to its whole process group) at a random moment
    of an uninterrupted run's wall time (10 to 90 %), then the same command again: its outputs against the
    uninterrupted run's."""
    import os
    import signal
    import time

    extra = {"plain": [], "flow": ["--flow"]}[path]
    ref, out = work / f"kill-ref-{path}", work / f"kill-out-{path}"
    for d in (ref, out):
        shutil.rmtree(d, ignore_errors=True)
    argv = [sys.executable, "-m", "lgi", "reconstruct", str(index), "--bundles", str(bundles), "-q", *extra]
    whole = lgi_timed(*argv[3:], "--out", str(ref))
    at = float(np.random.default_rng(seed).uniform(0.1, 0.9)) * whole.wall_s
    p = subprocess.Popen([*argv, "--out", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True)
    time.sleep(at)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    # Without -q: the run says where it went on from (the frames written, or the flow's chunks chosen).
    again = lgi_timed(*[a for a in argv[3:] if a != "-q"], "--out", str(out))
    said = again.stdout + again.stderr
    m = re.search(r"resumed a stopped run of the same command: its (\d+) (frames|chunks chosen)", said)
    resumed = ("not resumed" if m is None else f"frame {m.group(1)}" if m.group(2) == "frames"
               else f"{m.group(1)} chunks chosen")
    differ = same_files(ref, out)
    r = {"what": f"kill and resume ({path})", "frames": frames, "kind": kind, "killed_at_s": at,
         "whole_s": whole.wall_s, "again_s": again.wall_s, "resumed_from": resumed, "differ": differ,
         "commit": COMMIT}
    log(f"{path} {frames} {kind}: killed at {at:.0f} s of {whole.wall_s:.0f}; the same command again resumed from "
        f"{resumed} in {again.wall_s:.0f} s; outputs {'identical' if not differ else differ}")
    for d in (ref, out):
        shutil.rmtree(d, ignore_errors=True)
    return r


class Rows:
    """Measured rows, kept in ``path`` (when given) as they come so that an interrupted run loses none."""

    def __init__(self, path: Path | None, again: bool):
        self.path = path
        self.rows: list[dict] = json.loads(path.read_text()) if path is not None and path.is_file() else []
        self.again = again

    def has(self, what: str, frames: int, kind: str) -> bool:
        return not self.again and any(r["what"] == what and r["frames"] == frames and r["kind"] == kind
                                      for r in self.rows)

    def add(self, r: dict) -> None:
        self.rows = [o for o in self.rows if (o["what"], o["frames"], o["kind"]) != (r["what"], r["frames"], r["kind"])]
        self.rows.append(r)
        if self.path is not None:
            self.path.write_text(json.dumps(self.rows, indent=1))


ORDER = ["reconstruct (plain)", "reconstruct (flow)", "reconstruct (dask)", "export --usd", "review",
         "compare (one scan)", "rig-solve"]


def ordered(rows: list[dict]) -> list[dict]:
    return sorted(rows, key=lambda r: (ORDER.index(r["what"]) if r["what"] in ORDER else len(ORDER), r["kind"],
                                       r["frames"]))


def ratios(rows: list[dict]) -> str:
    """Peak memory and frames per second of every row against the same command's 1,000-frame row."""
    base = {(r["what"], r["kind"]): r for r in rows if r["frames"] == BASE_FRAMES}
    lines = [f"Against the same command at {BASE_FRAMES:,} frames (targets: peak at most 1.1x, frames/s at least "
             "0.9x):", "", "| what | bundles | frames | peak ratio | frames/s ratio |", "|---|---|---|---|---|"]
    for r in ordered(rows):
        b = base.get((r["what"], r["kind"]))
        if r["frames"] == BASE_FRAMES or b is None:
            continue
        lines.append(f"| {r['what']} | {r['kind']} | {r['frames']} | {r['peak_mib'] / b['peak_mib']:.2f} | "
                     f"{r['fps'] / b['fps']:.2f} |")
    return "\n".join(lines)


def kill_table(rows: list[dict]) -> str:
    kills = [r for r in rows if r["what"].startswith("kill and resume")]
    if not kills:
        return ""
    lines = ["Killed (SIGKILL to the process group) at a random moment, then the same command again (`--kill`):", "",
             "| what | frames | killed at | uninterrupted run | the run again | went on from | outputs |",
             "|---|---|---|---|---|---|---|"]
    for r in kills:
        lines.append(f"| {r['what']} | {r['frames']} | {r['killed_at_s']:.0f} s | {r['whole_s']:.0f} s | "
                     f"{r['again_s']:.0f} s | {r['resumed_from']} | "
                     f"{'byte-identical' if not r['differ'] else 'differ: ' + ', '.join(r['differ'])} |")
    return "\n".join(lines)


def table(rows: list[dict], shapes: int) -> str:
    lines = [f"ICT with {shapes} shapes and the jaw rig; the 1,000-frame eased shot looped to F frames (clean, and "
             f"{NOISE_MM:g} mm stereo noise); whole processes, one run each. Peak: the largest of the "
             "command's process and the processes it started (Dask's local workers), not their sum.", "",
             "| what | bundles | frames | wall s | frames/s | peak MiB | output MiB |", "|---|---|---|---|---|---|---|"]
    measured = [r for r in rows if "peak_mib" in r]
    for r in ordered(measured):
        # A row measured before commands were started through run_process's launcher: its peak may be the
        # benchmark's own (Linux keeps a forked process's high-water mark across exec).
        mark = "" if r.get("launcher") else " *"
        lines.append(f"| {r['what']} | {r['kind']} | {r['frames']} | {r['wall_s']:.1f} | {r['fps']:.0f} | "
                     f"{r['peak_mib']:.0f}{mark} | {r['out_mib']:.0f} |")
    if any(not r.get("launcher") for r in measured):
        lines += ["", "\\* measured from the benchmark's own process: the peak may be the benchmark's (at most "
                  "what it held then), not the command's."]
    return "\n".join(lines) + "\n\n" + ratios(measured) + ("\n\n" + kill_table(rows) if kill_table(rows) else "")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, help="material folder (default: a temporary one, removed at the end)")
    ap.add_argument("--shapes", type=int, default=500)
    ap.add_argument("--frames", default="1000,9000,36000")
    ap.add_argument("--kinds", default="clean,noisy")
    ap.add_argument("--paths", default="plain,flow,dask")
    ap.add_argument("--readers", default="export,review,compare,rig-solve")
    ap.add_argument("--doc", type=Path, action="append", default=[])
    ap.add_argument("--keep", action="store_true", help="keep the plain path's outputs in --work")
    ap.add_argument("--again", action="store_true", help="measure rows already kept in --work again")
    ap.add_argument("--kill", type=int, metavar="FRAMES", help="instead of the table: kill a run of this many frames "
                    "(clean) at a random moment, plain and with --flow, run it again, and compare the outputs")
    ap.add_argument("--rows", type=Path, help="where measured rows are kept (default: long-rows.json in --work)")
    args = ap.parse_args()
    if not has_ict(ICT_DIR):
        print(f"ICT FaceKit not found in {ICT_DIR}: nothing to measure")
        return 0
    frames = [int(f) for f in args.frames.split(",")]
    kinds = args.kinds.split(",")
    paths = [p for p in args.paths.split(",") if p]
    which = [r for r in args.readers.split(",") if r]
    work = args.work or Path(tempfile.mkdtemp(prefix="lgi-bench-long-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        mat = build_material(work, ICT_DIR, [args.shapes], BASE_FRAMES, 100, kinds, NOISE_MM,
                             Records(work / "records.json"), stereo=True)
        index = mat.indexes[(args.shapes, True)]
        rig_dir = work / "rig-generated"
        if which and "rig-solve" in which and not (rig_dir / "manifest.json").is_file():
            log("lgi rig-generate --template ict --index ...")
            lgi_timed("rig-generate", "--template", str(mat.ict), "--index", str(index), "--out", str(rig_dir), "-q")
        rows = Rows(args.rows or (args.work / "long-rows.json" if args.work else None), args.again)
        if args.kill:
            bundles = work / f"long-clean-{args.kill}.csv"
            if not bundles.is_file():
                looped(mat.files[("clean", mat.frames)], bundles, args.kill)
            for i, path in enumerate(("plain", "flow")):
                if not rows.has(f"kill and resume ({path})", args.kill, "clean"):
                    rows.add(kill_and_resume(index, bundles, work, path, args.kill, "clean", seed=i))
            print(kill_table(rows.rows))
            for doc in args.doc:
                write_marked(doc, "long", table(rows.rows, args.shapes))
            return 0
        reader_rows = {"export": "export --usd", "review": "review", "compare": "compare (one scan)",
                       "rig-solve": "rig-solve"}
        for n in frames:
            for kind in kinds:
                bundles = work / f"long-{kind}-{n}.csv"
                if not bundles.is_file():
                    log(f"{kind}: the shot looped to {n} frames")
                    looped(mat.files[(kind, mat.frames)], bundles, n)
                recon = work / f"out-plain-{kind}-{n}"
                need_readers = [w for w in which if not rows.has(reader_rows[w], n, kind)]
                # plain last, so that its outputs (12 GB at 36,000 frames) are on disk only while the readers run
                for path in sorted(paths, key=lambda q: q == "plain"):
                    out = work / f"out-{path}-{kind}-{n}"
                    if rows.has(f"reconstruct ({path})", n, kind) and not (path == "plain" and need_readers
                                                                             and not out.is_dir()):
                        continue
                    shutil.rmtree(out, ignore_errors=True)
                    extra = {"plain": [], "flow": ["--flow"], "dask": ["--flow", "--dask", "local:2"]}[path]
                    run = lgi_timed("reconstruct", str(index), "--bundles", str(bundles), "--out", str(out), "-q",
                                    *extra)
                    rows.add(row(f"reconstruct ({path})", n, kind, run, out))
                    if path != "plain":
                        shutil.rmtree(out, ignore_errors=True)
                if need_readers and not recon.is_dir():
                    lgi_timed("reconstruct", str(index), "--bundles", str(bundles), "--out", str(recon), "-q")
                if need_readers:
                    scratch = work / f"readers-{kind}-{n}"
                    shutil.rmtree(scratch, ignore_errors=True)
                    scratch.mkdir()
                    readers(recon, index, rig_dir, n, kind, need_readers, scratch, rows)
                    shutil.rmtree(scratch, ignore_errors=True)
                if not args.keep:  # a 36,000-frame ICT take's outputs are 12 GB
                    shutil.rmtree(recon, ignore_errors=True)
        text = table(rows.rows, args.shapes)
        print(text)
        for doc in args.doc:
            write_marked(doc, "long", text)
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
