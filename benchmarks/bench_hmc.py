"""Head-mounted cameras on the synthetic actor: calibration, dots to bundles, bundles to meshes, speed.

    python benchmarks/bench_hmc.py [--frames 300] [--work DIR]

1. Synthetic calibration from projected board corners with 0.2 px Gaussian noise (20 views), pinhole and
   fisheye rigs: RMS, focal-length error, baseline error; then from the rendered board images.
2. The whole chain through the `lgi` command line: `lgi synth --hmc` (fisheye, 1280x1024, 0.3 px random
   offset of every painted dot per camera and frame, helmet slip up to 1 deg / 1.5 mm), `lgi calibrate`,
   `lgi track`, `lgi build --jaw-rig`, `lgi reconstruct`; detection rate of the visible dots, label swaps
   (2D observations more than 3 px from their marker's true projection), bundle error against the truth,
   and the reconstructed meshes' error against the true meshes (beside the same reconstruction from the
   true bundles).
3. Speed, 100 dots in two 1280x1024 cameras: detection + tracking + triangulation on decoded images, and
   the same including PNG decoding (median of 3 runs).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from common import lgi


def synthetic_calibration() -> None:
    from lgi.capture.calibration import Board, calibrate_views
    from lgi.synthetic.hmc import board_corner_views, board_poses, hmc_rig

    print("## Calibration from projected corners, 0.2 px noise, 20 views")
    print("| model | RMS stereo px | RMS cameras px | focal error % (max) | baseline error mm | rotation error deg |")
    print("|---|---|---|---|---|---|")
    board = Board.parse("chessboard:9x6:12")
    for model in ("pinhole", "fisheye"):
        rig = hmc_rig(model)
        views = board_corner_views(rig, board, board_poses(rig, board, 20, seed=1), noise_px=0.2, seed=1)
        c = calibrate_views(views, rig.cameras[0].size, model)
        ferr = max(abs(c.K[k][i, i] / rig.cameras[k].K[i, i] - 1) for k in range(2) for i in range(2)) * 100
        R_true, _ = rig.relative()
        ang = np.degrees(np.arccos(np.clip((np.trace(c.R @ R_true.T) - 1) / 2, -1, 1)))
        print(f"| {model} | {c.rms_stereo:.3f} | {c.rms_camera[0]:.3f} / {c.rms_camera[1]:.3f} | {ferr:.3f} | "
              f"{abs(c.baseline_mm - rig.baseline):.3f} | {ang:.4f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args()
    synthetic_calibration()
    work = args.work or Path(tempfile.mkdtemp(prefix="lgi-bench-hmc-"))
    shot = work / "shot"
    t = time.perf_counter()
    if not (shot / "hmc" / "truth.npz").exists():
        lgi("synth", "--out", str(shot), "--frames", str(args.frames), "--hmc", "-q")
    print(f"\nrendered {args.frames} frames in {time.perf_counter() - t:.0f} s ({shot})")
    calib = shot / "calib.json"
    out = lgi("calibrate", str(shot / "hmc" / "calib"), "--board", "chessboard:9x6:12", "--fisheye",
              "--out", str(calib))
    print("## Calibration from the rendered board images (fisheye)\n" + out.splitlines()[0])
    import json

    true = json.loads((shot / "hmc" / "cameras_true.json").read_text())
    got = json.loads(calib.read_text())
    ferr = max(abs(got["cameras"][k]["K"][i][i] / true["cameras"][k]["K"][i][i] - 1)
               for k in range(2) for i in range(2))
    print(f"focal error max {100 * ferr:.3f} %, baseline {got['baseline_mm']:.3f} vs true {true['baseline_mm']:.3f} mm")

    print("\n## lgi track")
    tracked = shot / "tracked.csv"
    print(lgi("track", str(shot / "hmc"), "--calib", str(calib), "--markers", str(shot / "markers.csv"),
              "--out", str(tracked), "--helmet", str(shot / "hmc" / "helmet.csv")))
    import pandas as pd
    from scipy.spatial import cKDTree

    from lgi.capture.bundles import read_bundles
    from lgi.capture.footage import detect_footage

    t2 = np.load(shot / "hmc" / "truth.npz")
    names = list(t2["markers"])
    visible, centers = t2["visible"], t2["centers"]
    _, dots, _ = detect_footage(shot / "hmc")
    dist = np.array([[cKDTree(d.xy).query(centers[f, c])[0] for c, d in enumerate(p)] for f, p in enumerate(dots)])
    det = dist < 2
    print(f"visible dots: {visible.sum()} of {visible.size}; "
          f"detected {100 * (det & visible).sum() / visible.sum():.2f} %; "
          f"detection error RMS {np.sqrt(np.mean(dist[det & visible] ** 2)):.3f} px (includes the 0.3 px paint offset)")
    table = pd.read_parquet(shot / "tracked.tracks.parquet")
    m = np.array([names.index(n) for n in table["marker"]])
    xy = table[["x", "y"]].to_numpy()
    all_true = centers[table["frame"], table["camera"]]
    nearest = np.nanargmin(np.linalg.norm(all_true - xy[:, None], axis=2), axis=1)
    e2 = np.linalg.norm(xy - all_true[np.arange(len(m)), m], axis=1)
    found = np.zeros_like(visible)
    found[table["frame"], table["camera"], m] = True
    print(f"tracked {100 * (found & visible).sum() / visible.sum():.2f} % of visible dots; label swaps (observation "
          f"nearest another marker's true projection): {(nearest != m).sum()} of {len(m)}; 2D error RMS "
          f"{np.sqrt(np.mean(e2**2)):.3f} px, p99 {np.percentile(e2, 99):.2f}, max {e2.max():.2f} px")
    tb, truth = read_bundles(tracked), read_bundles(shot / "bundles.csv")
    idx = [truth.markers.index(n) for n in tb.markers]
    e3 = 10 * np.linalg.norm(tb.positions - truth.positions[:, idx], axis=2)
    ok = np.isfinite(e3)
    print(f"bundles vs truth (head frame): RMS {np.sqrt(np.mean(e3[ok] ** 2)):.3f} mm, "
          f"p95 {np.percentile(e3[ok], 95):.3f}, "
          f"max {e3[ok].max():.3f} mm; {100 * ok.mean():.2f} % of marker-frames triangulated")

    print("\n## Bundles to meshes (lgi build --jaw-rig, lgi reconstruct)")
    lgi("build", str(shot / "dataset"), "--markers", str(shot / "markers.csv"),
        "--jaw-rig", str(shot / "jaw_rig.npz"), "--out", str(shot / "index"), "-q")
    tv = np.load(shot / "truth.npz")["vertices"]
    for label, b in (("true bundles", shot / "bundles.csv"), ("tracked bundles", tracked)):
        rec = shot / f"recon_{label.split()[0]}"
        lgi("reconstruct", str(shot / "index"), "--bundles", str(b), "--out", str(rec), "-q")
        v = np.load(rec / "meshes.npz")["vertices"]
        e = 10 * np.linalg.norm(v - tv, axis=2)
        print(f"{label}: vertex error RMS {np.sqrt(np.mean(e**2)):.3f} mm, p95 {np.percentile(e, 95):.3f}, "
              f"max {e.max():.3f} mm")

    print("\n## Speed: detection + tracking + triangulation, 100+ dots, two 1280x1024 cameras")
    import cv2

    from lgi.capture.camera import StereoRig
    from lgi.capture.dots import detect_dots
    from lgi.capture.tracking import Tracker, thumbnail

    frames = sorted((shot / "hmc" / "cam0").iterdir())
    imgs = [(cv2.imread(str(p), 0), cv2.imread(str(shot / "hmc" / "cam1" / p.name), 0)) for p in frames]
    rig = StereoRig.load(calib)
    mk = pd.read_csv(shot / "markers.csv")
    layout = mk[["x", "y", "z"]].to_numpy() * 10
    from concurrent.futures import ThreadPoolExecutor

    runs, runs_io = [], []
    for _ in range(3):
        t = time.perf_counter()
        with ThreadPoolExecutor(2) as pool:
            d = list(pool.map(detect_dots, [im for p in imgs for im in p]))
        thumbs = np.stack([thumbnail(p[0]) for p in imgs])
        Tracker(rig, layout, mk["name"].tolist()).track([(d[2 * f], d[2 * f + 1]) for f in range(len(imgs))], thumbs)
        runs.append(len(imgs) / (time.perf_counter() - t))
        t = time.perf_counter()
        from lgi.capture.footage import track_footage

        track_footage(shot / "hmc", rig, layout, mk["name"].tolist())
        runs_io.append(len(imgs) / (time.perf_counter() - t))
    print(f"decoded images: {np.median(runs):.1f} frames/s (runs {', '.join(f'{r:.1f}' for r in runs)})")
    print(f"from PNG files, with decoding and head stabilisation: {np.median(runs_io):.1f} frames/s "
          f"(runs {', '.join(f'{r:.1f}' for r in runs_io)})")

    print("\n## A rig flexed by 0.3 deg after calibration (60 frames): without and with the helmet dots")
    flexed = work / "flexed"
    if not (flexed / "hmc" / "truth.npz").exists():
        lgi("synth", "--out", str(flexed), "--frames", "60", "--hmc", "--rig-flex", "0.3", "-q")
    truth = read_bundles(flexed / "bundles.csv")
    for extra in ([], ["--helmet", str(flexed / "hmc" / "helmet.csv")]):
        out = lgi("track", str(flexed / "hmc"), "--calib", str(calib), "--markers", str(flexed / "markers.csv"),
                  "--out", str(flexed / "tracked.csv"), *extra)
        tb = read_bundles(flexed / "tracked.csv")
        idx = [truth.markers.index(n) for n in tb.markers]
        e3 = 10 * np.linalg.norm(tb.positions - truth.positions[:, idx], axis=2)
        print(f"{'with' if extra else 'without'} --helmet: {out.splitlines()[1]}; bundles RMS "
              f"{np.sqrt(np.nanmean(e3**2)):.3f} mm")


if __name__ == "__main__":
    main()
