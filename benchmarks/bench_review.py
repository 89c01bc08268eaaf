"""Size and load time of the shot review page (``lgi review``): 300 synthetic frames and 1000 ICT frames.

    python benchmarks/bench_review.py [--work DIR] [--repeat 3] [--skip-ict] [--doc docs/review.md --doc README.md]

1. Material, built through the ``lgi`` command line in ``--work`` (default: a temporary directory) and reused
   when it is already there:
   - synthetic: ``lgi synth --vertices 20000 --frames 300`` (the demo's actor), its index with the jaw rig,
     ``lgi reconstruct``, ``lgi review --truth``;
   - ICT (from ``../shared/data/ict-facekit`` or ``$LGI_SHARED_DATA``; skipped with the reason when absent):
     ``lgi import ICT --rigid-vertices none``, ``lgi build`` with ``data/markers_ict.csv``, a 1000-frame
     performance (smooth random weights of 3 to 5 ICT shapes at a time, exact bundles of it; the truth kept
     for the distance map), ``lgi reconstruct``, ``lgi review --truth``.
2. Per page: its size on disk (all files; per 1000 frames), the time ``lgi review`` took, and in headless
   Chromium (Debian's ``/usr/bin/chromium`` through Playwright, SwiftShader WebGL on the CPU) opened from
   ``file://``: until the data scripts are parsed, the decode of the first block of frames, the first frame
   drawn, every frame decoded (the page is in use meanwhile), and the time per frame to step through 60
   frames (recompute normals, upload, draw): the median of ``--repeat`` page loads.
   ``--doc FILE`` (repeatable) writes the table between ``<!-- table:review -->`` and ``<!-- /table -->`` in
   FILE, with the machine's load average before and after the loads.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import write_marked  # noqa: E402


def lgi(*args: str) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "lgi", *args], check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


def synthetic(work: Path) -> tuple[Path, float]:
    s = work / "synth"
    if not (s / "review" / "index.html").is_file():
        lgi("synth", "--out", str(s / "s"), "--vertices", "20000", "--frames", "300", "-q")
        lgi("build", str(s / "s" / "dataset"), "--markers", str(s / "s" / "markers.csv"), "--out", str(s / "idx"),
            "--jaw-rig", str(s / "s" / "jaw_rig.npz"), "-q")
        lgi("reconstruct", str(s / "idx"), "--bundles", str(s / "s" / "bundles.csv"), "--out", str(s / "rec"), "-q")
    t = lgi("review", str(s / "rec"), "--index", str(s / "idx"), "--truth", str(s / "s" / "truth.npz"), "--out",
            str(s / "review"))
    return s / "review", t


def ict(work: Path, ict_dir: Path, frames: int = 1000) -> tuple[Path, float]:
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
    tr = lgi("review", str(s / "rec"), "--index", str(s / "idx"), "--truth", str(s / "truth.npz"), "--out",
             str(s / "review"))
    return s / "review", tr


def load_times(page: Path, repeat: int) -> dict[str, float]:
    """Median page-load figures (ms) in headless Chromium."""
    from playwright.sync_api import sync_playwright

    runs = []
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium",
                              args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
        for _ in range(repeat):
            pg = b.new_page(viewport={"width": 1280, "height": 800})
            t = time.perf_counter()
            pg.goto(page.resolve().as_uri() if page.suffix else (page / "index.html").resolve().as_uri())
            pg.wait_for_function("window.lgiReview && (window.lgiReview.allLoaded || window.lgiReview.error)",
                                 timeout=300_000)
            wall = (time.perf_counter() - t) * 1000
            err = pg.evaluate("window.lgiReview.error")
            if err:
                raise RuntimeError(err)
            timing = pg.evaluate("window.lgiReview.timing")
            n = min(60, pg.evaluate("window.lgiReview.nFrames"))
            step = pg.evaluate(f"""() => {{ const t = performance.now();
                for (let f = 0; f < {n}; f++) window.lgiReview.setFrame(f);
                return (performance.now() - t) / {n}; }}""")
            runs.append({"wall_ms": wall, **timing, "step_ms": step})
            pg.close()
        b.close()
    return {k: float(np.median([r[k] for r in runs])) for k in runs[0]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, help="material folder (default: a temporary one)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--skip-ict", action="store_true")
    ap.add_argument("--doc", type=Path, action="append", default=[], help="write the table into this Markdown "
                    "file's <!-- table:review --> markers (repeatable)")
    a = ap.parse_args()
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
    load0 = os.getloadavg()[0]
    for name, page, t_review in cases:
        meta = json.loads((page / "review_meta.js").read_text().split("=", 1)[1].rstrip().rstrip(";"))
        size = sum(p.stat().st_size for p in page.iterdir())
        n_f = len(meta["frames"])
        row = {"page": name, "MB": size / 1e6, "MB per 1000 frames": size / 1e6 / n_f * 1000,
               "frames file MB": (page / "review_frames.js").stat().st_size / 1e6,
               "lgi review s": t_review, **load_times(page, a.repeat)}
        rows.append(row)
        print(json.dumps(row, indent=1))
    lines = [f"Headless Chromium (Debian's, through Playwright; WebGL on the CPU with SwiftShader), the page opened "
             f"from `file://`, median of {a.repeat} loads; {os.cpu_count()} cores, 1-minute load average "
             f"{load0:.2f} before the loads and {os.getloadavg()[0]:.2f} after. Times from the start of the page.\n",
             "| page | size | per 1000 frames | `lgi review` | data scripts parsed | first block decoded | "
             "first frame drawn | all frames decoded | per frame step |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['page']} | {r['MB']:.1f} MB | {r['MB per 1000 frames']:.0f} MB | "
                     f"{r['lgi review s']:.1f} s | {r['scripts_ms'] / 1e3:.2f} s | {r['decode_ms'] / 1e3:.2f} s | "
                     f"{r['first_frame_ms'] / 1e3:.2f} s | {r['all_frames_ms'] / 1e3:.2f} s | {r['step_ms']:.1f} ms |")
    table = "\n".join(lines)
    print("\n" + table)
    for doc in a.doc:
        write_marked(doc, "review", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
