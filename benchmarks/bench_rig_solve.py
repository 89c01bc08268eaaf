"""A reconstructed shot solved onto the actor's rig (``lgi rig-solve``) against the truth.

    python benchmarks/bench_rig_solve.py [--work DIR] [--vertices 20000] [--frames 300] [--actor 1] [--doc docs/rigs.md]

Setup, all through the command line: ``lgi synth --actor 1 --template`` (a 300-frame performance of synthetic
actor 1, its dataset, markers, true jaw rig and truth, and the default actor's template rig on the same mesh: its 13
controls and its combination shapes of the 24 pairs that most differ from the sum of their parts), ``lgi build``
with its jaw rig, the actor's rig with ``lgi rig-generate --correctives auto --usd`` (the template's combinations),
the shot with ``lgi reconstruct``, then
``lgi rig-solve`` with the default smoothing, with ``--smooth 0`` (each frame on its own) and with ``--jaw fixed`` (the
rig's jaw joint held at the reconstruction's jaw instead of fitted with the weights). A second shot adds
0.2 mm of Gaussian noise per coordinate to the bundles (a tracker's jitter) before ``lgi reconstruct`` (its
``--noise auto``): synthetic bundles are exact, so only the noisy shot shows what the temporal term is for.

Figures, over the rig's face region (the vertices some rig shape moves), mm:
- the rig's playback against the reconstruction (what rig-solve fits) and against the truth (the true meshes);
- the curves against the actor's true activations (``truth.npz``): correlation and RMS per control;
- held frames: frames where a control's true activation does not move (its change over frames f-1..f+1 under
  0.001); the RMS of the solved curve's second difference there (chatter);
- fast frames: where the true activation changes by more than 0.03 per frame; the curve's RMS error there and
  the lag (the shift in frames, in [-3, 3], that best aligns the curve with the truth, per control);
- the jaw joint (the index has a jaw rig, so the rig's jaw is a joint): the solved jaw parameters against the true
  ones (``truth.npz`` ``jaw``), correlation and RMS (degrees; the slide in mm), beside the reconstruction's own jaw;
- the solve's time per frame (measured on a shared, loaded 2-core machine).
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def lgi(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "lgi", *args, "-q"], check=True, cwd=ROOT)


def prepare(work: Path, n_vertices: int, frames: int, actor: int) -> None:
    s = work / "synth"
    if not (s / "template").is_dir():
        lgi("synth", "--actor", str(actor), "--frames", str(frames), "--vertices", str(n_vertices), "--template",
            "--out", str(s))
    if not (work / "index").is_dir():
        lgi("build", str(s / "dataset"), "--markers", str(s / "markers.csv"), "--jaw-rig", str(s / "jaw_rig.npz"),
            "--out", str(work / "index"))
    if not (work / "rig").is_dir():
        lgi("rig-generate", "--template", str(s / "template"), "--index", str(work / "index"), "--out",
            str(work / "rig"), "--correctives", "auto", "--usd", str(work / "rig.usda"))
    if not (work / "recon").is_dir():
        lgi("reconstruct", str(work / "index"), "--bundles", str(s / "bundles.csv"), "--out", str(work / "recon"))
    if not (work / "recon_noisy").is_dir():
        add_noise(s / "bundles.csv", work / "bundles_noisy.csv")
        lgi("reconstruct", str(work / "index"), "--bundles", str(work / "bundles_noisy.csv"), "--out",
            str(work / "recon_noisy"))


def stats(e: np.ndarray) -> str:
    return f"{np.sqrt(np.mean(e**2)):.3f} / {np.percentile(e, 95):.3f} / {e.max():.2f}"


def best_shift(curve: np.ndarray, truth: np.ndarray, span: int = 3) -> int:
    """The shift s in [-span, span] minimising the RMS of curve[f + s] - truth[f] (positive: the curve is late)."""
    n = len(curve)
    err = [np.sqrt(np.mean((curve[span + s:n - span + s] - truth[span:n - span]) ** 2)) for s in range(-span, span + 1)]
    return int(np.argmin(err)) - span


SHOTS = (("exact bundles", "recon", ""), ("bundles + 0.2 mm noise", "recon_noisy", "_noisy"))
NOISE_CM = 0.02


def add_noise(src: Path, dst: Path) -> None:
    """The shot's bundles with Gaussian noise of ``NOISE_CM`` per coordinate (a tracker's jitter), seeded."""
    from lgi.capture.bundles import Bundles, read_bundles, write_bundles

    b = read_bundles(src)
    noisy = b.positions + np.random.default_rng(7).normal(0.0, NOISE_CM, b.positions.shape)
    write_bundles(dst, Bundles(b.frames, b.markers, noisy))


def evaluate(work: Path) -> tuple[list[str], dict]:

    from lgi.io.npz import load_npz
    from lgi.jobs.rig_solve import JAW_CURVES, load_rig, playback, read_curves

    rig, _ = load_rig(work / "rig")
    truth = load_npz(work / "synth" / "truth.npz")
    true_jaw = np.asarray(truth["jaw"], np.float64)
    jaw_rows = []
    true_names = [str(c) for c in truth["controls"]]
    acts = truth["activations"][:, [true_names.index(c) for c in rig.controls]].astype(np.float64)
    region = np.flatnonzero(rig.face_region())
    tv = truth["vertices"][:, region]
    rows, info = [], {}
    for shot, recon_name, suffix in SHOTS:
        z = load_npz(work / recon_name / "meshes.npz")
        recon = z["vertices"]
        if rig.jaw is not None:
            jaw_rows.append(jaw_row(shot, "(the reconstruction's jaw)", np.asarray(z["jaw"], np.float64), true_jaw))
        for label, out in (("lgi rig-solve (--smooth 4)", work / f"solved{suffix}"),
                           ("per-frame fit (--smooth 0)", work / f"raw{suffix}"),
                           ("--jaw fixed (--smooth 4)", work / f"fixed{suffix}")):
            c = read_curves(out, rig.controls)
            jaw = read_curves(out, list(JAW_CURVES)) if rig.jaw is not None else np.zeros((len(c), 0))
            if rig.jaw is not None:
                jaw_rows.append(jaw_row(shot, label, jaw, true_jaw))
            play = playback(rig, np.c_[c, jaw], region)
            e_rec = np.linalg.norm(play - recon[:, region], axis=2).ravel() * 10
            e_true = np.linalg.norm(play - tv, axis=2).ravel() * 10
            d2 = np.diff(c, 2, axis=0)
            dt = np.abs(np.diff(acts, axis=0))
            held = (dt[:-1] < 1e-3) & (dt[1:] < 1e-3)  # (F-2, K): frames f-1..f+1 at rest
            fast = dt > 0.03
            corr = [np.corrcoef(c[:, k], acts[:, k])[0, 1] if acts[:, k].std() > 1e-6 else np.nan
                    for k in range(rig.n_controls)]
            rmsk = np.sqrt(np.mean((c - acts) ** 2, axis=0))
            shifts = [best_shift(c[:, k], acts[:, k]) for k in range(rig.n_controls) if acts[:, k].std() > 0.02]
            ms = json.loads((out / "solve.json").read_text())["ms_per_frame"]
            info[(shot, label)] = {"corr": corr, "rms": rmsk}
            rows.append(f"| {shot} | {label} | {stats(e_rec)} | {stats(e_true)} | {np.nanmean(corr):.3f} "
                        f"(min {np.nanmin(corr):.3f}) | {np.sqrt(np.mean(rmsk**2)):.3f} | "
                        f"{np.sqrt(np.mean(d2[held] ** 2)):.4f} | "
                        f"{np.sqrt(np.mean((c[1:] - acts[1:])[fast] ** 2)):.3f} | "
                        f"{np.mean(shifts):+.2f} ({min(shifts)} to {max(shifts)}) | {ms:.0f} |")
        e_recon = np.linalg.norm(recon[:, region] - tv, axis=2).ravel() * 10
        rows.append(f"| {shot} | (the reconstruction itself) | | {stats(e_recon)} | | | | | | |")
    keys = [(SHOTS[0][0], "lgi rig-solve (--smooth 4)"), (SHOTS[1][0], "lgi rig-solve (--smooth 4)"),
            (SHOTS[1][0], "per-frame fit (--smooth 0)")]
    per = ["| control | exact bundles: correlation / RMS | noisy: correlation / RMS | noisy, per-frame fit: "
           "correlation / RMS | true range |", "|---|---|---|---|---|"]
    for k, name in enumerate(rig.controls):
        cells = " | ".join(f"{info[key]['corr'][k]:.3f} / {info[key]['rms'][k]:.3f}" for key in keys)
        per.append(f"| {name} | {cells} | {acts[:, k].min():.2f}-{acts[:, k].max():.2f} |")
    head = ["| shot | curves | playback - reconstruction (RMS / p95 / max mm) | playback - truth "
            "(RMS / p95 / max mm) | correlation with the true activations (mean over controls, min) | "
            "weight RMS error | held frames: RMS of second differences | fast frames: weight RMS error | "
            "lag, frames (mean, range) | ms per frame |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    jaw_head = ["| shot | jaw | open: correlation / RMS deg | yaw: correlation / RMS deg | roll: correlation / RMS deg "
                "| forward slide: correlation / RMS mm |", "|---|---|---|---|---|---|"]
    jaw_part = ["", *jaw_head, *jaw_rows] if jaw_rows else []
    return head + rows + [""] + per + jaw_part, info


def jaw_row(shot: str, label: str, jaw: np.ndarray, truth: np.ndarray) -> str:
    """A row of the jaw table: each parameter (F,) against the truth, correlation and RMS (the slide in mm)."""
    cells = []
    for i, unit in enumerate((1.0, 1.0, 1.0, 10.0)):
        c = np.corrcoef(jaw[:, i], truth[:, i])[0, 1] if truth[:, i].std() > 1e-9 else np.nan
        cells.append(f"{c:.3f} / {np.sqrt(np.mean((jaw[:, i] - truth[:, i]) ** 2)) * unit:.3f}")
    return f"| {shot} | {label} | " + " | ".join(cells) + " |"


def usd_check(work: Path) -> str:
    """UsdSkel's own bake of the noisy shot's animation at four frames against the rig's playback, and
    UsdValidation's errors."""
    from lgi.export.rig_anim import usd_playback, validate_usd
    from lgi.jobs.rig_solve import JAW_CURVES, load_rig, playback, read_curves

    rig, _ = load_rig(work / "rig")
    c = read_curves(work / "solved_noisy", rig.controls)
    if rig.jaw is not None:
        c = np.c_[c, read_curves(work / "solved_noisy", list(JAW_CURVES))]
    # Four frames spread over the shot, and the widest jaw opening.
    frames = sorted({0, len(c) // 3, 2 * len(c) // 3, len(c) - 1,
                     int(np.argmax(c[:, rig.n_controls])) if rig.jaw is not None else 0})
    baked = usd_playback(work / "shot_noisy.usda", frames)
    diff = float(np.abs(baked - playback(rig, c[frames])).max())
    errors = validate_usd(work / "shot_noisy.usda")
    jaw = "" if rig.jaw is None else (f" (the jaw joint open {c[frames, rig.n_controls].min():.1f} to "
                                      f"{c[frames, rig.n_controls].max():.1f} deg there)")
    return (f"USD animation of the noisy shot: UsdSkel.BakeSkinning at frames {frames}{jaw} is {diff:.1e} cm from the "
            f"rig's playback at most; UsdValidation: {len(errors)} errors" + (f" ({errors[:2]})" if errors else ""))


def update_doc(path: Path, lines: list[str]) -> None:
    text = path.read_text()
    body = "\n".join(lines)
    new, n = re.subn(r"<!-- table:rig-solve -->\n.*?<!-- /table -->",
                     lambda _: f"<!-- table:rig-solve -->\n{body}\n<!-- /table -->", text, flags=re.S)
    if n == 0:
        raise SystemExit(f"{path}: no <!-- table:rig-solve --> ... <!-- /table --> markers")
    path.write_text(new)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default=None, help="working folder, reused when it holds the setup (default: temporary)")
    ap.add_argument("--vertices", type=int, default=20000)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--actor", type=int, default=1)
    ap.add_argument("--doc", default=None, help="also write the table into this Markdown file (docs/rigs.md)")
    args = ap.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="bench-rig-solve-"))
    work.mkdir(parents=True, exist_ok=True)
    prepare(work, args.vertices, args.frames, args.actor)
    for _, recon, suffix in SHOTS:
        if not (work / f"solved{suffix}").is_dir():
            lgi("rig-solve", str(work / recon), "--rig", str(work / "rig"), "--out", str(work / f"solved{suffix}"),
                "--usd", str(work / f"shot{suffix}.usda"), "--rig-usd", str(work / "rig.usda"))
        if not (work / f"raw{suffix}").is_dir():
            lgi("rig-solve", str(work / recon), "--rig", str(work / "rig"), "--out", str(work / f"raw{suffix}"),
                "--smooth", "0")
        if not (work / f"fixed{suffix}").is_dir():
            lgi("rig-solve", str(work / recon), "--rig", str(work / "rig"), "--out", str(work / f"fixed{suffix}"),
                "--jaw", "fixed")
    lines, _ = evaluate(work)
    lines += ["", usd_check(work)]
    print("\n".join(lines))
    if args.doc:
        update_doc(Path(args.doc), lines)


if __name__ == "__main__":
    main()
