"""LGI's frames and the rigged blendshape fit's against scans of another topology (``lgi compare``).

    python benchmarks/bench_compare.py [--vertices N] [--frames F] [--scans K] [--out DIR]

The synthetic actor's shot (``lgi synth``: a random performance, exact bundles) is reconstructed by LGI (``lgi
build --jaw-rig``, ``lgi reconstruct``) and by the rigged bounded blendshape fit
(:class:`lgi.evaluation.baselines.RiggedBlendshapeSolver` on the same index, its frames written as a
``meshes.npz`` of the same format). The "scans" are the true frames remeshed by pymeshlab (isotropic remeshing at
0.8 x the mesh's mean edge: another topology) with a hole cut in the forehead, written as OBJ in mm: the K frames
the blendshape fit misses most (its true vertex RMS over the face; the nonlinear creases), 10 frames apart.
``lgi compare --index --region face --units mm`` (the job function) measures both, without and with ``--align
rigid``; the table also gives each frame's true vertex RMS over the same region (known here, not in a studio) for
reference. Prints a Markdown table (mm).

``--dense 1e6,5e6``: the size studios scan. One of those scans (a remeshed frame with its hole) subdivided at
edge midpoints until it has about each count of vertices, written as binary PLY in mm, and ``lgi compare`` on the
LGI frame as a whole process (its wall time and peak resident memory), with and without ``--align rigid``. The
table goes into docs/compare.md with ``--doc``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
from common import lgi_timed, log, write_marked

HOLE = (0.0, 6.0, 1.6, 1.2)  # the forehead (cm): centre x, y, half width, half height


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--vertices", type=int, default=20000)
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--scans", type=int, default=3)
    p.add_argument("--out", help="keep the work folder here (default: a temporary one)")
    p.add_argument("--dense", help="comma-separated scan sizes (vertices, e.g. 2.5e5,1e6,5e6): the dense-scan "
                                   "table instead of the methods' one")
    p.add_argument("--doc", type=Path, action="append", default=[], help="write the table into this Markdown file")
    a = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-compare-") as tmp:
        w = Path(a.out) if a.out else Path(tmp)
        if a.dense:
            text = dense(w, a.vertices, a.frames, [int(float(x)) for x in a.dense.split(",")])
            print(text)
            for doc in a.doc:
                write_marked(doc, "compare-dense", text)
        else:
            run(w, a.vertices, a.frames, a.scans)


def dense(w: Path, vertices: int, frames: int, sizes: list[int]) -> str:
    """The dense-scan table: ``lgi compare`` of the LGI frame against its remeshed frame subdivided to about each
    of ``sizes`` vertices, as a whole process."""
    from lgi.dataset.shapes import ShapeDataset
    from lgi.evaluation.compare import remeshed_scan, subdivided, write_ply
    from lgi.jobs.build import build
    from lgi.jobs.reconstruct import reconstruct
    from lgi.jobs.synthetic import SynthOptions, write_synthetic

    s = w / "synth"
    if not (w / "lgi" / "meshes.npz").is_file():
        write_synthetic(s, SynthOptions(vertices=vertices, frames=frames))
        build(s / "dataset", s / "markers.csv", w / "index", jaw_rig=s / "jaw_rig.npz")
        reconstruct(w / "index", s / "bundles.csv", w / "lgi")
    truth = np.load(s / "truth.npz")["vertices"].astype(np.float64)
    ds = ShapeDataset.load(s / "dataset")
    tri = ds.triangles.astype(np.int64)
    frame = frames // 2
    edge = float(np.linalg.norm(ds.neutral[tri[:, 0]] - ds.neutral[tri[:, 1]], axis=1).mean())
    rows = []
    for size in sizes:
        # Subdivision multiplies the count by about 4: the remeshed base is sized so that the last level lands
        # near ``size``.
        levels = max(0, round(np.log(size / ds.n_vertices) / np.log(4)))
        base = size / 4 ** levels
        sv, st = remeshed_scan(truth[frame], tri, 0.8 * edge * np.sqrt(ds.n_vertices * 1.19 / base), HOLE)
        for _ in range(levels):
            sv, st = subdivided(sv, st)
        path = w / "scans" / f"scan_{len(sv)}.ply"
        write_ply(path, sv * 10.0, st)
        log(f"{path.name}: {len(sv)} vertices, {len(st)} triangles, {path.stat().st_size / 2 ** 20:.0f} MiB")
        del sv, st
        for align in ("none", "rigid"):
            out = w / f"compare-{size}-{align}"
            shutil.rmtree(out, ignore_errors=True)
            r = lgi_timed("compare", str(w / "lgi"), "--frame", str(frame), "--scan", str(path), "--index",
                          str(w / "index"), "--region", "face", "--units", "mm", "--align", align, "--out", str(out))
            summary = json.loads((out / "summary.json").read_text())[0]
            rows.append((summary["scan_points"], path.stat().st_size / 2 ** 20, align, r.wall_s, r.peak_mib,
                         summary["rms_mm"], summary["covered_share"]))
            shutil.rmtree(out, ignore_errors=True)
        path.unlink()
    lines = [f"synthetic actor, {ds.n_vertices} vertices; frame {frame} of LGI's reconstruction against its true "
             "surface remeshed with the forehead hole and subdivided at edge midpoints; binary PLY in mm; `lgi "
             "compare --region face --units mm` as a whole process, one run each; peak resident memory of the "
             "process", "",
             "| scan vertices | PLY MiB | align | wall s | us per scan vertex | peak MiB | RMS mm | covered |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {n:,} | {mib:.0f} | {align} | {wall:.1f} | {wall / n * 1e6:.1f} | {peak:.0f} | {rms:.3f} | "
              f"{cov * 100:.1f} % |" for n, mib, align, wall, peak, rms, cov in rows]
    return "\n".join(lines) + "\n"


def run(w: Path, vertices: int, frames: int, n_scans: int) -> None:
    from lgi.capture.bundles import read_bundles
    from lgi.dataset.shapes import ShapeDataset
    from lgi.evaluation.baselines import RiggedBlendshapeSolver
    from lgi.evaluation.compare import remeshed_scan
    from lgi.index.build import LGIIndex
    from lgi.io.npz import save_npz
    from lgi.io.obj import write_obj
    from lgi.jobs.build import build
    from lgi.jobs.compare import CompareOptions, compare
    from lgi.jobs.layout import measured_region
    from lgi.jobs.reconstruct import reconstruct
    from lgi.jobs.synthetic import SynthOptions, write_synthetic

    s = w / "synth"
    write_synthetic(s, SynthOptions(vertices=vertices, frames=frames))
    build(s / "dataset", s / "markers.csv", w / "index", jaw_rig=s / "jaw_rig.npz")
    reconstruct(w / "index", s / "bundles.csv", w / "lgi")
    index = LGIIndex.load(w / "index")
    b = read_bundles(s / "bundles.csv", index.marker_names)
    (w / "blendshape").mkdir(exist_ok=True)
    fit = RiggedBlendshapeSolver(index).solve_sequence(b.positions).astype(np.float32)
    save_npz(w / "blendshape" / "meshes.npz", vertices=fit, frames=b.frames)

    truth = np.load(s / "truth.npz")["vertices"].astype(np.float64)
    ds = ShapeDataset.load(s / "dataset")
    tri = ds.triangles.astype(np.int64)
    region = measured_region(ds)[0]
    # The frames a blendshape system gets most wrong (the moving creases): where a scan check matters.
    fit_rms = np.sqrt(np.mean(np.sum((fit - truth) ** 2, axis=2)[:, region], axis=1))
    picked: list[int] = []
    for f in np.argsort(fit_rms)[::-1].tolist():  # the worst first, 10 frames apart (distinct expressions)
        if len(picked) < n_scans and all(abs(f - g) >= 10 for g in picked):
            picked.append(f)
    picked.sort()
    edge = float(np.linalg.norm(ds.neutral[tri[:, 0]] - ds.neutral[tri[:, 1]], axis=1).mean())
    scans = []
    for f in picked:
        sv, st = remeshed_scan(truth[f], tri, 0.8 * edge, HOLE)
        path = w / "scans" / f"scan_{f:05d}.obj"
        write_obj(path, sv * 10.0, st.ravel(), np.arange(0, 3 * len(st) + 1, 3))  # mm, as a scanner writes
        scans.append(str(path))
    print(f"synthetic actor, {ds.n_vertices} vertices; frames {picked} (the {n_scans} the blendshape fit misses most) "
          f"against their true surface remeshed by pymeshlab ({edge * 8:.1f} mm edges, "
          f"{ds.n_vertices} -> about {len(sv)} vertices) with a {HOLE[2] * 20:.0f} x {HOLE[3] * 20:.0f} mm forehead "
          "hole; lgi compare --region face --units mm; mm\n")
    print("| method | align | frame | covered | RMS | p95 | max | scan RMS | Hausdorff | true vertex RMS |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    names = {"lgi": "LGI", "blendshape": "blendshape fit + rig"}
    for method in ("lgi", "blendshape"):
        rec = np.load(w / method / "meshes.npz")["vertices"].astype(np.float64)
        for align in ("none", "rigid"):
            opts = CompareOptions(frames=tuple(picked), scans=tuple(scans), index=str(w / "index"), align=align,
                                  region="face", units="mm")
            for r in compare(w / method, opts)["pairs"]:
                f = r["frame"]
                true_rms = float(np.sqrt(np.mean(np.sum((rec[f] - truth[f]) ** 2, axis=1)[region])) * 10)
                print(f"| {names[method]} | {align} | {f} | {r['covered_share'] * 100:.1f} % | {r['rms_mm']:.3f} | "
                      f"{r['p95_mm']:.3f} | {r['max_mm']:.3f} | {r['scan_rms_mm']:.3f} | {r['hausdorff_mm']:.3f} | "
                      f"{true_rms:.3f} |", flush=True)


if __name__ == "__main__":
    main()
