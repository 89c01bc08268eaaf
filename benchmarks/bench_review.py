"""Size, load time and memory of the shot review page (``lgi review``): short shots, and long takes up to 36,000
ICT frames.

    python benchmarks/bench_review.py [--work DIR] [--repeat 3] [--skip-ict] [--doc docs/review.md]
    python benchmarks/bench_review.py --long RECON_DIR --index INDEX_DIR [--frames 1000,36000] [--blocks 128]
                                      [--scratch /tmp/DIR] [--keep] [--doc docs/review.md]
    python benchmarks/bench_review.py --floor PAGE_DIR [--doc docs/review.md]

Default mode, the material built through the ``lgi`` command line in ``--work`` (default: a temporary directory)
and reused when it is already there:

- synthetic: ``lgi synth --vertices 20000 --frames 300`` (the demo's actor), its index with the jaw rig,
  ``lgi reconstruct``, ``lgi review --truth``;
- ICT (from ``../shared/data/ict-facekit`` or ``$LGI_SHARED_DATA``; skipped with the reason when absent):
  ``lgi import ICT --rigid-vertices none``, ``lgi build`` with ``data/markers_ict.csv``, a 1000-frame
  performance (smooth random weights of 3 to 5 ICT shapes at a time, exact bundles of it; the truth kept for the
  distance map), ``lgi reconstruct``, ``lgi review --truth``.

``--long RECON_DIR``: takes of ``--frames`` lengths made from a real reconstruction's frames played forwards and
backwards (ping-pong, so that the take has no jump), written under ``--scratch`` block by block (``NpzWriter``:
36,000 ICT frames are an 11.5 GB ``meshes.npz``; the ``shapes`` and ``weights`` text columns of the diagnostics
are left out, 3.5 GB of the 4.9 GB CSV at that length) and removed afterwards unless ``--keep``. ``--blocks
64,128,256`` writes each page at those block sizes; ``--reuse`` measures the pages a ``--keep`` run left again,
with the current ``viewer.js``, and that run's ``lgi review`` figures.

``--floor PAGE_DIR``: where a far jump's time goes, on a page ``lgi review`` wrote. In the same headless Chromium,
from ``file://``, median of ``JUMPS`` trials each: framing a block page that holds nothing (lgi's own page script,
an empty block: the cost of the iframe itself, the floor of any design that loads files beside a ``file://`` page
without a server), framing each of ``JUMPS`` of the page's block files until their text arrives, ``JSON.parse`` of
that text, and the page's own far jump (block loaded, decoded, drawn). ``--doc`` writes it between
``<!-- table:review-floor -->`` and ``<!-- /table -->``.

Per page: its size on disk (all files; per 1000 frames), ``lgi review``'s wall time and peak resident memory
(its own high-water mark, VmHWM), and in headless Chromium (Debian's ``/usr/bin/chromium`` through Playwright,
SwiftShader WebGL on the CPU, a fresh browser per load) opened from ``file://``: the time until the data scripts
are parsed, the first frame drawn (the overview's frame 0, which is frame 0 itself), the first block decoded and
drawn in full; then ten jumps to random far frames (seeded): the time until the overview's nearest frame is drawn
and until the full frame is (its block loaded, decoded and drawn), median and worst, both ended by ``gl.finish``;
the time per step over 60 consecutive frames of a loaded block; and after the jumps (``gc()`` first) the page's
memory: the JavaScript heap (``performance.memory.usedJSHeapSize``, precise), the renderer process's resident
memory and the GPU process's (SwiftShader's buffers), and the bytes of decoded blocks the page holds. The median of
``--repeat`` page loads. ``--doc FILE`` writes the table between ``<!-- table:review -->`` (default mode) or
``<!-- table:review-long -->`` (``--long``; ``<!-- table:review-blocks -->`` with ``--blocks``) and
``<!-- /table -->`` in FILE, with the machine's load average
before and after: another job running on the machine makes every time longer.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import log, run_process, write_marked  # noqa: E402

#: Random far frames a page jumps to.
JUMPS = 10
#: Consecutive frames stepped through for the time per step.
STEPS = 60
#: Chromium in headless mode, WebGL on the CPU (a headless machine has no GPU), exact heap figures, gc() callable.
CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--enable-precise-memory-info", "--js-flags=--expose-gc"]


def review_run(recon: Path, index: Path, out: Path, *extra: str, block: int | None = None) -> tuple[float, float]:
    """``lgi review`` in a process of its own: (wall seconds, peak resident MiB: its VmHWM, polled every 20 ms).
    ``block``: frames per block file, other than lgi's default."""
    args = [str(recon), "--index", str(index), "--out", str(out), *extra]
    if block is None:
        argv = [sys.executable, "-m", "lgi", "review", *args]
    else:
        code = ("import sys, lgi.jobs.review as j; from lgi.cli import main; "
                f"j.BLOCK = {int(block)}; sys.exit(main(['review', *sys.argv[1:]]))")
        argv = [sys.executable, "-c", code, *args]
    # The peak is the child's own VmHWM, polled: ru_maxrss carries the parent's size over fork and exec (this
    # script holds ICT's dataset when it forks: every lgi review then "peaked" at its 1.4 GB).
    t = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=err, cwd=ROOT)
        peak = 0.0
        while proc.poll() is None:
            with contextlib.suppress(OSError, ValueError, IndexError):  # a process exiting has no VmHWM
                status = Path(f"/proc/{proc.pid}/status").read_text()
                peak = max(peak, int(status.split("VmHWM:")[1].split()[0]) / 1024)
            time.sleep(0.02)
        wall = time.perf_counter() - t
        if proc.returncode != 0:
            err.seek(0)
            raise SystemExit(f"lgi review {recon} failed ({proc.returncode}):\n{err.read().decode(errors='replace')}")
    return wall, peak


def lgi(*args: str) -> None:
    r = run_process([sys.executable, "-m", "lgi", *args])
    if r.returncode != 0:
        raise SystemExit(f"lgi {' '.join(args)} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}")


def synthetic(work: Path) -> tuple[Path, Path, Path, tuple[str, ...]]:
    s = work / "synth"
    if not (s / "rec" / "meshes.npz").is_file():
        lgi("synth", "--out", str(s / "s"), "--vertices", "20000", "--frames", "300", "-q")
        lgi("build", str(s / "s" / "dataset"), "--markers", str(s / "s" / "markers.csv"), "--out", str(s / "idx"),
            "--jaw-rig", str(s / "s" / "jaw_rig.npz"), "-q")
        lgi("reconstruct", str(s / "idx"), "--bundles", str(s / "s" / "bundles.csv"), "--out", str(s / "rec"), "-q")
    return s / "rec", s / "idx", s / "review", ("--truth", str(s / "s" / "truth.npz"))


def ict(work: Path, ict_dir: Path, frames: int = 1000) -> tuple[Path, Path, Path, tuple[str, ...]]:
    from lgi.capture.bundles import Bundles, write_bundles
    from lgi.dataset.markers import read_layout
    from lgi.dataset.shapes import ShapeDataset
    from lgi.io.npz import save_npz

    s = work / "ict"
    if not (s / "rec" / "meshes.npz").is_file():
        if not (s / "ds" / "manifest.json").is_file():
            lgi("import", str(ict_dir), "--out", str(s / "ds"), "--rigid-vertices", "none", "-q")
        if not (s / "idx" / "manifest.json").is_file():
            lgi("build", str(s / "ds"), "--markers", str(ROOT / "data" / "markers_ict.csv"), "--out", str(s / "idx"),
                "-q")
        ds = ShapeDataset.load(s / "ds")
        rng = np.random.default_rng(7)
        # Smooth random weights: each shape rises and falls over 20-60 frames, a few at a time.
        w = np.zeros((frames, ds.n_shapes))
        t = np.arange(frames)
        for _ in range(frames // 8):
            k, c, d = rng.integers(ds.n_shapes), rng.uniform(0, frames), rng.uniform(20, 60)
            w[:, k] += rng.uniform(0.3, 0.8) * np.clip(np.cos(np.clip((t - c) / d, -1, 1) * np.pi / 2), 0, 1)
        w = np.clip(w, 0, 1)
        truth = (ds.neutral[None] + np.tensordot(w, ds.deltas, axes=1)).astype(np.float32)
        layout = read_layout(ROOT / "data" / "markers_ict.csv", ds.triangles)
        pos = np.stack([layout.evaluate(v.astype(np.float64)) for v in truth])
        s.mkdir(parents=True, exist_ok=True)
        write_bundles(s / "bundles.csv", Bundles(frames=t, markers=layout.names, positions=pos))
        save_npz(s / "truth.npz", vertices=truth, frames=t)
        lgi("reconstruct", str(s / "idx"), "--bundles", str(s / "bundles.csv"), "--out", str(s / "rec"),
            "--noise", "0", "-q")
    return s / "rec", s / "idx", s / "review", ("--truth", str(s / "truth.npz"))


# ------------------------------------------------------------------------------------------------ long takes
def ping_pong(n: int, n_src: int) -> np.ndarray:
    """(n,) int: the source frame of each frame of a take played forwards and backwards over ``n_src`` frames."""
    period = max(2 * n_src - 2, 1)
    i = np.arange(n) % period
    return np.where(i < n_src, i, period - i)


def long_take(src: Path, out: Path, frames: int, drop: tuple[str, ...] = ("shapes", "weights")) -> None:
    """A reconstruction of ``frames`` frames in ``out`` from ``src``'s frames in ping-pong (:func:`ping_pong`):
    ``meshes.npz`` written a block at a time, ``diagnostics.csv`` without the ``drop`` columns, ``per_frame.csv``
    and ``run.json``."""
    import pandas as pd

    from lgi.io.npz import NpzWriter, npz_member

    out.mkdir(parents=True, exist_ok=True)
    v = npz_member(src / "meshes.npz", "vertices")
    s = ping_pong(frames, len(v))
    with NpzWriter(out / "meshes.npz") as w:
        w.begin("vertices", (frames, *v.shape[1:]), v.dtype)
        for lo in range(0, frames, 64):
            w.write(v[s[lo:lo + 64]])
        w.end()
        w.add("frames", np.arange(frames, dtype=np.int64))
        for name in ("jaw",):
            try:
                a = np.asarray(npz_member(src / "meshes.npz", name))
            except Exception:  # noqa: BLE001 - a reconstruction without a jaw rig has none
                continue
            w.add(name, a[s])
    d = pd.read_csv(src / "diagnostics.csv", keep_default_na=False, na_values=[""])
    d = d.drop(columns=[c for c in drop if c in d]).sort_values("frame", kind="stable")
    per = d.groupby("frame").size()
    if not (per == per.iloc[0]).all():
        raise SystemExit(f"{src / 'diagnostics.csv'}: frames with different numbers of rows")
    m = int(per.iloc[0])
    for lo in range(0, frames, 1000):
        idx = s[lo:lo + 1000]
        part = d.iloc[(idx[:, None] * m + np.arange(m)).ravel()].copy()
        part["frame"] = np.repeat(np.arange(lo, lo + len(idx)), m)
        part.to_csv(out / "diagnostics.csv", mode="w" if lo == 0 else "a", header=lo == 0, index=False)
    pf = pd.read_csv(src / "per_frame.csv").set_index("frame").loc[s].reset_index(drop=True)
    pf.insert(0, "frame", np.arange(frames))
    pf.to_csv(out / "per_frame.csv", index=False)
    if (src / "run.json").is_file():
        shutil.copy(src / "run.json", out / "run.json")


# ------------------------------------------------------------------------------------------------ the browser
def _tree_rss(tag: str) -> dict[str, float]:
    """Resident MiB of the renderer and GPU processes of the Chromium started with ``tag`` on its command line."""
    import psutil

    out = {"renderer_mib": 0.0, "gpu_mib": 0.0}
    for p in psutil.process_iter(["cmdline"]):
        if tag not in " ".join(p.info["cmdline"] or []):
            continue
        for c in [p, *p.children(recursive=True)]:
            try:
                cmd = " ".join(c.cmdline())
                rss = c.memory_info().rss / 2**20
            except psutil.Error:
                continue
            if "--type=renderer" in cmd:
                out["renderer_mib"] += rss
            elif "--type=gpu-process" in cmd:
                out["gpu_mib"] += rss
        break
    return out


def page_figures(page: Path, repeat: int, seed: int = 0) -> dict[str, float]:
    """Median page figures in headless Chromium (a fresh browser per load): times in ms, memory in MiB."""
    from playwright.sync_api import sync_playwright

    runs = []
    with sync_playwright() as p:
        for _ in range(repeat):
            tag = f"--lgi-bench={uuid.uuid4().hex}"  # finds this browser's processes (Chromium ignores the switch)
            b = p.chromium.launch(executable_path="/usr/bin/chromium", args=[*CHROMIUM_ARGS, tag])
            # The page's policy forbids eval, which Playwright's string predicates use.
            pg = b.new_page(viewport={"width": 1280, "height": 800}, bypass_csp=True)
            pg.goto((page / "index.html").resolve().as_uri())
            pg.wait_for_function("window.lgiReview && (window.lgiReview.idle || window.lgiReview.error)",
                                 timeout=300_000)
            err = pg.evaluate("window.lgiReview.error")
            if err:
                raise RuntimeError(err)
            n = pg.evaluate("window.lgiReview.nFrames")
            block = pg.evaluate("window.lgiReview.block")
            rng = np.random.default_rng(seed)
            jumps = []
            for _ in range(JUMPS):
                # A frame at least 3 blocks from the cursor whose block the page does not hold (it holds blocks
                # ahead of and behind the cursor), where the shot allows.
                here = pg.evaluate("window.lgiReview.frame()")
                held = set(pg.evaluate("window.lgiReview.blocksHeld()"))
                far = [f for f in range(n) if abs(f // block - here // block) > 3 and f // block not in held] \
                    or list(range(n))
                f = int(rng.choice(far))
                jumps.append(pg.evaluate(f"""async () => {{ const api = window.lgiReview, t = performance.now();
                    const p = api.setFrame({f}); api.finish(); const rough = performance.now() - t;
                    const was = api.shown().exact; await p; api.finish();
                    return [rough, performance.now() - t, was]; }}"""))
                pg.wait_for_function("window.lgiReview.idle", timeout=300_000)
            lo = pg.evaluate("window.lgiReview.frame()") // block * block
            steps = min(STEPS, n - lo)
            step = pg.evaluate(f"""() => {{ const api = window.lgiReview, t = performance.now();
                for (let f = {lo}; f < {lo + steps}; f++) {{ api.setFrame(f); api.finish(); }}
                return (performance.now() - t) / {steps}; }}""")
            pg.wait_for_function("window.lgiReview.idle", timeout=300_000)
            pg.evaluate("window.gc && (window.gc(), window.gc())")
            time.sleep(0.5)
            timing = pg.evaluate("window.lgiReview.timing")
            rough = [j[0] for j in jumps]
            # The full frame's time of the jumps whose block was not held (a short shot's page holds most).
            full = [j[1] for j in jumps if not j[2]] or [float("nan")]
            runs.append({**{k: timing[k] for k in ("scripts_ms", "first_frame_ms", "first_block_ms")},
                         "jump_rough_ms": float(np.median(rough)), "jump_rough_max_ms": max(rough),
                         "jump_full_ms": float(np.median(full)), "jump_full_max_ms": float(np.max(full)),
                         "jumps_already_full": sum(bool(j[2]) for j in jumps), "step_ms": step,
                         "heap_mib": pg.evaluate("performance.memory.usedJSHeapSize") / 2**20,
                         "held_mib": pg.evaluate("window.lgiReview.bytesHeld()") / 2**20,
                         "blocks_held": len(pg.evaluate("window.lgiReview.blocksHeld()")), **_tree_rss(tag)})
            pg.close()
            b.close()
    return {k: float(np.median([r[k] for r in runs])) for k in runs[0]}


def page_size(page: Path) -> tuple[float, int]:
    """(MB on disk of every file of the page, frames)."""
    size = sum(p.stat().st_size for p in page.rglob("*") if p.is_file())
    meta = (page / "review_meta.js").read_text()
    return size / 1e6, len(json.loads(meta[meta.index("= {") + 2:].rstrip().rstrip(";"))["frames"])


def _row(name: str, page: Path, wall: float, peak: float, repeat: int) -> dict:
    mb, n_f = page_size(page)
    files = len(list((page / "frames").glob("block_*.html")))
    row = {"page": name, "frames": n_f, "MB": mb, "MB per 1000 frames": mb / n_f * 1000,
           "overview MB": (page / "frames" / "overview.html").stat().st_size / 1e6, "block files": files,
           "lgi review s": wall, "lgi review peak MiB": peak, **page_figures(page, repeat)}
    print(json.dumps(row), flush=True)
    return row


def _load() -> str:
    return f"{os.getloadavg()[0]:.2f}"


def table(rows: list[dict], repeat: int, load0: str, note: str = "") -> str:
    lines = [f"Headless Chromium {_chromium()} (Debian's, through Playwright; WebGL on the CPU with SwiftShader), the "
             f"page opened from `file://`, median of {repeat} loads (a fresh browser each); {os.cpu_count()} cores, "
             f"1-minute load average {load0} before and {_load()} after. Times from the start of the page; a jump "
             f"is to a random frame at least 3 blocks away whose block the page does not hold, median (worst) of "
             f"{JUMPS} (the full frame: of those not in the overview, which are whole at once); memory after the "
             f"jumps.{note}\n",
             "| page | size (per 1000 frames) | overview | `lgi review` (peak RSS) | first frame drawn | first block "
             "drawn | jump: overview drawn | jump: full frame drawn | per frame step | JS heap | renderer RSS | GPU "
             "process RSS |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['page']} | {r['MB']:,.0f} MB ({r['MB per 1000 frames']:.0f} MB), {r['block files']:.0f} blocks | "
            f"{r['overview MB']:.1f} MB | {r['lgi review s']:.0f} s ({r['lgi review peak MiB']:.0f} MiB) | "
            f"{r['first_frame_ms'] / 1e3:.2f} s | {r['first_block_ms'] / 1e3:.2f} s | "
            f"{r['jump_rough_ms']:.0f} ms ({r['jump_rough_max_ms']:.0f}) | "
            f"{r['jump_full_ms']:.0f} ms ({r['jump_full_max_ms']:.0f}) | {r['step_ms']:.1f} ms | "
            f"{r['heap_mib']:.0f} MiB | {r['renderer_mib']:.0f} MiB | {r['gpu_mib']:.0f} MiB |")
    return "\n".join(lines)


def _chromium() -> str:
    import subprocess

    try:
        out = subprocess.run(["/usr/bin/chromium", "--version"], capture_output=True, text=True, timeout=30).stdout
        return out.split()[1]
    except (OSError, IndexError, subprocess.SubprocessError):
        return ""


FLOOR_JS = """async ([files, empty]) => {
    const frame = (url) => new Promise((resolve) => {
        const f = document.createElement("iframe"), t = performance.now();
        f.style.display = "none"; f.src = url;
        const on = (e) => { if (!e.data || typeof e.data.lgiReviewBlock !== "string" || f.contentWindow !== e.source)
            return; window.removeEventListener("message", on, true); e.stopImmediatePropagation(); f.remove();
            resolve([performance.now() - t, e.data.lgiReviewBlock]); };
        window.addEventListener("message", on, true);
        document.body.appendChild(f);
    });
    const out = { empty: [], framed: [], parsed: [], bytes: 0 };
    for (let i = 0; i < files.length; i++) {
        out.empty.push((await frame(empty))[0]);
        const [ms, text] = await frame(files[i]);
        out.framed.push(ms);
        const t = performance.now(); JSON.parse(text); out.parsed.push(performance.now() - t);
        out.bytes = Math.max(out.bytes, text.length);
    }
    return out;
}"""


def floor_figures(page: Path) -> dict[str, float]:
    """Where a far jump's time goes on ``page`` (ms, medians): an empty block page framed, a real block page framed
    until its text arrives, its JSON parsed, and the page's own jump to a full frame (:func:`page_figures`)."""
    from playwright.sync_api import sync_playwright

    from lgi.review.pack import write_block_page

    files = sorted(p for p in page.rglob("*.html") if p.name != "index.html" and "overview" not in p.name)
    rng = np.random.default_rng(0)
    pick = [files[i] for i in rng.choice(len(files), min(JUMPS, len(files)), replace=False)]
    empty = files[0].parent / "floor-empty.html"
    write_block_page(empty, {"block": -1}, "LGI_REVIEW_BLOCKS")
    try:
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
            pg = b.new_page(viewport={"width": 1280, "height": 800}, bypass_csp=True)
            pg.goto((page / "index.html").resolve().as_uri())
            pg.wait_for_function("window.lgiReview && (window.lgiReview.idle || window.lgiReview.error)",
                                 timeout=300_000)
            r = pg.evaluate(FLOOR_JS, [[f.resolve().as_uri() for f in pick], empty.resolve().as_uri()])
            b.close()
    finally:
        empty.unlink()
    jump = page_figures(page, 1)
    return {"empty_ms": float(np.median(r["empty"])), "framed_ms": float(np.median(r["framed"])),
            "parsed_ms": float(np.median(r["parsed"])), "block_mb": r["bytes"] / 1e6,
            "jump_full_ms": jump["jump_full_ms"]}


def floor_table(page: Path, f: dict[str, float], load0: str) -> str:
    return (f"Headless Chromium {_chromium()} from `file://`, {page.name}; median of {JUMPS} trials; 1-minute load "
            f"average {load0} before and {_load()} after.\n\n"
            "| empty block page framed | block page framed (its text arrived) | its JSON parsed | the page's far jump "
            "to a full frame | block text |\n|---|---|---|---|---|\n"
            f"| {f['empty_ms']:.0f} ms | {f['framed_ms']:.0f} ms | {f['parsed_ms']:.0f} ms | "
            f"{f['jump_full_ms']:.0f} ms | {f['block_mb']:.1f} MB |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, help="material folder (default: a temporary one)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--skip-ict", action="store_true")
    ap.add_argument("--long", type=Path, metavar="RECON_DIR", help="long takes looped from this reconstruction")
    ap.add_argument("--index", type=Path, help="with --long: the index it was reconstructed with")
    ap.add_argument("--frames", default="1000,36000", help="with --long: the takes' lengths (default %(default)s)")
    ap.add_argument("--blocks", default="", help="with --long: frames per block file to compare (default: lgi's)")
    ap.add_argument("--scratch", type=Path, help="with --long: where the takes are written (default: a temporary "
                    "folder); check its free space first: 36,000 ICT frames are 12.5 GB")
    ap.add_argument("--keep", action="store_true", help="with --long: keep the takes and pages")
    ap.add_argument("--reuse", action="store_true", help="with --long: measure the pages an earlier --keep run left "
                    "in --scratch again (with this lgi's viewer.js) instead of writing them")
    ap.add_argument("--doc", type=Path, action="append", default=[], help="write the table into this Markdown "
                    "file's markers (repeatable)")
    ap.add_argument("--floor", type=Path, metavar="PAGE_DIR", help="where a far jump's time goes on this page")
    a = ap.parse_args()
    load0 = _load()
    if a.floor:
        text = floor_table(a.floor, floor_figures(a.floor), load0)
        print("\n" + text)
        for doc in a.doc:
            write_marked(doc, "review-floor", text)
        return 0
    if a.long:
        if not a.index:
            ap.error("--long needs --index")
        scratch = a.scratch or Path(tempfile.mkdtemp(prefix="lgi-bench-review-long-"))
        rows = []
        blocks = [int(b) for b in a.blocks.split(",") if b] or [None]
        for n in (int(f) for f in a.frames.split(",")):
            take = scratch / f"take{n}"
            made = not (take / "meshes.npz").is_file()  # a take already there (an earlier --keep) is used as it is
            if made:
                log(f"{n} frames: writing the take in {take}")
                long_take(a.long, take, n)
            for block in blocks:
                page = scratch / f"page{n}-{block or 'default'}"
                record = page.with_suffix(".json")  # lgi review's time and peak, beside the page
                if a.reuse and record.is_file() and (page / "index.html").is_file():
                    log(f"{n} frames: the page in {page}, with this lgi's viewer.js")
                    shutil.copy(ROOT / "lgi" / "review" / "static" / "viewer.js", page / "viewer.js")
                    wall, peak = json.loads(record.read_text())
                else:
                    log(f"{n} frames: lgi review (block {block or 'default'})")
                    wall, peak = review_run(take, a.index, page, block=block)
                    record.write_text(json.dumps([wall, peak]))
                label = f"ICT, {n:,} frames (looped)" + (f", blocks of {block}" if block else "")
                rows.append(_row(label, page, wall, peak, a.repeat))
                if not a.keep:
                    shutil.rmtree(page)
                    record.unlink()
            if made and not a.keep:
                shutil.rmtree(take)
        text = table(rows, a.repeat, load0, " The takes play a real reconstruction's frames forwards and backwards "
                     "(`--long`); their diagnostics lack the `shapes` and `weights` text columns (disk space).")
        print("\n" + text)
        for doc in a.doc:
            write_marked(doc, "review-blocks" if a.blocks else "review-long", text)
        return 0
    from lgi.paths import shared_data

    work = a.work or Path(tempfile.mkdtemp(prefix="lgi-bench-review-"))
    cases = [("synthetic, 300 frames x 20k vertices", *synthetic(work))]
    ict_dir = shared_data("ict-facekit")
    if a.skip_ict:
        print("ICT skipped (--skip-ict)")
    elif not (ict_dir / "generic_neutral_mesh.obj").is_file():
        print(f"ICT skipped: ICT FaceKit not found at {ict_dir} (set LGI_SHARED_DATA)")
    else:
        cases.append(("ICT, 1000 frames x 26,719 vertices", *ict(work, ict_dir)))
    rows = []
    for name, recon, index, page, extra in cases:
        wall, peak = review_run(recon, index, page, *extra)
        rows.append(_row(name, page, wall, peak, a.repeat))
    text = table(rows, a.repeat, load0)
    print("\n" + text)
    for doc in a.doc:
        write_marked(doc, "review", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
