"""Post-process constraints on the synthetic HMC shot: markers seen by one camera as rays (LGI 7.4).

    python benchmarks/bench_constraints.py [--frames 300] [--work DIR] [--slip smooth|jolts] [--head-pose joint|stable]

The shot: `lgi synth --hmc --slip SLIP` (fisheye pair, 1280x1024, 0.3 px paint offset per dot and camera),
`lgi calibrate` on its board images, `lgi build --jaw-rig`, `lgi track` (with `--index`: the head pose solved with
the face, unless `--head-pose stable`); then `lgi reconstruct` from the
tracked bundles alone and with `--observations` (the tracks table's one-camera observations as rays), each
with the bundle noise estimated (the default) and with `--noise 0` (exact bundles); and from the true bundles.
Vertex error against the true meshes (mm): the whole face, the lip region (|y - mouth| < 1 cm, |x| < 2.9 cm on
the neutral) and the frames where some marker is seen by one camera only.

Two oracle rows bound what any constraint could give (they use the truth, so no method can reach them): the
tracked bundles with the lip markers replaced by their true positions (carried into the tracked head frame, so the
head-pose error stays), and the tracked bundles rigidly aligned to the true ones per frame (the head-pose error
removed, the markers' own noise kept).

Lip contours: `hmc/lip_contours.csv` (the true inner lip edges each camera sees, `lgi synth --hmc`), exact
and with 1 px Gaussian noise added here (as `lgi synth --contour-noise 1` would), given with `--contours`.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from common import lgi


def stats(e: np.ndarray) -> str:
    return f"{np.sqrt(np.mean(e**2)):.3f} / {np.percentile(e, 95):.3f} / {e.max():.3f}"


def kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation and translation that best map points a onto b, (N, 3) each, least squares."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - r @ ca


def write_oracles(shot: Path, tracked: Path) -> None:
    """Write `oracle_lips_TRACKED.csv` (lip markers true, tracked head frame) and `oracle_pose_TRACKED.csv` (posed
    by truth)."""
    import pandas as pd

    from lgi.synthetic.actor import MOUTH_HALF_WIDTH, MOUTH_Y

    m = pd.read_csv(tracked).merge(pd.read_csv(shot / "bundles.csv"), on=["frame", "marker"],
                                                  suffixes=("", "_t"))
    lip = ((np.abs(m.y_t - MOUTH_Y) < 1.2) & (np.abs(m.x_t) < MOUTH_HALF_WIDTH + 0.6)).to_numpy()
    lips, pose = m.copy(), m.copy()
    for _, g in m.groupby("frame"):
        p, t = g[["x", "y", "z"]].to_numpy(), g[["x_t", "y_t", "z_t"]].to_numpy()
        r, tr = kabsch(p, t)
        k = lip[g.index]
        lips.loc[g.index[k], ["x", "y", "z"]] = ((t - tr) @ r)[k]
        pose.loc[g.index, ["x", "y", "z"]] = p @ r.T + tr
    for name, d in (("lips", lips), ("pose", pose)):
        d[["frame", "marker", "x", "y", "z"]].to_csv(shot / f"oracle_{name}_{tracked.stem}.csv", index=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--slip", choices=["smooth", "jolts"], default="smooth", help="the helmet's slip (lgi synth)")
    ap.add_argument("--head-pose", choices=["joint", "stable"], default="joint",
                    help="track with the head pose solved with the face (lgi track --index; default) or the "
                         "stable-marker fit")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="lgi-bench-constraints-"))
    shot = work / "shot"
    if not (shot / "hmc" / "lip_contours.csv").exists():
        lgi("synth", "--out", str(shot), "--frames", str(args.frames), "--hmc", "--slip", args.slip, "-q")
    calib, tracked = shot / "calib.json", shot / f"tracked-{args.head_pose}.csv"
    if not calib.exists():
        lgi("calibrate", str(shot / "hmc" / "calib"), "--board", "chessboard:9x6:12", "--fisheye", "--out", str(calib))
    if not (shot / "index" / "manifest.json").exists():
        lgi("build", str(shot / "dataset"), "--markers", str(shot / "markers.csv"), "--jaw-rig",
            str(shot / "jaw_rig.npz"), "--out", str(shot / "index"), "-q")
    if not tracked.exists():
        lgi("track", str(shot / "hmc"), "--calib", str(calib), "--markers", str(shot / "markers.csv"),
            "--out", str(tracked), *(["--index", str(shot / "index")] if args.head_pose == "joint" else []))
    from lgi.capture.bundles import read_bundles
    from lgi.capture.observations import read_rays
    from lgi.index.build import LGIIndex
    from lgi.synthetic.actor import MOUTH_HALF_WIDTH, MOUTH_Y

    index = LGIIndex.load(shot / "index")
    tb = read_bundles(tracked, index.marker_names)
    rays = read_rays(tracked.with_name(tracked.stem + ".tracks.parquet"), index.marker_names, tb.frames, tb.seen)
    truth = np.load(shot / "truth.npz")["vertices"]
    neutral = index.arrays["neutral"]
    lips = (np.abs(neutral[:, 1] - MOUTH_Y) < 1.0) & (np.abs(neutral[:, 0]) < MOUTH_HALF_WIDTH + 0.5)
    ray_frames = np.unique(rays.frame)
    true_b = read_bundles(shot / "bundles.csv", index.marker_names)
    off = rays.distance(true_b.positions[rays.frame, rays.marker]) * 10
    print(f"{len(tb.frames)} frames, {len(rays)} one-camera marker observations in {len(ray_frames)} frames; the true "
          f"marker points are {np.median(off):.3f} mm (median, max {off.max():.3f}) from their rays\n")
    print("vertex error against the true meshes, mm: RMS / p95 / max\n")
    print("| bundles | noise | whole face | lip region | frames with one-camera markers | surface to ray, max mm "
          "| lip edges to contours, px (median frame RMS, before -> after) |")
    print("|---|---|---|---|---|---|---|")
    import pandas as pd

    exact = pd.read_csv(shot / "hmc" / "lip_contours.csv")
    noisy = exact.copy()
    rng = np.random.default_rng(1)
    noisy[["x", "y"]] += rng.normal(0.0, 1.0, (len(noisy), 2))
    noisy.to_csv(shot / "lip_contours_1px.csv", index=False)
    obs = ["--observations", tracked.stem + ".tracks.parquet"]
    runs = [("tracked", "auto", []), ("tracked + rays", "auto", obs),
            ("tracked + rays + contours", "auto", [*obs, "--contours", "hmc/lip_contours.csv"]),
            ("tracked + rays + contours 1 px", "auto", [*obs, "--contours", "lip_contours_1px.csv"]),
            ("tracked", "0", []), ("tracked + rays", "0", obs),
            ("tracked + rays + contours", "0", [*obs, "--contours", "hmc/lip_contours.csv"]),
            ("true", "auto", []),
            ("oracle: lip markers exact", "auto", []), ("oracle: head pose exact", "auto", [])]
    write_oracles(shot, tracked)
    sources = {"true": "bundles.csv", "oracle: lip markers exact": f"oracle_lips_{tracked.stem}.csv",
               "oracle: head pose exact": f"oracle_pose_{tracked.stem}.csv"}
    for label, noise, extra in runs:
        out = work / f"rec_{args.head_pose}_{label.replace(' + ', '_').replace(': ', '_').replace(' ', '_')}_{noise}"
        bundles = shot / sources.get(label, tracked.name)
        lgi("reconstruct", str(shot / "index"), "--bundles", str(bundles), "--out", str(out), "--noise", noise,
            "-q", *[str(shot / e) if e.endswith((".parquet", ".csv")) else e for e in extra])
        v = np.load(out / "meshes.npz")["vertices"]
        e = 10 * np.linalg.norm(v - truth, axis=2)
        d = pd.read_csv(out / "diagnostics.csv")
        ray_d = d.loc[d.constraint == "ray", "ray_distance_mm"]
        to_ray = f"{ray_d.max():.2e}" if len(ray_d) else "-"
        px = "-"
        if "contour_px_before" in d:
            per = d.groupby("frame")[["contour_px_before", "contour_px_after"]].first()
            px = f"{per.contour_px_before.median():.3f} -> {per.contour_px_after.median():.3f}"
        print(f"| {label} | {noise} | {stats(e)} | {stats(e[:, lips])} | {stats(e[ray_frames])} | {to_ray} | {px} |")


if __name__ == "__main__":
    main()
