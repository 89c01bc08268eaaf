"""Head stabilisation on synthetic head-mounted-camera shots: the stable-marker fit, the joint fit of the head
pose with the face, and the exact head pose.

    python benchmarks/bench_stabilise.py [--frames 300] [--actors 0,2] [--slips smooth,jolts] [--work DIR]
                                         [--doc docs/hmc.md]

Per actor and slip, the shot is `lgi synth --hmc --slip SLIP --actor A` (fisheye pair, 1280x1024, 0.3 px paint
offset per dot and camera), `lgi calibrate` on its board images and `lgi build --jaw-rig`. Then `lgi track`
three ways, and `lgi reconstruct` (defaults) from each tracking's bundles:

- **stable markers**: `lgi track` without `--index`: the neutral layout fitted rigidly to the markers that move
  least over the shot;
- **joint**: `lgi track --index INDEX`: the head pose solved with the jaw and the shape weights per frame;
- **exact pose** (an oracle: it uses the truth): the tracked world-frame bundles mapped into the head frame
  with the true head pose (`hmc/truth.npz` and the true cameras); the calibration's error and the markers' own
  tracking noise are left;
- **rigidly aligned to the truth** (an oracle): the tracked bundles moved rigidly onto the true markers per
  frame (least squares), which removes every rigid error, the calibration's included; only the markers' own
  noise is left.

Vertex error against the true meshes, mm (RMS / p95 / max): the whole face and the lip region (|y - mouth| < 1
cm, |x| < mouth half width + 0.5 cm on the neutral). Head-pose error per frame against the true pose (the
rotation angle of R_est^T R_true in deg; how far the markers' centre lands from where the true pose puts it, mm;
`lgi.capture.headpose.pose_error`): median, p95 and max over the shot, and the max over the frames from the
fourth after each jolt on (`jolts` only).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from common import lgi

TABLE = "table:stabilise"


def stats(e: np.ndarray) -> str:
    return f"{np.sqrt(np.mean(e**2)):.4f} / {np.percentile(e, 95):.4f} / {e.max():.4f}"


def prepare(shot: Path, frames: int, actor: int, slip: str) -> None:
    """Synthesise, calibrate and build the index of one shot (each step skipped when its output exists)."""
    if not (shot / "hmc" / "truth.npz").exists():
        lgi("synth", "--out", str(shot), "--frames", str(frames), "--hmc", "--slip", slip, "--actor", str(actor),
            "--seed", str(actor), "-q")
    if not (shot / "calib.json").exists():
        lgi("calibrate", str(shot / "hmc" / "calib"), "--board", "chessboard:9x6:12", "--fisheye", "--out",
            str(shot / "calib.json"))
    if not (shot / "index" / "manifest.json").exists():
        lgi("build", str(shot / "dataset"), "--markers", str(shot / "markers.csv"), "--jaw-rig",
            str(shot / "jaw_rig.npz"), "--out", str(shot / "index"), "-q")


def track(shot: Path, name: str, extra: list[str]) -> Path:
    out = shot / f"{name}.csv"
    if not out.exists():
        lgi("track", str(shot / "hmc"), "--calib", str(shot / "calib.json"), "--markers", str(shot / "markers.csv"),
            "--out", str(out), *extra)
    return out


def true_pose(shot: Path, tracked: Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Head -> calibration frame (camera 0), per frame: R (F, 3, 3), t (F, 3) mm, from the synthetic truth.

    The calibration's camera 0 is not exactly the true one: with ``tracked`` (a tracking's bundles and tracks
    table), the one rigid map from the true camera-0 frame to the calibrated one that best carries the true markers
    onto the tracked ones over the whole shot is fitted and composed in, so that what is left is the head's motion
    alone, as exactly as the shot's calibration allows."""
    from lgi.capture.camera import StereoRig

    doc = json.loads((shot / "hmc" / "cameras_true.json").read_text())
    cam0 = StereoRig.from_calibration(doc["head_frame"]).cameras[0]  # head frame -> camera 0: x_c = R0 x_h + t0
    truth = np.load(shot / "hmc" / "truth.npz")
    Rs, ts = truth["head_rotation"], truth["head_translation"]  # the face as the helmet sees it: Rs x_h + ts
    R = np.einsum("ij,fjk->fik", cam0.R, Rs)
    t = np.einsum("ij,fj->fi", cam0.R, ts) + cam0.t[None]
    if tracked is None:
        return R, t
    import pandas as pd

    X, x_names = world_bundles(tracked)
    true_b = pd.read_csv(shot / "bundles.csv")
    names = sorted(set(true_b.marker))
    H = true_b.pivot(index="frame", columns="marker")
    h = np.stack([H[c][names].to_numpy() for c in ("x", "y", "z")], -1) * 10  # (F, M, 3) mm, head frame
    a = np.einsum("fij,fmj->fmi", R, h) + t[:, None]
    b = X[:, [x_names.index(n) for n in names]]
    ok = np.all(np.isfinite(a), -1) & np.all(np.isfinite(b), -1)
    p, q = a[ok], b[ok]
    cp, cq = p.mean(0), q.mean(0)
    u, _, vt = np.linalg.svd((p - cp).T @ (q - cq))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    Rc = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    tc = cq - Rc @ cp
    return np.einsum("ij,fjk->fik", Rc, R), np.einsum("ij,fj->fi", Rc, t) + tc


def world_bundles(tracked: Path) -> tuple[np.ndarray, list[str]]:
    """A tracking's bundles back in the calibration frame with its own head pose: (F, M, 3) mm and the names."""
    import pandas as pd
    from scipy.spatial.transform import Rotation

    from lgi.capture.footage import HEAD_POSE_COLUMNS

    b = pd.read_csv(tracked)
    names = sorted(set(b.marker))
    P = b.pivot(index="frame", columns="marker")
    x = np.stack([P[c][names].to_numpy() for c in ("x", "y", "z")], -1) * 10
    pose = pd.read_parquet(tracked.with_name(tracked.stem + ".tracks.parquet")).groupby("frame")[
        HEAD_POSE_COLUMNS].first().reindex(P.index).to_numpy()
    R = Rotation.from_quat(pose[:, :4]).as_matrix()
    return np.einsum("fij,fmj->fmi", R, x) + pose[:, None, 4:], names


def oracle_bundles(shot: Path, tracked: Path, out: Path) -> Path:
    """The tracked bundles, back in the calibration frame, then into the head frame with the true pose
    (:func:`true_pose` with the calibration's offset fitted over the shot)."""
    import pandas as pd

    if out.exists():
        return out
    X, names = world_bundles(tracked)
    R, t = true_pose(shot, tracked)
    xh = np.einsum("fmi,fij->fmj", X - t[:, None], R) / 10
    f, m = np.nonzero(np.all(np.isfinite(xh), -1))
    pd.DataFrame({"frame": f, "marker": np.asarray(names)[m], "x": xh[f, m, 0], "y": xh[f, m, 1],
                  "z": xh[f, m, 2]}).to_csv(out, index=False)
    return out


def floor_poses(shot: Path, tracked: Path, calib: Path) -> tuple[np.ndarray, np.ndarray]:
    """The pose a method that knew the face exactly would find: the true head-frame markers fitted rigidly to the
    tracked world-frame ones per frame, each weighted by its triangulation's information (as the joint fit
    weights them). What is left of its error against the true pose is the tracking's and the calibration's."""
    import pandas as pd

    from lgi.capture.camera import StereoRig
    from lgi.capture.headpose import _rotation, _skew, triangulation_information

    X, names = world_bundles(tracked)
    true_b = pd.read_csv(shot / "bundles.csv")
    H = true_b.pivot(index="frame", columns="marker")
    h = np.stack([H[c][names].to_numpy() for c in ("x", "y", "z")], -1) * 10
    info = triangulation_information(X, StereoRig.load(calib).cameras)
    R_all, t_all = true_pose(shot, tracked)
    R, t = R_all.copy(), t_all.copy()
    for f in range(len(X)):
        s = np.all(np.isfinite(X[f]), 1) & np.all(np.isfinite(h[f]), 1)
        S = np.linalg.cholesky(info[f, s]).transpose(0, 2, 1)
        for _ in range(8):  # Gauss-Newton on the world-frame residual R h + t - x, from the true pose
            q = h[f, s] @ R[f].T
            J = np.concatenate([-_skew(q), np.broadcast_to(np.eye(3), (len(q), 3, 3))], axis=2)
            A = np.einsum("mij,mjk->mik", S, J).reshape(-1, 6)
            b = -np.einsum("mij,mj->mi", S, q + t[f] - X[f, s]).ravel()
            step = np.linalg.lstsq(A, b, rcond=None)[0]
            dR = _rotation(step[:3])
            R[f], t[f] = dR @ R[f], dR @ t[f] + step[3:]
    return R, t


def aligned_bundles(shot: Path, tracked: Path, out: Path) -> Path:
    """The tracked bundles moved rigidly onto the true markers per frame (least squares over all markers): every
    rigid error removed, the head pose's and the calibration's, the markers' own noise kept."""
    import pandas as pd

    if out.exists():
        return out
    m = pd.read_csv(tracked).merge(pd.read_csv(shot / "bundles.csv"), on=["frame", "marker"], suffixes=("", "_t"))
    for _, g in m.groupby("frame"):
        p, q = g[["x", "y", "z"]].to_numpy(), g[["x_t", "y_t", "z_t"]].to_numpy()
        cp, cq = p.mean(0), q.mean(0)
        u, _, vt = np.linalg.svd((p - cp).T @ (q - cq))
        d = np.sign(np.linalg.det(vt.T @ u.T))
        r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
        m.loc[g.index, ["x", "y", "z"]] = (p - cp) @ r.T + cq
    m[["frame", "marker", "x", "y", "z"]].to_csv(out, index=False)
    return out


def pose_cells(R: np.ndarray, t: np.ndarray, R_true: np.ndarray, t_true: np.ndarray, centre: np.ndarray,
               jolting: np.ndarray, slip: str) -> str:
    """The table's pose columns: deg and mm (median / p95 / max) and the largest after the jolts."""
    from lgi.capture.headpose import pose_error

    deg, mm = pose_error(R, t, R_true, t_true, centre)
    after = np.zeros(len(deg), bool)
    for f0 in np.flatnonzero(np.diff(np.concatenate([[0], jolting.astype(int)])) == 1):
        end = f0 + int(np.argmin(jolting[f0:])) if not jolting[f0:].all() else len(jolting)
        after[end + 3:] = True  # from the fourth frame after the jolt's last on
    jolt = f"{deg[after].max():.3f} / {mm[after].max():.3f}" if slip == "jolts" and after.any() else "-"
    return (f"{np.median(deg):.3f} / {np.percentile(deg, 95):.3f} / {deg.max():.3f} | "
            f"{np.median(mm):.3f} / {np.percentile(mm, 95):.3f} / {mm.max():.3f} | {jolt}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--actors", default="0,2")
    ap.add_argument("--slips", default="smooth,jolts")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--prepare-only", action="store_true", help="build the shots and their trackings, then stop")
    ap.add_argument("--doc", type=Path, action="append", default=[],
                    help=f"rewrite the table between <!-- {TABLE} --> markers in this Markdown file")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="lgi-bench-stabilise-"))
    shots = [(int(a), s) for a in args.actors.split(",") for s in args.slips.split(",")]
    for actor, slip in shots:
        shot = work / f"actor{actor}-{slip}"
        prepare(shot, args.frames, actor, slip)
        track(shot, "stable", [])
        track(shot, "joint", ["--index", str(shot / "index")])
    if args.prepare_only:
        return
    from lgi.capture.observations import read_head_poses
    from lgi.index.build import LGIIndex
    from lgi.synthetic.actor import MOUTH_HALF_WIDTH, MOUTH_Y

    lines = [f"Frames: {args.frames}-frame synthetic HMC shots (`lgi synth --hmc`, fisheye pair, 0.3 px paint offset "
             "per dot and camera), tracked with `lgi track`, reconstructed with `lgi reconstruct` defaults. Vertex "
             "error against the true meshes, mm (RMS / p95 / max); head-pose error against the true pose, deg and "
             "mm at the markers' centre (median / p95 / max; after jolts: the largest from the fourth frame after "
             "each jolt on).",
             "",
             "| actor | slip | head pose from | whole face | lip region | pose deg | pose mm | after jolts deg / mm |",
             "|---|---|---|---|---|---|---|---|"]
    for actor, slip in shots:
        shot = work / f"actor{actor}-{slip}"
        index = LGIIndex.load(shot / "index")
        neutral = index.arrays["neutral"]
        lips = (np.abs(neutral[:, 1] - MOUTH_Y) < 1.0) & (np.abs(neutral[:, 0]) < MOUTH_HALF_WIDTH + 0.5)
        truth = np.load(shot / "truth.npz")["vertices"]
        jolting = np.load(shot / "hmc" / "truth.npz")["jolting"]
        stable = shot / "stable.csv"
        R_true, t_true = true_pose(shot, stable)
        centre = index.arrays["ptab"][0].mean(0) * 10
        for label, bundles in (("stable markers", stable), ("joint", shot / "joint.csv"),
                               ("exact pose (oracle)", oracle_bundles(shot, stable, shot / "oracle_pose.csv")),
                               ("rigidly aligned to the truth (oracle)",
                                aligned_bundles(shot, stable, shot / "oracle_aligned.csv"))):
            out = shot / f"rec-{label.split()[0]}"
            if not (out / "meshes.npz").exists():
                lgi("reconstruct", str(shot / "index"), "--bundles", str(bundles), "--out", str(out), "-q")
            v = np.load(out / "meshes.npz")["vertices"]
            e = 10 * np.linalg.norm(v - truth, axis=2)
            pose = "- | - | -"
            if "oracle" not in label:
                R, t = read_head_poses(bundles.with_name(bundles.stem + ".tracks.parquet"), np.arange(len(truth)))
                pose = pose_cells(R, t, R_true, t_true, centre, jolting, slip)
            lines.append(f"| {actor} | {slip} | {label} | {stats(e)} | {stats(e[:, lips])} | {pose} |")
        R, t = floor_poses(shot, stable, shot / "calib.json")
        lines.append(f"| {actor} | {slip} | the true face fitted rigidly (pose floor) | - | - | "
                     f"{pose_cells(R, t, R_true, t_true, centre, jolting, slip)} |")
    print("\n".join(lines))
    for doc in args.doc:
        text = doc.read_text()
        a, b = f"<!-- {TABLE} -->", "<!-- /table -->"
        i = text.index(a) + len(a)
        j = text.index(b, i)
        doc.write_text(text[:i] + "\n" + "\n".join(lines) + "\n" + text[j:])


if __name__ == "__main__":
    main()
