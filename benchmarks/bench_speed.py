"""Speed of ``lgi reconstruct`` on a continuous shot, end to end, as whole processes, beside the bounded
blendshape fit of the same frames.

    python benchmarks/bench_speed.py [--work DIR] [--shapes 100,500,2000] [--frames 1000] [--repeat 3]
                                     [--stage-config 500,rig,clean] [--cold] [--cprofile N] [--kinds clean,noisy]
                                     [--given-noise] [--blas-threads N] [--doc docs/benchmarks.md] [--stages-only]

1. Test material, built in ``--work`` (default: a temporary directory, removed at the end) through the
   ``lgi`` command line, and reused when it is already there (a second run with the same ``--work`` only
   times):
   - ``lgi import ICT --out ict --rigid-vertices none`` (ICT FaceKit from ``../shared/data/ict-facekit``
     or ``$LGI_SHARED_DATA``; without it the benchmark says so and exits with status 0);
   - a dataset of N shapes for every N of ``--shapes``: ICT's 57 shapes plus
     ``lgi augment --linear --budget N-57`` (default levels 0.25,0.5,0.75,1 and orders 2,3: 2-3 shape
     linear in-betweens);
   - a jaw rig, ``lgi rig ict --jaw-vertices 19247:21450 --shapes 'jawOpen*'``;
   - an index per dataset with and without the rig, ``lgi build DS --markers data/markers_ict.csv
     [--jaw-rig rig.npz]``: wall time and peak memory of the build process;
   - a continuous shot of F frames (``--frames``): F/10 + 1 key poses, held-out 2-3 shape mixes
     (``lgi augment ict --linear --budget K+margin --seed 9``, the combinations that are also in-betweens of the
     largest dataset dropped, evaluated by ``lgi bundles``), 10 frames apart and eased into each other
     (smoothstep in time: a hold at every key pose, the fastest motion half-way). The bundles are linear in
     the shape weights, so every frame is the bundles of a mix of the dataset's shapes that is not itself in
     the dataset. A copy with Gaussian noise (``--noise-mm``, 0.3 mm per coordinate) is written with pandas
     in the format of ``lgi bundles``; the first S frames (``--short``, 100) of each file are a second shot.
2. ``python -m lgi reconstruct INDEX --bundles FRAMES --out OUT -q`` as whole processes, for the short and
   the long shot, ``--repeat`` times each (interleaved), for every shapes x {no rig, rig} x bundles kind:
   median wall time, cost per extra frame ``(t_F - t_S) / (F - S)``, start-up ``t_S - S x that``, peak
   resident memory of the process (``os.wait4``) and what the process said about the bundles. Beside it, in
   the same run and the same way, the bounded blendshape fit of the same frames (``FIT_CHILD``: the same
   shot preparation, so the noisy copies' smoothed bundles; per frame :class:`~lgi.solve.globalfit.GlobalFit`
   with the jaw, the compiled blend of its weights and the skinning; ``meshes.npz`` written). One untimed
   process first (changed kernels are compiled by the first process that uses them).
3. Per-stage time for one configuration (``--stage-config``): ``lgi.cli.main(["reconstruct", ...])`` in
   one process, once on the short shot (imports, numba cache load) and then, with timers around the
   library calls it makes, on the long shot; ms per frame per stage. ``--cprofile N`` adds a cProfile
   run (top N functions by own time). ``--cold``: the short shot in one process with an empty numba cache
   (``NUMBA_CACHE_DIR`` set to a new directory for that process only): the first run after an install.
4. ``--doc FILE`` (repeatable) rewrites the tables between ``<!-- table:speed -->`` (the configurations) or
   ``<!-- table:stages -->`` (the per-stage breakdown) and ``<!-- /table -->`` in FILE. ``--stages-only`` runs
   the per-stage breakdown (and ``--cold``) without timing the configurations.

The children inherit this process's environment as a user's shell would give it; the thread variables
seen (``OPENBLAS_NUM_THREADS`` etc.) are printed. ``--blas-threads N`` sets ``OPENBLAS_NUM_THREADS`` and
``OMP_NUM_THREADS`` for the children. Every figure is printed; nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from common import (
    ICT_DIR,
    ICT_JAW_VERTICES,
    ICT_MARKERS,
    add_noise,
    combos,
    dir_mib,
    eased_shot,
    escape,
    first_frames,
    has_ict,
    lgi_timed,
    log,
    manifest,
    run_process,
    write_marked,
)
from common import lgi as run_lgi  # python -m lgi ARGS, exits with its output on failure

ICT_SHAPES = 57
MIX_SEED = 9
STEP = 10  # frames from one key pose to the next
MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
# --stereo: the noisy copies' deviation per axis as shares of --noise-mm (x, y across the cameras' rays, z along).
STEREO_AXES = (0.25, 0.25, 1.0)
THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")
KINDS = {
    "clean": "clean",
    "noisy": "{noise} mm Gaussian noise per coordinate",
}

# In-process stage timers: (depth, label, module, qualified name). Functions that are absent (renamed by
# later work on the solver) are reported as such; children are timed inside their parents.
STAGES = [
    (0, "index load (LGIIndex.load)", "lgi.index.build", "LGIIndex.load"),
    (0, "read bundles (read_bundles)", "lgi.capture.bundles", "read_bundles"),
    (0, "solver set-up (LGISolver.__init__)", "lgi.solve.solver", "LGISolver.__init__"),
    (0, "prepare_shot (align, noise estimate, gaps)", "lgi.solve.solver", "LGISolver.prepare_shot"),
    (1, "model fit (each frame's fit and its leverage)", "lgi.solve.solver", "LGISolver.model_fit"),
    (0, "denoise (trajectory smoothing)", "lgi.solve.solver", "LGISolver.denoise"),
    (0, "solve (Shot.run -> LGISolver.solve_prepared)", "lgi.solve.solver", "LGISolver.solve_prepared"),
    (1, "select_sequence (without smoothing: on a second thread)", "lgi.solve.solver", "LGISolver.select_sequence"),
    (2, "select_frame", "lgi.solve.solver", "LGISolver.select_frame"),
    (3, "global fit (GlobalFit.solve)", "lgi.solve.globalfit", "GlobalFit.solve"),
    (3, "select (simplex search)", "lgi.solve.solver", "LGISolver.select"),
    (4, "solve_bundles", "lgi.solve.selection", "solve_bundles"),
    (4, "solve_bundles_serial", "lgi.solve.selection", "solve_bundles_serial"),
    (4, "agreement", "lgi.solve.selection", "agreement"),
    (3, "_local (local refits)", "lgi.solve.solver", "LGISolver._local"),
    (4, "local_fits", "lgi.solve.selection", "local_fits"),
    (4, "local_fits_serial", "lgi.solve.selection", "local_fits_serial"),
    (4, "weight_misfits", "lgi.solve.selection", "weight_misfits"),
    (3, "far_shares (far field)", "lgi.solve.solver", "LGISolver.far_shares"),
    (1, "finish_sequence (smoothing; exact shots)", "lgi.solve.solver", "LGISolver.finish_sequence"),
    (1, "blend, skin, correct a frame (_Finisher.frame)", "lgi.solve.finish", "_Finisher.frame"),
    (2, "surface (blend, skin)", "lgi.solve.solver", "LGISolver.surface"),
    (3, "blend", "lgi.solve.surface", "blend"),
    (3, "blend_uniform", "lgi.solve.surface", "blend_uniform"),
    (3, "blend_on_base", "lgi.solve.surface", "blend_on_base"),
    (2, "correct (residual correction)", "lgi.solve.solver", "LGISolver.correct"),
    (3, "add_correction", "lgi.solve.surface", "add_correction"),
    (3, "add_correction_serial", "lgi.solve.surface", "add_correction_serial"),
    (1, "diagnostics table (_diagnostics)", "lgi.solve.solver", "LGISolver._diagnostics"),
    (0, "write outputs (write_reconstruction)", "lgi.jobs.reconstruct.run", "write_reconstruction"),
    (1, "meshes.npz (save_npz)", "lgi.io.npz", "save_npz"),
    (1, "diagnostics.csv (write_csv)", "lgi.io.csvio", "write_csv"),
    (1, "per_frame.csv (per_frame_table)", "lgi.jobs.reconstruct.outputs", "per_frame_table"),
]

STAGE_CHILD = r"""
import cProfile, importlib, io, json, pstats, shutil, sys, time
cfg = json.loads(sys.argv[1])
t0 = time.perf_counter()
import lgi.cli
t_import = time.perf_counter() - t0


def reconstruct(bundles, out):
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    rc = lgi.cli.main(["reconstruct", cfg["index"], "--bundles", bundles, "--out", out, "-q", *cfg["extra"]])
    dt = time.perf_counter() - t
    shutil.rmtree(out, ignore_errors=True)
    if rc != 0:
        sys.exit(rc)
    return dt


first = reconstruct(cfg["warm"], cfg["out"])  # imports of the solver's modules, numba cache load or compile
timers, found = {}, {}


def wrap(key, mod, qual):
    obj = importlib.import_module(mod)
    *owners, attr = qual.split(".")
    for o in owners:
        obj = getattr(obj, o, None)
    raw = (obj.__dict__.get(attr) if isinstance(obj, type) else None) or getattr(obj, attr, None)
    if raw is None:
        return False
    kind = type(raw) if isinstance(raw, (classmethod, staticmethod)) else None
    fn = raw.__func__ if kind else raw
    acc = timers.setdefault(key, [0.0, 0])

    def timed(*a, **k):
        t = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            acc[0] += time.perf_counter() - t
            acc[1] += 1

    setattr(obj, attr, kind(timed) if kind else timed)
    return True


for _, label, mod, qual in cfg["stages"]:
    found[label] = wrap(label, mod, qual)
total = reconstruct(cfg["bundles"], cfg["out"])
timers = {k: list(v) for k, v in timers.items()}  # the cProfile run below must not add to them
profile = ""
if cfg["cprofile"]:
    prof = cProfile.Profile()
    prof.enable()
    reconstruct(cfg["bundles"], cfg["out"])
    prof.disable()
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(cfg["cprofile"])
    profile = s.getvalue()
print(json.dumps({"import_s": t_import, "first_s": first, "total_s": total, "timers": timers, "found": found,
                  "profile": profile}))
"""


class Records:
    """Figures of the build steps kept in ``WORK/records.json``, so a run that reuses the material still
    reports how long the build took when it was made."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = json.loads(path.read_text()) if path.is_file() else {}

    def put(self, key: str, value: dict) -> None:
        self.data[key] = value
        self.path.write_text(json.dumps(self.data, indent=1))


@dataclass
class Material:
    """Paths of the built test material."""

    ict: Path
    rig: Path
    markers: Path
    datasets: dict[int, Path]
    indexes: dict[tuple[int, bool], Path]
    files: dict[tuple[str, int], Path]  # (kind, frames) -> bundles file
    frames: int
    short: int
    excluded: int
    units: str
    budget: int
    augment: str  # levels and orders of the datasets' in-betweens, from the manifest


def build_material(work: Path, ict_dir: Path, shapes: list[int], frames: int, short: int, kinds: list[str],
                   noise_mm: float, records: Records, stereo: bool = False) -> Material:
    """Import, augment, rig, index and test frames in ``work``; what exists there is reused."""
    markers = ICT_MARKERS
    ict = work / "ict"
    if not (ict / "manifest.json").is_file():
        log(f"lgi import {ict_dir} --out {ict} --rigid-vertices none")
        run_lgi("import", str(ict_dir), "--out", str(ict), "--rigid-vertices", "none", "-q")
    units = manifest(ict).get("units", "cm")
    datasets = {}
    for n in shapes:
        if n == ICT_SHAPES:
            datasets[n] = ict
            continue
        d = work / f"ds{n}"
        if not (d / "manifest.json").is_file():
            log(f"lgi augment ict --out {d.name} --linear --budget {n - ICT_SHAPES}")
            run_lgi("augment", str(ict), "--out", str(d), "--linear", "--budget", str(n - ICT_SHAPES), "-q")
        got = len(manifest(d)["shapes"])
        if got != n:
            log(f"warning: {d.name} has {got} shapes, not {n} (the augmentation ran out of combinations)")
        datasets[n] = d
    rig = work / "rig.npz"
    if not rig.is_file():
        log(f"lgi rig ict --jaw-vertices {ICT_JAW_VERTICES} --shapes 'jawOpen*' --out rig.npz")
        run_lgi("rig", str(ict), "--jaw-vertices", ICT_JAW_VERTICES, "--shapes", "jawOpen*", "--out", str(rig))
    indexes = {}
    for n in shapes:
        for with_rig in (False, True):
            idx = work / f"idx{n}{'-rig' if with_rig else ''}"
            if not (idx / "manifest.json").is_file():
                log(f"lgi build {datasets[n].name} --markers {markers.name}{' --jaw-rig rig.npz' if with_rig else ''}"
                    f" --out {idx.name}")
                r = lgi_timed("build", str(datasets[n]), "--markers", str(markers), "--out", str(idx), "-q",
                              *(["--jaw-rig", str(rig)] if with_rig else []))
                records.put(f"build/{idx.name}", {"wall_s": r.wall_s, "peak_mib": r.peak_mib})
            indexes[(n, with_rig)] = idx

    # Key poses: combinations drawn with another seed, minus any that are in-betweens of a dataset.
    n_keys = frames // STEP + 1
    margin = max(20, n_keys // 10)
    budget = n_keys + margin
    mixes = work / f"mixes-b{budget}-s{MIX_SEED}"
    if not (mixes / "manifest.json").is_file():
        log(f"lgi augment ict --out {mixes.name} --linear --budget {budget} --seed {MIX_SEED}")
        run_lgi("augment", str(ict), "--out", str(mixes), "--linear", "--budget", str(budget), "--seed", str(MIX_SEED),
            "-q")
    taken = set()
    for n in shapes:
        if n > ICT_SHAPES:
            taken |= {c for _, c in combos(datasets[n])}
    candidates = combos(mixes)
    held = [name for name, c in candidates if c not in taken]
    excluded = sum(1 for _, c in candidates[:n_keys] if c in taken)
    if len(held) < n_keys:
        log(f"warning: only {len(held)} held-out mixes; using them all")
    held = held[:n_keys]
    fdir = work / f"shot-K{len(held)}-vs{max(shapes)}"
    fdir.mkdir(exist_ok=True)
    (fdir / "names.txt").write_text("\n".join(held) + "\n")
    keys = fdir / "keys.csv"
    if not keys.is_file():
        pattern = ",".join(escape(n) for n in held)
        if len(pattern) > 120_000:  # one argument may not exceed 128 KiB (Linux MAX_ARG_STRLEN)
            raise SystemExit(f"--frames {frames}: the list of shape names is too long for one argument")
        log(f"lgi bundles {mixes.name} --markers {markers.name} --out {keys.name} --shapes <{len(held)} key poses>")
        run_lgi("bundles", str(mixes), "--markers", str(markers), "--out", str(keys), "--shapes", pattern)
    files = {}
    clean = fdir / "clean.csv"
    frames = eased_shot(keys, clean, STEP)
    short = short if short < frames else max(1, frames // 5)
    files[("clean", frames)] = clean
    sigma = noise_mm / MM_PER_UNIT[units]
    if "noisy" in kinds:
        dst = fdir / f"noisy{noise_mm:g}mm{'-stereo' if stereo else ''}.csv"
        log(f"{noise_mm:g} mm noise ({sigma:g} {units}{', stereo' if stereo else ''}) -> {dst.name}")
        add_noise(clean, dst, [sigma * a for a in STEREO_AXES] if stereo else sigma, seed=1)
        files[("noisy", frames)] = dst
    for kind in kinds:
        long = files[(kind, frames)]
        dst = long.with_name(f"{long.stem}-first{short}.csv")
        first_frames(long, dst, short)
        files[(kind, short)] = dst
    aug = manifest(datasets[max(shapes)])["info"].get("augmented", {}) if max(shapes) > ICT_SHAPES else {}
    how = ", ".join(f"{k} {','.join(f'{v:g}' for v in aug[k])}" for k in ("levels", "orders") if k in aug)
    return Material(ict, rig, markers, datasets, indexes, files, frames, short, excluded, units, budget, how)


def summary(stdout: str) -> dict:
    """What ``lgi reconstruct`` printed about the bundles: contained share and how noise was treated."""
    out = {}
    m = re.search(r"([\d.]+) % contained", stdout)
    out["contained"] = float(m.group(1)) if m else float("nan")
    m = re.search(r"([\d.]+) % (fitted as measurements|met by the global fit)", stdout)
    out["fitted"] = float(m.group(1)) if m else 0.0
    m = re.search(r"bundles treated as (exact|measurements with ([\d.]+) mm noise)", stdout)
    out["noise"] = "?" if not m else ("exact" if m.group(1) == "exact" else f"{m.group(2)} mm")
    m = re.search(r"local fits for ([\d.]+) %", stdout)
    out["local"] = float(m.group(1)) if m else float("nan")
    return out


def reconstruct_argv(index: Path, bundles: Path, out: Path, extra: list[str]) -> list[str]:
    """The timed command line."""
    return [sys.executable, "-m", "lgi", "reconstruct", str(index), "--bundles", str(bundles), "--out", str(out), "-q",
            *extra]


def noise_args(kind: str, args: argparse.Namespace) -> list[str]:
    """``--noise MM`` for the noisy kinds with ``--given-noise``; nothing otherwise (``--noise auto``)."""
    return ["--noise", f"{args.noise_mm:g}"] if args.given_noise and kind.endswith("noisy") else []


def time_config(mat: Material, index: Path, kind: str, repeat: int, env: dict[str, str], scratch: Path,
                extra: list[str]) -> dict:
    """Median wall times of the short and the long shot (runs interleaved), peak memory, summary."""
    walls = {mat.short: [], mat.frames: []}
    peaks = {mat.short: [], mat.frames: []}
    last = ""
    for _ in range(repeat):
        for n in (mat.short, mat.frames):
            out = scratch / "recon"
            shutil.rmtree(out, ignore_errors=True)
            r = run_process(reconstruct_argv(index, mat.files[(kind, n)], out, extra), env)
            shutil.rmtree(out, ignore_errors=True)
            if r.returncode != 0:
                log(f"reconstruct failed ({index.name}, {kind}, {n} frames):\n{r.stderr[-3000:]}")
                return {"failed": True}
            walls[n].append(r.wall_s)
            peaks[n].append(r.peak_mib)
            if n == mat.frames:
                last = r.stdout
    ts, tl = statistics.median(walls[mat.short]), statistics.median(walls[mat.frames])
    return {"failed": False, "t_short": ts, "t_long": tl, "peak_mib": max(peaks[mat.frames]),
            "walls_long": walls[mat.frames], "extra_ms": (tl - ts) / max(mat.frames - mat.short, 1) * 1e3,
            **summary(last)}


FIT_CHILD = r"""
import sys, time
import numpy as np
from lgi.solve import _blend_kernels as K
from lgi.solve import _jaw_kernels as J
from lgi.jobs.reconstruct import ReconstructOptions, Shot
from lgi.solve.jaw import jaw_matrix
from lgi.threads import one_blas_thread

index, bundles, out = sys.argv[1:4]
shot = Shot(index, bundles, ReconstructOptions())  # the same reading, checks, noise estimate and smoothing
sol = shot.solver
fit, x0, deltas = sol.global_fit, sol.neutral.reshape(-1), sol.deltas.reshape(len(sol.deltas), -1)
ones = np.ones(len(sol.neutral))
skin_w = sol.skin_weights


@one_blas_thread
def run(pos):
    verts = np.empty((len(pos), len(sol.neutral), 3), np.float32)
    prev = None
    x = np.empty_like(sol.neutral)
    for f in range(len(pos)):
        prev = fit.solve(pos[f], init=prev)
        nz = np.flatnonzero(prev.weights > 0)
        K.blend_uniform(x0, deltas, ones, (nz + 1).astype(np.int64), prev.weights[nz], x.reshape(-1))
        if skin_w is not None:
            J.skin_points(x, skin_w, np.ascontiguousarray(jaw_matrix(prev.jaw, sol.rig.pivot)[:3]), x)
        verts[f] = x
    return verts


verts = run(np.asarray(shot.fit_pos))
np.savez(out, vertices=verts)
"""


def time_fit(mat: Material, index: Path, kind: str, repeat: int, env: dict[str, str], scratch: Path) -> dict:
    """Median wall times of the blendshape fit (``FIT_CHILD``) on the short and the long shot, as
    :func:`time_config` times LGI."""
    walls = {mat.short: [], mat.frames: []}
    for _ in range(repeat):
        for n in (mat.short, mat.frames):
            out = scratch / "fit.npz"
            r = run_process([sys.executable, "-c", FIT_CHILD, str(index), str(mat.files[(kind, n)]), str(out)], env)
            out.unlink(missing_ok=True)
            if r.returncode != 0:
                log(f"blendshape fit failed ({index.name}, {kind}, {n} frames):\n{r.stderr[-3000:]}")
                return {"failed": True}
            walls[n].append(r.wall_s)
    ts, tl = statistics.median(walls[mat.short]), statistics.median(walls[mat.frames])
    return {"failed": False, "t_short": ts, "t_long": tl,
            "extra_ms": (tl - ts) / max(mat.frames - mat.short, 1) * 1e3}


def stage_breakdown(index: Path, warm: Path, bundles: Path, frames: int, env: dict[str, str], scratch: Path,
                    cprofile: int, extra: list[str]) -> str | None:
    """ms per frame per stage of ``lgi reconstruct`` run in one process (see the module docstring), as
    Markdown; None when the run failed (said on stdout)."""
    cfg = {"index": str(index), "warm": str(warm), "bundles": str(bundles), "out": str(scratch / "stage-recon"),
           "stages": STAGES, "cprofile": cprofile, "extra": extra}
    r = run_process([sys.executable, "-c", STAGE_CHILD, json.dumps(cfg)], env)
    if r.returncode != 0:
        print(f"stage breakdown failed (status {r.returncode}):\n{r.stderr[-3000:]}")
        return None
    res = json.loads(r.stdout.strip().splitlines()[-1])
    timers, total = res["timers"], res["total_s"]
    out = [f"Process: python start-up not included; `import lgi.cli` {res['import_s']:.2f} s; first call (short "
           f"shot, imports of the solver's modules, numba cache load) {res['first_s']:.2f} s; the timed call below "
           f"{total:.2f} s = {total / frames * 1e3:.2f} ms per frame ({frames / total:.0f} frames/s); peak RSS of "
           f"the process {r.peak_mib:.0f} MiB.\n",
           "| stage | calls | s | ms per frame | % of the call |",
           "|---|---|---|---|---|"]

    def row(depth: int, label: str, calls: str, secs: float) -> None:
        out.append(f"| {'. ' * depth}{label} | {calls} | {secs:.3f} | {secs / frames * 1e3:.3f} | "
                   f"{100 * secs / total:.1f} |")

    pending: dict[int, list] = {}  # row -> "rest of" rows printed after it (after a parent's last descendant)
    for i, (depth, label, _, _) in enumerate(STAGES):
        if not res["found"].get(label):
            out.append(f"| {'. ' * depth}{label} | absent | | | |")
        else:
            secs, calls = timers[label]
            row(depth, label, str(calls), secs)
            end, kids = i, []
            while end + 1 < len(STAGES) and STAGES[end + 1][0] > depth:
                end += 1
                d2, l2 = STAGES[end][:2]
                if d2 == depth + 1 and res["found"].get(l2):
                    kids.append(timers[l2][0])
            if kids and sum(kids) <= secs:
                pending.setdefault(end, []).insert(0, (depth + 1, f"(rest of {label.split(' (')[0]})",
                                                       secs - sum(kids)))
            elif kids:  # children on two threads: their times overlap
                pending.setdefault(end, []).insert(0, (depth + 1, f"(children of {label.split(' (')[0]} overlap "
                                                       "on two threads by)", sum(kids) - secs))
        for d, lab, secs in pending.pop(i, []):
            row(d, lab, "", secs)
    top = sum(timers[label][0] for d, label, _, _ in STAGES if d == 0 and res["found"].get(label))
    row(0, "(rest of lgi reconstruct: arguments, prints)", "", total - top)
    out.append("\nWithout smoothing, `select_sequence` runs on a second thread while the main thread "
               "blends the frames already chosen (`_Finisher.frame`), so the stages under `solve_prepared` add up "
               "to more than its wall time. `(rest of _Finisher.frame)` is marker evaluation and residuals; "
               "`(rest of select_frame)` includes unskinning the bundles with a rig.")
    table = "\n".join(out)
    if res["profile"]:
        print(f"{table}\n\ncProfile of a third call (same shot; timings inflated by the profiler):\n```\n"
              f"{res['profile'].strip()}\n```")
    return table


def cold_run(index: Path, bundles: Path, frames: int, env: dict[str, str], scratch: Path, extra: list[str]) -> None:
    """One process with an empty numba cache against one with the cache in place."""
    cache = Path(tempfile.mkdtemp(prefix="numba-cold-", dir=scratch))
    out = scratch / "cold-recon"
    try:
        cold = run_process(reconstruct_argv(index, bundles, out, extra), {**env, "NUMBA_CACHE_DIR": str(cache)})
        shutil.rmtree(out, ignore_errors=True)
        warm = run_process(reconstruct_argv(index, bundles, out, extra), env)
        shutil.rmtree(out, ignore_errors=True)
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    if cold.returncode or warm.returncode:
        print(f"cold run failed:\n{cold.stderr[-2000:]}\n{warm.stderr[-2000:]}")
        return
    print(f"First run after a fresh install ({index.name}, {frames} frames): empty numba cache "
          f"(NUMBA_CACHE_DIR set to a new directory for that process) {cold.wall_s:.1f} s, with the cache "
          f"{warm.wall_s:.1f} s: compiling the kernels costs about {cold.wall_s - warm.wall_s:.1f} s once.")


def parse_config(text: str, shapes: list[int], kinds: list[str]) -> tuple[int, bool, str]:
    """``"500,rig,noisy"`` -> (shapes, rig, kind); shapes not built fall back to the nearest built."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 3 or parts[1] not in ("rig", "norig", "none") or parts[2] not in KINDS:
        raise SystemExit(f"--stage-config: SHAPES,rig|norig,{'|'.join(KINDS)} expected, got {text!r}")
    n = int(parts[0])
    if n not in shapes:
        near = min(shapes, key=lambda s: abs(s - n))
        log(f"--stage-config: {n} shapes not in --shapes; using {near}")
        n = near
    kind = parts[2] if parts[2] in kinds else kinds[-1]
    return n, parts[1] == "rig", kind


def main() -> int:
    """Build or reuse the material, time the configurations, print the tables."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=None, help="material directory, reused (default: a temp dir)")
    ap.add_argument("--shapes", default="100,500,2000", help="dataset sizes, comma-separated (>= 57)")
    ap.add_argument("--frames", type=int, default=1000, help="frames of the long shot (1000)")
    ap.add_argument("--short", type=int, default=100, help="frames of the short shot (100; F/5 if >= F)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per shot and configuration; medians (3)")
    ap.add_argument("--kinds", default=None, help="bundles kinds: clean,noisy (both)")
    ap.add_argument("--doc", type=Path, action="append", default=[], help="rewrite the speed table of this Markdown "
                    "file (repeatable: docs/benchmarks.md and README.md)")
    ap.add_argument("--noise-mm", type=float, default=0.3, help="noise per coordinate of the noisy copies (0.3)")
    ap.add_argument("--stereo", action="store_true",
                    help="the noisy copies' noise along z only, a quarter of it along x and y (two cameras' depth)")
    ap.add_argument("--given-noise", action="store_true", help="pass --noise MM to lgi reconstruct for the noisy "
                    "copies (default: --noise auto, which may call unrelated poses exact)")
    ap.add_argument("--stage-config", default="500,rig,clean", help="SHAPES,rig|norig,KIND for the per-stage "
                    "breakdown, or 'none' (500,rig,clean)")
    ap.add_argument("--stages-only", action="store_true", help="only the per-stage breakdown (and --cold): no "
                    "configuration timing, the speed table left as it is")
    ap.add_argument("--cprofile", type=int, default=0, metavar="N", help="also cProfile the stage run: top N")
    ap.add_argument("--cold", action="store_true", help="also one run with an empty numba cache")
    ap.add_argument("--blas-threads", type=int, default=None, help="set OPENBLAS_NUM_THREADS/OMP_NUM_THREADS for "
                    "the children (default: inherit)")
    ap.add_argument("--ict", type=Path, default=ICT_DIR)
    args = ap.parse_args()
    if not has_ict(args.ict):
        print(f"skipped: ICT FaceKit not found at {args.ict} (put it in ../shared/data/ict-facekit or set "
              "$LGI_SHARED_DATA)")
        return 0
    shapes = sorted({int(s) for s in args.shapes.split(",") if s.strip()})
    if not shapes or shapes[0] < ICT_SHAPES:
        raise SystemExit(f"--shapes: every size must be at least ICT's {ICT_SHAPES} shapes")
    kinds = args.kinds.split(",") if args.kinds else ["clean", "noisy"]
    bad = [k for k in kinds if k not in KINDS]
    if bad:
        raise SystemExit(f"--kinds: unknown {bad}")
    env = dict(os.environ)
    if args.blas_threads is not None:
        env["OPENBLAS_NUM_THREADS"] = env["OMP_NUM_THREADS"] = str(args.blas_threads)
    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="lgi-bench-speed-")
        work = Path(tmp.name)
    else:
        work = args.work.resolve()
        work.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    try:
        records = Records(work / "records.json")
        mat = build_material(work, args.ict, shapes, args.frames, args.short, kinds, args.noise_mm, records,
                             args.stereo)
        run_all(args, mat, shapes, kinds, env, work, records)
    finally:
        if tmp is not None:
            tmp.cleanup()
    print(f"\n({time.perf_counter() - t_start:.0f} s in all; material in "
          f"{'a temporary directory, removed (--work DIR keeps it)' if tmp else work})")
    return 0


def stages(args: argparse.Namespace, mat: Material, shapes: list[int], kinds: list[str], env: dict[str, str],
           scratch: Path) -> None:
    """The per-stage breakdown of ``--stage-config``: printed, and written into each ``--doc`` that has a
    ``<!-- table:stages -->`` marker."""
    if args.stage_config == "none":
        return
    n, with_rig, kind = parse_config(args.stage_config, shapes, kinds)
    what = KINDS[kind].format(noise=f"{args.noise_mm:g}")
    head = (f"Per stage: {n} shapes, {'rig' if with_rig else 'no rig'}, {what}; the continuous {mat.frames}-frame "
            f"shot (`bench_speed.py --stage-config {args.stage_config}`, 1-minute load average "
            f"{os.getloadavg()[0]:.2f} before the run).")
    print(f"## {head}\n")
    log(f"stage breakdown: {n} shapes, {'rig' if with_rig else 'no rig'}, {kind}")
    table = stage_breakdown(mat.indexes[(n, with_rig)], mat.files[(kind, mat.short)], mat.files[(kind, mat.frames)],
                            mat.frames, env, scratch, args.cprofile, noise_args(kind, args))
    if table is None:
        return
    print(table)
    for doc in args.doc:
        write_marked(doc, "stages", f"{head}\n\n{table}")


def cold(args: argparse.Namespace, mat: Material, shapes: list[int], kinds: list[str], env: dict[str, str],
         scratch: Path) -> None:
    """``--cold``: the first run after an install, for the ``--stage-config`` configuration."""
    n, with_rig, kind = parse_config(args.stage_config if args.stage_config != "none" else "500,rig,clean",
                                     shapes, kinds)
    log("cold run (empty numba cache)")
    print()
    cold_run(mat.indexes[(n, with_rig)], mat.files[(kind, mat.short)], mat.short, env, scratch,
             noise_args(kind, args))


def run_all(args: argparse.Namespace, mat: Material, shapes: list[int], kinds: list[str], env: dict[str, str],
            work: Path, records: Records) -> None:
    """Time every configuration and print the tables."""
    scratch = work / "scratch"
    scratch.mkdir(exist_ok=True)
    given = f" plus `--noise {args.noise_mm:g}` for the noisy copies" if args.given_noise else ""
    threads = ", ".join(f"{v}={env.get(v, 'unset')}" for v in THREAD_VARS)
    log("one untimed process first (compiles the kernels whose modules changed)")
    first = run_process(reconstruct_argv(mat.indexes[(shapes[0], True)], mat.files[(kinds[0], mat.short)],
                                         scratch / "recon", []), env)
    shutil.rmtree(scratch / "recon", ignore_errors=True)
    if args.stages_only:
        stages(args, mat, shapes, kinds, env, scratch)
        if args.cold:
            cold(args, mat, shapes, kinds, env, scratch)
        shutil.rmtree(scratch, ignore_errors=True)
        return
    load0 = os.getloadavg()[0]
    results, fits = {}, {}
    for kind in kinds:
        for n in shapes:
            for with_rig in (False, True):
                log(f"timing {n} shapes, {'rig' if with_rig else 'no rig'}, {kind}: {args.repeat} x "
                    f"({mat.short} + {mat.frames} frames), LGI and the blendshape fit")
                idx = mat.indexes[(n, with_rig)]
                results[(kind, n, with_rig)] = time_config(mat, idx, kind, args.repeat, env, scratch,
                                                           noise_args(kind, args))
                fits[(kind, n, with_rig)] = time_fit(mat, idx, kind, args.repeat, env, scratch)

    print(f"# lgi reconstruct speed ({os.cpu_count()} cores; 1-minute load average {load0:.2f} before the timed "
          f"runs, {os.getloadavg()[0]:.2f} after; {threads})\n")
    frames_text = (f"a continuous {mat.frames}-frame shot: {mat.frames // STEP + 1} held-out 2-3 shape mixes of ICT "
                   f"shapes (not in the dataset) as key poses {STEP} frames apart, eased into each other")
    print(f"Datasets: ICT FaceKit ({ICT_SHAPES} shapes, 26,719 vertices, {mat.units}) plus `lgi augment --linear "
          f"--budget N-{ICT_SHAPES}` ({mat.augment or 'no in-betweens'}). Frames: {frames_text} (`lgi augment "
          f"--linear --budget {mat.budget} --seed {MIX_SEED}`, the combinations that are in-betweens of the "
          f"{max(shapes)}-shape dataset removed: {mat.excluded}). Short shot: its first {mat.short} frames. Every "
          f"run is a whole process (`python -m lgi reconstruct INDEX --bundles FRAMES --out OUT -q`{given}, "
          f"defaults otherwise), median of {args.repeat}; ms/extra frame = (t{mat.frames} - t{mat.short}) / "
          f"{mat.frames - mat.short}; start-up = t{mat.short} - {mat.short} x ms/extra frame. The blendshape fit: "
          "the same shot preparation, then per frame the bounded fit with the jaw (the global fit LGI starts "
          "from), the compiled blend and skinning (`FIT_CHILD`). The first process (untimed) took "
          f"{first.wall_s:.1f} s for {mat.short} frames.\n")
    rows = []
    for kind in kinds:
        for n in shapes:
            for with_rig in (False, True):
                r, f = results[(kind, n, with_rig)], fits[(kind, n, with_rig)]
                head = f"| {n} | {'rig' if with_rig else 'none'} | {kind} |"
                if r["failed"] or f["failed"]:
                    rows.append(f"{head} failed | | | | | | |")
                    continue
                start = r["t_short"] - mat.short * r["extra_ms"] / 1e3
                rows.append(f"{head} {r['extra_ms']:.1f} | {1e3 / r['extra_ms']:.0f} | {f['extra_ms']:.1f} | "
                            f"{r['extra_ms'] / f['extra_ms']:.2f} | {start:.2f} | {r['t_long']:.1f} | "
                            f"{r['peak_mib']:.0f} |")
    table = "\n".join([
        f"Frames: {frames_text}; clean, and with {args.noise_mm:g} mm Gaussian noise "
        f"{'along z and a quarter of it along x and y (stereo)' if args.stereo else 'per coordinate'}. "
        f"{os.cpu_count()} cores, whole processes, medians of {args.repeat}.\n",
        "| shapes | rig | bundles | LGI ms per extra frame | LGI frames/s | fit ms per extra frame | LGI / fit | "
        f"start-up s | {mat.frames} frames s | peak MiB |",
        "|---|---|---|---|---|---|---|---|---|---|", *rows])
    print(table + "\n")
    for doc in args.doc:
        write_marked(doc, "speed", table)
    for kind in kinds:
        print(f"| shapes | rig | bundles | build s | build peak MiB | {mat.short} frames s | {mat.frames} frames s "
              "| contained % | fitted % | noise treated as |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for n in shapes:
            for with_rig in (False, True):
                idx = mat.indexes[(n, with_rig)]
                b = records.data.get(f"build/{idx.name}", {})
                r = results[(kind, n, with_rig)]
                if r["failed"]:
                    continue
                print(f"| {n} | {'rig' if with_rig else 'none'} | {kind} | {b.get('wall_s', float('nan')):.1f} | "
                      f"{b.get('peak_mib', float('nan')):.0f} | {r['t_short']:.2f} | {r['t_long']:.2f} | "
                      f"{r['contained']:.1f} | {r['fitted']:.1f} | {r['noise']} |")
        print()
    print("| index | shapes | rig | simplices | on disk MiB |")
    print("|---|---|---|---|---|")
    for (n, with_rig), idx in mat.indexes.items():
        counts = manifest(idx).get("counts", {})
        print(f"| {idx.name} | {n} | {'rig' if with_rig else 'none'} | {counts.get('simplices', '?')} | "
              f"{dir_mib(idx):.0f} |")
    print()

    stages(args, mat, shapes, kinds, env, scratch)
    if args.cold:
        cold(args, mat, shapes, kinds, env, scratch)
    shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
