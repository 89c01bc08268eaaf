"""The ``lgi`` command line. Its interface is a contract (documented in the README): add, never break."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__
from .errors import InputError, LgiError


def _identity_weights(text: str | None) -> dict[str, float] | None:
    if not text:
        return None
    out = {}
    for part in text.split(","):
        name, sep, w = part.partition("=")
        try:
            out[name.strip()] = float(w) if sep else 1.0
        except ValueError:
            raise InputError(f"--identity: weight {w!r} of {name!r} is not a number") from None
    return out


def cmd_import(args: argparse.Namespace) -> int:
    from .importers import import_obj_folder

    t0 = time.perf_counter()
    rigid = args.rigid_vertices
    ds = import_obj_folder(
        args.shapes_dir, neutral=args.neutral, include=args.include, exclude=args.exclude, units=args.units,
        rigid_vertices=rigid, deltas=args.deltas, identity_weights=_identity_weights(args.identity),
        show_progress=not args.quiet,
    )
    ds.save(args.out)
    st = ds.info["stabilisation"]
    print(f"imported {ds.n_shapes} shapes, {ds.n_vertices} vertices, {len(ds.face_offsets) - 1} faces "
          f"({ds.units}) in {time.perf_counter() - t0:.1f} s")
    if st["method"] != "none":
        angles = [np.degrees(np.arccos(np.clip((np.trace(m.rigid_transform[:3, :3]) - 1) / 2, -1, 1)))
                  for m in ds.shape_meta]
        shifts = [np.linalg.norm(m.rigid_transform[:3, 3]) for m in ds.shape_meta]
        print(f"stabilised on {st['count']} rigid vertices ({st['method']}): removed up to "
              f"{max(angles):.3g} deg and {max(shifts):.3g} {ds.units}; "
              f"worst fit RMS {st['fit_rms_max']:.2g} {ds.units}")
    print(f"dataset: {Path(args.out).resolve()}  (content hash {ds.content_hash()[:16]})")
    return 0


def _stage(out: Path) -> Path:
    from .atomic import make_temp_dir

    out.mkdir(parents=True, exist_ok=True)
    return make_temp_dir(out, ".lgi-staging-")


def _commit(stage: Path, out: Path) -> None:
    """Move every staged entry into ``out`` (replacing same-named ones), then drop the stage."""
    import os
    import shutil

    for entry in sorted(stage.iterdir()):
        target = out / entry.name
        if target.is_dir() and not target.is_symlink():
            old = out / f".{entry.name}.old-{os.getpid()}"
            os.replace(target, old)
            os.replace(entry, target)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(entry, target)
    stage.rmdir()


def write_synthetic(out: Path, n_vertices: int, n_frames: int, seed: int, quiet: bool = False) -> dict:
    """Write the synthetic actor's dataset, markers, performance bundles and truth into ``out``."""
    import shutil

    from . import synth
    from .bundles import Bundles, write_bundles
    from .markers import layout_from_points, read_layout, write_layout
    from .paths import shipped

    actor = synth.make_actor(n_vertices)
    ds = synth.make_dataset(actor)
    shipped_layout = read_layout(shipped("markers_synth.csv"))
    import pandas as pd

    xyz = pd.read_csv(shipped("markers_synth.csv"))[["x", "y", "z"]].to_numpy(float)
    layout, dist = layout_from_points(shipped_layout.names, xyz, actor.neutral, actor.triangles)
    acts = synth.random_performance(n_frames, seed=seed)
    truth = actor.evaluate_many(acts)
    bundles = Bundles(frames=np.arange(n_frames), markers=layout.names,
                      positions=layout.evaluate(truth.astype(np.float64)))
    stage = _stage(out)
    try:
        ds.save(stage / "dataset")
        write_layout(stage / "markers.csv", layout, neutral=actor.neutral)
        write_bundles(stage / "bundles.csv", bundles)
        np.savez(stage / "truth.npz", vertices=truth, activations=acts.astype(np.float32),
                 controls=np.asarray(synth.CONTROLS), jaw=actor.jaw_parameters(acts).astype(np.float32),
                 frames=np.arange(n_frames))
        _commit(stage, out)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return {"actor": actor, "dataset": ds, "layout": layout, "activations": acts, "truth": truth,
            "marker_snap_cm": float(dist.max())}


def cmd_synth(args: argparse.Namespace) -> int:
    out = Path(args.out)
    r = write_synthetic(out, args.vertices, args.frames, args.seed, args.quiet)
    print(f"synthetic actor: {r['actor'].n_vertices} vertices, {r['dataset'].n_shapes} shapes, "
          f"{len(r['layout'])} markers, {args.frames} frames (seed {args.seed})")
    for name in ("dataset", "markers.csv", "bundles.csv", "truth.npz"):
        print(f"  {out / name}")
    return 0


def cmd_bundles(args: argparse.Namespace) -> int:
    import pandas as pd

    from .atomic import atomic_file
    from .bundles import Bundles, write_bundles
    from .dataset import ShapeDataset
    from .markers import read_layout

    ds = ShapeDataset.load(args.dataset_dir)
    if args.shapes:
        ds = ds.select(include=args.shapes)
        if ds.n_shapes == 0:
            raise InputError(f"no shape matches {args.shapes!r}", path=args.dataset_dir)
    layout = read_layout(args.markers, ds.triangles)
    pos = layout.evaluate(ds.neutral[None] + np.asarray(ds.deltas, np.float64))
    out = Path(args.out)
    write_bundles(out, Bundles(frames=np.arange(ds.n_shapes), markers=layout.names, positions=pos))
    side = out.with_name(out.stem + ".shapes.csv")
    with atomic_file(side) as tmp:
        pd.DataFrame({"frame": np.arange(ds.n_shapes), "shape": ds.names}).to_csv(tmp, index=False)
    print(f"{ds.n_shapes} frames x {len(layout)} markers -> {out}\nframe -> shape map -> {side}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from . import synth

    out = Path(args.out)
    t0 = time.perf_counter()
    r = write_synthetic(out, args.vertices, args.frames, args.seed, args.quiet)
    actor = r["actor"]
    print(f"[1/2] synthetic actor: {actor.n_vertices} vertices, {r['dataset'].n_shapes} dataset shapes, "
          f"{len(r['layout'])} markers, {args.frames}-frame performance ({time.perf_counter() - t0:.1f} s)")
    nl = synth.nonlinearity(actor, r["activations"])
    print("[2/2] how far the truth is from a linear blend of the extreme shapes (mm), over the performance:")
    print(f"      RMS per frame: median {np.median(nl[:, 0]):.2f}, 95th pct {np.percentile(nl[:, 0], 95):.2f}; "
          f"max per frame: median {np.median(nl[:, 1]):.2f}, 95th pct {np.percentile(nl[:, 1], 95):.2f}, "
          f"worst {nl[:, 1].max():.2f}")
    print(f"outputs in {out.resolve()}: dataset/, markers.csv, bundles.csv, truth.npz")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lgi", description="Facial performance capture by Local Geometric Indexing.")
    p.add_argument("--version", action="version", version=f"lgi {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("import", help="import a folder of OBJ shapes into a shape dataset",
                       description="Import a folder of OBJ shapes (one neutral plus shapes with its vertex order) "
                                   "into a shape dataset directory, stabilising head motion.")
    s.add_argument("shapes_dir", metavar="SHAPES_DIR")
    s.add_argument("--out", required=True, metavar="DATASET_DIR")
    s.add_argument("--neutral", metavar="NAME", help="file stem of the neutral (default: the file named *neutral*)")
    s.add_argument("--include", metavar="PATTERN", help="shell patterns of shapes to import, comma-separated")
    s.add_argument("--exclude", metavar="PATTERN", help="shell patterns of shapes to leave out, comma-separated")
    s.add_argument("--rigid-vertices", default="auto", metavar="FILE|auto|none",
                   help="vertex indices that move with the skull (JSON/text/npy), 'auto' to find them, "
                        "'none' to skip stabilisation (default: auto)")
    s.add_argument("--units", default="cm", choices=["mm", "cm", "m", "in"], help="units of the files (default cm)")
    s.add_argument("--deltas", action="store_true", help="shape files hold displacements, not full meshes")
    s.add_argument("--identity", metavar="NAME=W,...", help="blend identity modes (identity*.obj) into the neutral")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_import)

    s = sub.add_parser("synth", help="write the synthetic actor: dataset, markers, performance, truth",
                       description="Write DIR/dataset, DIR/markers.csv, DIR/bundles.csv and DIR/truth.npz "
                                   "(ground-truth vertices (F, V, 3) float32 under 'vertices').")
    s.add_argument("--out", required=True, metavar="DIR")
    s.add_argument("--vertices", type=int, default=20000, metavar="N",
                   help="at least this many vertices (default 20000)")
    s.add_argument("--frames", type=int, default=240, metavar="F", help="performance length (default 240)")
    s.add_argument("--seed", type=int, default=0, metavar="S", help="performance seed (default 0)")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=cmd_synth)

    s = sub.add_parser("bundles", help="evaluate markers on dataset shapes (one frame per shape)",
                       description="Write a bundles file with one frame per dataset shape, and OUT.shapes.csv "
                                   "mapping frames to shape names.")
    s.add_argument("dataset_dir", metavar="DATASET_DIR")
    s.add_argument("--markers", required=True, metavar="MARKERS_CSV")
    s.add_argument("--out", required=True, metavar="BUNDLES", help=".csv or .parquet")
    s.add_argument("--shapes", metavar="PATTERN", help="only shapes matching these shell patterns")
    s.set_defaults(func=cmd_bundles)

    s = sub.add_parser("demo", help="run the main job end to end on the built-in synthetic actor",
                       description="Build the synthetic actor and run the pipeline on its performance; "
                                   "prints figures and where the outputs are.")
    s.add_argument("--out", default="lgi-demo", metavar="DIR", help="output directory (default ./lgi-demo)")
    s.add_argument("--vertices", type=int, default=20000, metavar="N")
    s.add_argument("--frames", type=int, default=240, metavar="F")
    s.add_argument("--seed", type=int, default=0, metavar="S")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for name in ("vertices", "frames"):
        if getattr(args, name, 1) is not None and getattr(args, name, 1) < 1:
            parser.error(f"--{name} must be positive")
    try:
        return int(args.func(args) or 0)
    except LgiError as exc:
        print(f"lgi {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"lgi {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
