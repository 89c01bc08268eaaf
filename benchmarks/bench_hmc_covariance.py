"""Bundle covariances (`lgi track`'s cov_* columns) in `lgi reconstruct`, on synthetic head-mounted-camera shots.

    python benchmarks/bench_hmc_covariance.py [--frames 240] [--shots 0:smooth:0,2:jolts:2] [--vertices N]
                                              [--work DIR] [--doc docs/hmc.md]

Per shot (`ACTOR:SLIP:SEED`): `lgi synth --hmc --actor ACTOR --slip SLIP --seed SEED` (fisheye pair, 1280x1024,
0.3 px paint offset per dot and camera), `lgi calibrate` on its board views, `lgi build --jaw-rig`, and
`lgi track --index` (the head pose solved with the face, as the flows track) with the default `--pixel-noise`.
Then `lgi reconstruct` (defaults otherwise) of:

- **(a) with their covariances**: the tracked bundles as written (`--noise auto`: each marker's median covariance,
  in its principal axes);
- **(b) without them**: the same bundles with the cov_* columns dropped (`--noise auto`: the per-axis noise
  estimated from the shot's trajectories);
- **(a') diagonal only** (an ablation): the covariances with their off-diagonal entries zeroed: each marker's
  own noise per head-frame axis, without its orientation;
- **(a'') one covariance for all** (an ablation): every bundle given the covariances' median per head-frame axis
  (the noise level of (a), the same for every marker);
- **(b') the same at the estimated noise** (a check): every bundle given the diagonal covariance of (b)'s
  estimated per-axis noise, which should reconstruct as (b) does;
- **(c) `--noise 0`**: the same bundles treated as exact;
- **(d) `--method blendshape`**: the rigged bounded blendshape fit of the same bundles;
- the true bundles (`--noise auto`, read as exact), for scale.

Vertex error against the true meshes, mm, over the whole face (RMS / p95 / max). The noise each LGI run used:
run.json's `noise_mm` and, per head-frame axis, the solver's (the same `Shot` the job builds, in this process).
The smoothed bundles (what the frames are fitted to) against the true bundles, RMS mm, across and along each
bundle's rays (its covariance's short and long axes).

The covariances against the truth (second table; the first shot also tracked with the true cameras, unless
`--no-true-cameras`): their median standard deviation along and across the rays; the tracked bundles' error
along / across (RMS, and 1.4826 x the median absolute value); the mean and median squared Mahalanobis distance (3
and 2.37 if calibrated), as tracked and with each marker's mean error over the shot (its bias, which no smoothing
removes) taken off; that bias; the part of the error shared by a frame's markers (the rigid motion that best
carries the frame's tracked bundles onto the true ones: the head pose's error, which no per-bundle covariance
holds), beside the same fit to independent noise drawn from the covariances; per marker, its median covariance's
std per head-frame axis, how it follows the spread of the marker's errors, and its long axis' tilt from z.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
from common import lgi, log, write_marked

TABLE = "hmc_covariance"


def stats(e: np.ndarray) -> str:
    return f"{np.sqrt(np.mean(e**2)):.4f} / {np.percentile(e, 95):.4f} / {e.max():.4f}"


def prepare(shot: Path, frames: int, actor: int, slip: str, seed: int, vertices: int | None) -> None:
    """Synthesise, calibrate, build the index and track one shot (each step skipped when its output exists);
    write the bundle variants next to the tracking."""
    if not (shot / "hmc" / "truth.npz").exists():
        log(f"lgi synth --hmc {shot.name}")
        lgi("synth", "--out", str(shot), "--frames", str(frames), "--hmc", "--slip", slip, "--actor", str(actor),
            "--seed", str(seed), *(["--vertices", str(vertices)] if vertices else []), "-q")
    if not (shot / "calib.json").exists():
        lgi("calibrate", str(shot / "hmc" / "calib"), "--board", "chessboard:9x6:12", "--fisheye", "--out",
            str(shot / "calib.json"))
    if not (shot / "index" / "manifest.json").exists():
        log(f"lgi build {shot.name}")
        lgi("build", str(shot / "dataset"), "--markers", str(shot / "markers.csv"), "--jaw-rig",
            str(shot / "jaw_rig.npz"), "--out", str(shot / "index"), "-q")
    tracked = shot / "tracked.csv"
    if not tracked.exists():
        log(f"lgi track --index {shot.name}")
        out = lgi("track", str(shot / "hmc"), "--calib", str(shot / "calib.json"), "--markers",
                  str(shot / "markers.csv"), "--index", str(shot / "index"), "--out", str(tracked))
        (shot / "track.log").write_text(out)
    df = pd.read_csv(tracked)
    cov = [c for c in df.columns if c.startswith("cov_")]
    df.drop(columns=cov).to_csv(shot / "tracked-nocov.csv", index=False)
    diag = df.copy()
    diag[["cov_xy", "cov_xz", "cov_yz"]] = np.where(diag[["cov_xy", "cov_xz", "cov_yz"]].notna(), 0.0, np.nan)
    diag.to_csv(shot / "tracked-diag.csv", index=False)
    # Every bundle the same diagonal covariance: the median over markers of each marker's median (what the solver
    # reports as its per-axis noise for (a)).
    per_marker = df.groupby("marker")[["cov_xx", "cov_yy", "cov_zz"]].median().median()
    uniform = diag.copy()
    for c in ("cov_xx", "cov_yy", "cov_zz"):
        uniform[c] = np.where(uniform[c].notna(), per_marker[c], np.nan)
    uniform.to_csv(shot / "tracked-uniform.csv", index=False)


def rigid_part(x: np.ndarray, t: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Per frame, the rigid motion that best carries the seen tracked bundles x onto the true ones t (least
    squares): the part of the error x - t that motion explains (NaN where not seen)."""
    out = np.full_like(x, np.nan)
    for f in range(len(x)):
        k = ok[f]
        if k.sum() < 3:
            continue
        a, b = x[f, k], t[f, k]
        ca, cb = a.mean(0), b.mean(0)
        u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
        r = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
        out[f, k] = a - ((a - ca) @ r.T + cb)
    return out


def covariance_figures(shot: Path, tracked: Path) -> dict:
    """A tracking's covariances against its bundles' errors (true bundles), mm (see the module's docstring)."""
    import warnings

    from lgi.capture.bundles import read_bundles

    tb = read_bundles(tracked)
    truth = read_bundles(shot / "bundles.csv", tb.markers)
    x, t, C = tb.positions * 10, truth.positions * 10, tb.covariance * 100
    ok = np.isfinite(x).all(-1) & np.isfinite(t).all(-1)
    err = np.where(ok[..., None], x - t, np.nan)
    c = C[ok]
    w, v = np.linalg.eigh(c)

    def split(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # (N, 3) along / across each bundle's rays
        return np.einsum("ni,ni->n", d, v[:, :, 2]), np.einsum("ni,nik->nk", d, v[:, :, :2])

    def d2(d: np.ndarray) -> np.ndarray:
        return np.einsum("ni,ni->n", d, np.linalg.solve(c, d[..., None])[..., 0])

    rms = lambda a: float(np.sqrt(np.mean(a**2)))  # noqa: E731
    mad = lambda a: float(1.4826 * np.median(np.abs(a)))  # noqa: E731
    along, across = split(err[ok])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # markers never seen
        bias = np.nanmean(err, axis=0)  # each marker's mean error over the shot
        # Each marker's noise per head-frame axis: its median covariance's diagonal, against the robust std of its
        # errors about their median over the shot (its bias left out).
        per_marker = np.nanmedian(C, axis=0)
        pred = np.sqrt(np.diagonal(per_marker, axis1=1, axis2=2))
        meas = 1.4826 * np.nanmedian(np.abs(err - np.nanmedian(err, axis=0)), axis=0)
    seen = np.isfinite(pred).all(1) & np.isfinite(meas).all(1)
    long_axis = np.linalg.eigh(per_marker[seen])[1][:, :, 2]
    b_along, b_across = split(np.broadcast_to(bias, err.shape)[ok])
    marker_along = np.einsum("mi,mi->m", bias[seen], np.linalg.eigh(per_marker[seen])[1][:, :, 2])
    names = np.asarray(tb.markers)[seen]
    order = np.argsort(-np.abs(marker_along))
    worst = [(str(names[i]), float(marker_along[i])) for i in order[:3]]
    # The squared Mahalanobis distance without the two markers of the largest biases.
    rest = ok.copy()
    rest[:, np.flatnonzero(seen)[order[:2]]] = False
    d2_rest = float(np.einsum("ni,ni->n", err[rest], np.linalg.solve(C[rest], err[rest][..., None])[..., 0]).mean())
    # The part of the error a frame's markers share (its rigid motion onto the truth), and the same fit of
    # independent noise drawn from the covariances: what the fit takes of the per-bundle noise alone.
    sh_along, sh_across = split(rigid_part(x, t, ok)[ok])
    L = np.linalg.cholesky(np.where(ok[..., None, None], C, np.eye(3)))
    drawn = t + np.einsum("fmij,fmj->fmi", L, np.random.default_rng(0).normal(size=x.shape))
    null_along, null_across = split(rigid_part(drawn, t, ok)[ok])
    return {"std_along": float(np.median(np.sqrt(w[:, 2]))), "std_across": float(np.median(np.sqrt(w[:, :2]))),
            "err_along": rms(along), "err_across": rms(across), "mad_along": mad(along), "mad_across": mad(across),
            "d2": d2(err[ok]), "d2_unbiased": d2((err - bias)[ok]),
            "shared": (rms(sh_along), rms(sh_across)), "null": (rms(null_along), rms(null_across)),
            "bias": (rms(b_along), rms(b_across)),
            "corr": [float(np.corrcoef(pred[seen, a], meas[seen, a])[0, 1]) for a in range(3)],
            "spread": [np.percentile(pred[seen, a], [10, 90]) for a in range(3)],
            "tilt": float(np.median(np.degrees(np.arccos(np.clip(np.abs(long_axis[:, 2]), 0, 1))))),
            "bias_median": float(np.median(np.abs(marker_along))), "worst": worst, "d2_rest": d2_rest}


def covariance_row(label: str, f: dict) -> str:
    return (f"| {label} | {f['std_along']:.3f} / {f['std_across']:.3f} | {f['err_along']:.3f} / {f['err_across']:.3f}"
            f" | {f['mad_along']:.3f} / {f['mad_across']:.3f} | {f['d2'].mean():.2f} / {np.median(f['d2']):.2f} | "
            f"{f['d2_unbiased'].mean():.2f} / {np.median(f['d2_unbiased']):.2f} | {f['bias'][0]:.3f} / "
            f"{f['bias'][1]:.3f} | {f['shared'][0]:.3f} / {f['shared'][1]:.3f} ({f['null'][0]:.3f} / "
            f"{f['null'][1]:.3f}) | " + " / ".join(f"{lo:.3f}-{hi:.3f}" for lo, hi in f["spread"]) + " | "
            + " / ".join(f"{r:.2f}" for r in f["corr"]) + f" | {f['tilt']:.0f} |")


def solver_noise(shot: Path, bundles: Path) -> tuple[np.ndarray, np.ndarray]:
    """The noise `lgi reconstruct` (defaults) resolves for these bundles, per head-frame axis (mm), and the
    smoothed bundles it fits the frames to against the true bundles: RMS (mm) across and along each bundle's rays
    (the tracked covariance's short and long axes)."""
    from lgi.capture.bundles import read_bundles
    from lgi.jobs.reconstruct.options import ReconstructOptions
    from lgi.jobs.reconstruct.shot import Shot

    s = Shot(shot / "index", bundles, ReconstructOptions())
    names = s.index.marker_names
    truth = read_bundles(shot / "bundles.csv", names).positions
    cov = read_bundles(shot / "tracked.csv", names).covariance
    e = (np.asarray(s.fit_pos) - truth) * 10
    ok = np.isfinite(e).all(-1) & np.isfinite(cov).all((-1, -2))
    _, v = np.linalg.eigh(cov[ok])
    along = np.einsum("ni,ni->n", e[ok], v[:, :, 2])
    across = np.einsum("ni,nik->nk", e[ok], v[:, :, :2])
    return np.asarray(s.noise.axes, float), np.array([np.sqrt(np.mean(across**2)), np.sqrt(np.mean(along**2))])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--shots", default="0:smooth:0,2:jolts:2", help="ACTOR:SLIP:SEED, comma-separated")
    ap.add_argument("--vertices", type=int, default=None, help="lgi synth --vertices (default the actor's own)")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--no-true-cameras", dest="true_cameras", action="store_false",
                    help="do not track the first shot again with the true cameras (a row of the covariance table)")
    ap.add_argument("--doc", type=Path, action="append", default=[],
                    help=f"rewrite the table between <!-- table:{TABLE} --> markers in this Markdown file")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="lgi-bench-hmc-cov-"))
    shots = []
    for spec in args.shots.split(","):
        a, slip, seed = spec.split(":")
        shots.append((int(a), slip, int(seed)))
    rows, cov_rows, bias_lines, track_lines = [], [], [], []
    for k, (actor, slip, seed) in enumerate(shots):
        shot = work / f"actor{actor}-{slip}-s{seed}"
        label = f"actor {actor}, {slip}, seed {seed}"
        prepare(shot, args.frames, actor, slip, seed, args.vertices)
        if (shot / "track.log").exists():
            track_lines += [ln for ln in (shot / "track.log").read_text().splitlines()
                            if ln.startswith("bundle covariance")]
        truth = np.load(shot / "truth.npz")["vertices"]
        solved = {b: solver_noise(shot, shot / b) for b in ("tracked.csv", "tracked-nocov.csv", "tracked-diag.csv",
                                                             "tracked-uniform.csv")}
        # (b'): every bundle the diagonal covariance of the noise estimated without the covariances (cm^2).
        est = pd.read_csv(shot / "tracked-uniform.csv")
        for c, sigma in zip(("cov_xx", "cov_yy", "cov_zz"), solved["tracked-nocov.csv"][0], strict=True):
            est[c] = np.where(est[c].notna(), (sigma / 10) ** 2, np.nan)
        est.to_csv(shot / "tracked-uniform-est.csv", index=False)
        solved["tracked-uniform-est.csv"] = solver_noise(shot, shot / "tracked-uniform-est.csv")
        runs = [("(a) with their covariances", "tracked.csv", []),
                ("(b) without them (noise estimated)", "tracked-nocov.csv", []),
                ("(a') covariances, diagonal only", "tracked-diag.csv", []),
                ("(a'') one covariance for all markers", "tracked-uniform.csv", []),
                ("(b') (a'') at (b)'s estimated noise", "tracked-uniform-est.csv", []),
                ("(c) `--noise 0` (exact)", "tracked.csv", ["--noise", "0"]),
                ("(d) `--method blendshape`", "tracked.csv", ["--method", "blendshape"]),
                ("true bundles", "bundles.csv", [])]
        for name, bundles, extra in runs:
            out = shot / f"rec-{bundles.split('.')[0]}{''.join(extra).replace('-', '')}"
            if not (out / "meshes.npz").exists():
                log(f"lgi reconstruct {shot.name} {name}")
                lgi("reconstruct", str(shot / "index"), "--bundles", str(shot / bundles), "--out", str(out), "-q",
                    *extra)
            e = 10 * np.linalg.norm(np.load(out / "meshes.npz")["vertices"] - truth, axis=2)
            run = json.loads((out / "run.json").read_text())
            noise, smoothed = "-", "-"
            if run["method"] == "blendshape":
                noise = "- (fits the bundles as given)"
            elif extra:
                noise = f"{run['noise_mm']:g} (given)"
            elif bundles.startswith("tracked"):
                axes, sm = solved[bundles]
                how = "estimated" if run["noise_estimated"] else "covariances"
                noise = f"{run['noise_mm']:.3f} ({how}; {axes[0]:.3f} / {axes[1]:.3f} / {axes[2]:.3f})"
                smoothed = f"{sm[0]:.3f} / {sm[1]:.3f}"
            else:
                noise = f"{run['noise_mm']:g} (estimated: exact)"
            rows.append(f"| {label} | {name} | {noise} | {stats(e)} | {smoothed} |")
        fig = covariance_figures(shot, shot / "tracked.csv")
        cov_rows.append(covariance_row(label, fig))
        bias_lines.append(f"{label}: median {fig['bias_median']:.3f} mm; largest "
                          + ", ".join(f"{n} {b:+.3f}" for n, b in fig["worst"])
                          + f" (d^2 mean without the first two markers {fig['d2_rest']:.2f})")
        if k == 0 and args.true_cameras:
            # Is the markers' bias the calibration's? The first shot tracked again with the true cameras.
            true_cam = shot / "tracked-true-cameras.csv"
            if not true_cam.exists():
                log(f"lgi track --index {shot.name} with the true cameras")
                lgi("track", str(shot / "hmc"), "--calib", str(shot / "hmc" / "cameras_true.json"), "--markers",
                    str(shot / "markers.csv"), "--index", str(shot / "index"), "--out", str(true_cam))
            cov_rows.append(covariance_row(f"{label}, tracked with the true cameras",
                                           covariance_figures(shot, true_cam)))
    doc = [f"Frames: {args.frames}-frame synthetic HMC shots (`lgi synth --hmc`, fisheye pair, 1280x1024, 0.3 px "
           "paint offset per dot and camera; actor, helmet slip and performance seed per row), calibrated with "
           "`lgi calibrate`, tracked with `lgi track --index` (head pose solved with the face) and the default "
           "`--pixel-noise` 0.25 px, reconstructed with `lgi reconstruct` defaults (jaw rig). Vertex error against "
           "the true meshes over the whole face, mm. Noise: run.json's `noise_mm` and, per head-frame axis x / y / z, "
           "the solver's (mm). Smoothed bundles: what the frames are fitted to, against the true bundles, RMS mm "
           "across / along each bundle's rays.",
           "",
           "| shot | bundles | noise used, mm | RMS / p95 / max mm | smoothed bundles across / along mm |",
           "|---|---|---|---|---|", *rows,
           "",
           "The tracked bundles' covariances against their errors (true bundles), mm, along / across the rays (each "
           "bundle's covariance's long / short axes): the covariances' median std; the errors' RMS and robust std "
           "(1.4826 x median absolute); the squared Mahalanobis distance, mean / median (3 / 2.37 if calibrated), "
           "as tracked and with each marker's mean error over the shot (its bias) taken off; that bias, RMS over the "
           "markers; the part of the error a frame's markers share (the rigid motion carrying them onto the truth: "
           "the head pose's error), RMS, and in brackets the same fit of independent noise drawn from the "
           "covariances (what it takes of the bundles' own noise). Per marker (its median covariance): its std per "
           "head-frame axis x / y / z (10th-90th percentile over the markers), the correlation over the markers of "
           "that std with the robust std of the marker's errors about their median, and the angle of its long axis "
           "to the head frame's z (median, deg).",
           "",
           "| shot | covariance std | error RMS | robust std | d^2 | d^2, bias off | marker bias | shared by the "
           "frame (independent noise) | markers' std x / y / z | correlation with their errors x / y / z | long "
           "axis to z, deg |",
           "|---|---|---|---|---|---|---|---|---|---|---|", *cov_rows,
           "",
           "Each marker's bias along its rays (its mean error over the shot), median size over the markers and the "
           "largest: "
           + "; ".join(bias_lines) + "."]
    text = "\n".join(doc)
    print(text)
    for line in track_lines:
        print(f"\nlgi track: {line}")
    for d in args.doc:
        write_marked(d, TABLE, text)


if __name__ == "__main__":
    main()
