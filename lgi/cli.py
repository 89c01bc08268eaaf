"""The ``lgi`` command line. Its interface is a contract (documented in the README): add, never break."""

from __future__ import annotations

import argparse
import logging
import sys

from lgi import __version__
from lgi.errors import InputError, LgiError, Terminated
from lgi.jobs.bench import BenchOptions
from lgi.jobs.cache import PruneOptions
from lgi.jobs.capture import CalibrateOptions, TrackFootageOptions
from lgi.jobs.compare import SHOT_SCAN_OPTIONS, CompareOptions
from lgi.jobs.dataset import AugmentOptions, ImportOptions
from lgi.jobs.export import ExportOptions
from lgi.jobs.reconstruct.options import GROUPS as RECONSTRUCT_GROUPS
from lgi.jobs.reconstruct.options import ReconstructOptions
from lgi.jobs.rig import RigOptions
from lgi.jobs.rig_generate import RigGenerateOptions
from lgi.jobs.rig_solve import RigSolveOptions
from lgi.jobs.synthetic import DemoOptions, SynthOptions
from lgi.jobs.verify import VerifyOptions
from lgi.options import add_flags, declared_fields, flag_name, from_args, params, take


def _import_options(args: argparse.Namespace):
    return from_args(ImportOptions, args)


def cmd_import(args: argparse.Namespace) -> int:
    from lgi.jobs.dataset import import_dataset, import_report

    opts = _import_options(args)
    if args.flow:
        from lgi.jobs.dataset import check_rebuild
        from lgi.jobs.rebuild import rebuild_report
        from lgi.orchestration.rebuild import rebuild_dataset

        check_rebuild(args.shapes_dir, args.out, opts, args.markers)  # before Prefect starts

        s = rebuild_dataset(args.shapes_dir, args.out, markers=args.markers, **opts.to_json())
        for line in rebuild_report(s):
            print(line)
        return 0 if "verification" not in s or s["verification"]["passed"] else 1
    if args.markers:
        # Warned, not refused: releases before the check ignored --markers without --flow, and scripts pass it.
        logging.getLogger(__name__).warning("--markers builds and verifies an index only with --flow: ignored (add "
                                            "--flow, or run lgi build and lgi verify)")
    for line in import_report(import_dataset(args.shapes_dir, args.out, opts, show_progress=not args.quiet)):
        print(line)
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from lgi.jobs.synthetic import SynthOptions, synth_report, write_synthetic

    opts = from_args(SynthOptions, args)
    for line in synth_report(write_synthetic(args.out, opts, show_progress=not args.quiet), opts):
        print(line)
    return 0


def cmd_track(args: argparse.Namespace) -> int:
    from lgi.jobs.capture import TrackFootageOptions, track, track_report

    opts = from_args(TrackFootageOptions, args)
    for line in track_report(track(args.footage_dir, args.calib, args.markers, args.out, opts)):
        print(line)
    return 0


def cmd_bundles(args: argparse.Namespace) -> int:
    from lgi.jobs.dataset import dataset_bundles

    r = dataset_bundles(args.dataset_dir, args.markers, args.out, args.shapes)
    print(f"{r['frames']} frames x {r['markers']} markers -> {r['bundles']}\nframe -> shape map -> {r['shapes']}")
    return 0


def _index_options(args: argparse.Namespace):
    from lgi.index.build import IndexOptions
    from lgi.index.cloud import CloudOptions

    c = CloudOptions(min_motion_rel=args.min_motion_rel, min_motion_abs=args.min_motion_abs, merge_tol=args.merge_tol,
                     n_subsets=args.subsets, subset_fraction=args.subset_fraction, knn=args.knn,
                     min_quality=args.min_quality, max_edge_rel=args.max_edge_rel, budget=args.budget, seed=args.seed)
    return IndexOptions(cloud=c, region_radius=args.region_radius)


def cmd_build(args: argparse.Namespace) -> int:
    from lgi.jobs.build import build, build_report

    summary = build(args.dataset_dir, args.markers, args.out, _index_options(args), args.jaw_rig,
                    show_progress=not args.quiet)
    for line in build_report(summary):
        print(line)
    return 0


def _reconstruct_options(args: argparse.Namespace):
    from lgi.jobs.reconstruct import ReconstructOptions
    from lgi.options import from_args

    return from_args(ReconstructOptions, args)


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from lgi.jobs.compare import shot_scan_options
    from lgi.jobs.reconstruct import InProcess, ReconstructJob, report_lines

    opts = _reconstruct_options(args)
    if args.dask and not args.flow:
        raise InputError("--dask runs the flow's chunk tasks on Dask: it needs --flow")
    if opts.method == "blendshape" and args.flow:
        raise InputError("--method blendshape runs in this process: it does not take --flow")
    scan = take(SHOT_SCAN_OPTIONS, args)
    scan_flags = declared_fields(SHOT_SCAN_OPTIONS)
    if not args.scans and scan != {f.name: f.default for f in scan_flags}:
        logging.getLogger(__name__).warning("%s apply to --scans: ignored without it",
                                            ", ".join(flag_name(f, SHOT_SCAN_OPTIONS.prefix) for f in scan_flags))
    job = ReconstructJob(args.index_dir, args.bundles, args.out, opts, shot_scan_options(args.scans, args.index_dir,
                                                                                         args.out, **scan), args.review)
    if args.review:
        from lgi.io.atomic import check_output
        from lgi.jobs.review import REVIEW_ENTRIES

        check_output(f"{args.out}/review", "dir", owned=REVIEW_ENTRIES, what="lgi review folder")  # before the work
    from lgi.io.atomic import output_lock

    with output_lock(args.out):  # one run at a time in OUT: the reconstruction, its scans' comparison, its page
        summary = _on_flow(args, job, scan) if args.flow else job.run(InProcess(show_progress=not args.quiet))
    report = report_lines
    if opts.method == "blendshape":
        from lgi.jobs.reconstruct.blendshape import blendshape_report as report
    for line in report(summary):
        print(line)
    c = summary.get("compare")
    if c is not None and c["status"] == "done":
        print(f"scans: {len(c['pairs'])} frames compared, tables and heat maps in {c['out']}")
    if summary.get("review"):
        print(f"review page: {summary['review']}")
    if c is not None and c["status"] != "done":
        print(f"lgi reconstruct: error: the reconstruction in {args.out} is written, but the scan comparison "
              f"failed: {c['error']}", file=sys.stderr)
        return 2
    return 0


def _on_flow(args: argparse.Namespace, job, scan: dict) -> dict:
    """``lgi reconstruct --flow``: the job checked here (bad input refused before Prefect starts), then run by the
    reconstruct-shot flow."""
    from lgi.jobs.reconstruct import preflight
    from lgi.orchestration.reconstruct import reconstruct_shot

    job.check()
    preflight(job.index_dir, job.bundles, job.options)
    return reconstruct_shot(job.index_dir, job.bundles, job.out, dask_address=args.dask, review=args.review,
                            scans=args.scans, **params(SHOT_SCAN_OPTIONS, scan), **job.options.to_json())


def cmd_verify(args: argparse.Namespace) -> int:
    from lgi.jobs.verify import VerifyOptions, verify, verify_report

    table, summary = verify(args.index_dir, from_args(VerifyOptions, args), show_progress=not args.quiet)
    for line in verify_report(table, summary):
        print(line)
    return 0 if summary["passed"] else 1


def cmd_augment(args: argparse.Namespace) -> int:
    from lgi.jobs.dataset import AugmentOptions, augment_dataset, augment_report

    opts = from_args(AugmentOptions, args)
    s = augment_dataset(args.dataset_dir, args.out, opts, args.jaw_rig, args.markers, show_progress=not args.quiet)
    for line in augment_report(s):
        print(line)
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from lgi.jobs.capture import CalibrateOptions, calibrate, calibrate_report

    opts = from_args(CalibrateOptions, args)
    for line in calibrate_report(calibrate(args.images_dir, args.out, opts)):
        print(line)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from lgi.jobs.export import ExportOptions, export, export_report

    opts = from_args(ExportOptions, args)
    for line in export_report(export(args.recon_dir, args.index, opts, show_progress=not args.quiet), opts):
        print(line)
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from lgi.jobs.compare import CompareOptions, compare, compare_report

    opts = from_args(CompareOptions, args)
    for line in compare_report(compare(args.recon_dir, opts)):
        print(line)
    return 0


def cmd_rig(args: argparse.Namespace) -> int:
    from lgi.jobs.rig import RigOptions, fit_jaw_rig, rig_report

    for line in rig_report(fit_jaw_rig(args.dataset_dir, args.out, from_args(RigOptions, args))):
        print(line)
    return 0


def cmd_rig_generate(args: argparse.Namespace) -> int:
    from lgi.jobs.rig_generate import RigGenerateOptions, generate_rig, rig_generate_report

    opts = from_args(RigGenerateOptions, args)
    for line in rig_generate_report(generate_rig(args.template, args.index, args.out, opts, usd=args.usd,
                                                 show_progress=not args.quiet)):
        print(line)
    return 0


def cmd_rig_solve(args: argparse.Namespace) -> int:
    from lgi.jobs.rig_solve import RigSolveOptions, rig_solve, rig_solve_report

    opts = from_args(RigSolveOptions, args)
    for line in rig_solve_report(rig_solve(args.recon_dir, args.rig, args.out, opts, usd=args.usd,
                                           rig_usd=args.rig_usd, show_progress=not args.quiet)):
        print(line)
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from lgi.jobs.bench import BenchOptions, bench

    bench(args.out, from_args(BenchOptions, args))
    return 0


def cmd_cache(args: argparse.Namespace) -> int:
    from lgi.jobs.cache import PruneOptions, cache_report, list_cache, prune_cache

    if args.action == "ls":
        lines = cache_report(list_cache(args.cache_dir))
    else:
        opts = from_args(PruneOptions, args)
        lines = cache_report(prune_cache(args.cache_dir, opts), removed=True)
    for line in lines:
        print(line)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from lgi.jobs.synthetic import DemoOptions, demo

    demo(args.out, from_args(DemoOptions, args),
         show_progress=not args.quiet)
    return 0


def cmd_review(args: argparse.Namespace) -> int:
    from lgi.jobs.review import ReviewOptions, review, review_report

    opts = ReviewOptions(truth=args.truth, compare=args.compare, fps=args.fps, step_um=args.step, scans=args.scans,
                         rig_solve=args.rig_solve, rig=args.rig)
    for line in review_report(review(args.recon_dir, args.index, args.out, opts)):
        print(line)
    return 0


def cmd_layout_design(args: argparse.Namespace) -> int:
    from lgi.jobs.layout import DesignOptions, design, design_report

    opts = DesignOptions(count=args.count, min_spacing=args.min_spacing, symmetric=args.symmetric,
                         exclude=args.exclude, held_out=args.held_out, epsilon=args.epsilon,
                         time_limit=args.time_limit)
    for line in design_report(design(args.dataset_dir, args.out, opts)):
        print(line)
    return 0


def cmd_layout_evaluate(args: argparse.Namespace) -> int:
    from lgi.jobs.layout import EvaluateOptions, evaluate, evaluate_report

    table, summary = evaluate(args.dataset_dir, args.markers, EvaluateOptions(held_out=args.held_out, out=args.out))
    for line in evaluate_report(table, summary):
        print(line)
    return 0


#: ``lgi --help``: where to start, the words a newcomer meets, and the exit statuses (as the README says them).
DESCRIPTION = """\
Start with `lgi demo`: it builds a synthetic actor, indexes it and reconstructs its performance, and says \
where the outputs are. Then `lgi COMMAND --help` for each step.

lgi turns each frame of an actor's painted dots into a full face mesh, by Local Geometric Indexing \
(Cong, Lan and Fedkiw)."""

EPILOG = """\
terms:
  bundles     the 3D positions of the painted dots (markers) per frame: a CSV or Parquet
              table frame, marker, x, y, z (lgi track, lgi synth and lgi bundles write one)
  HMC         head-mounted stereo camera: two cameras on a helmet filming the painted face
  dataset     the actor's facial shapes on one mesh (lgi import writes one from OBJ files)
  marker layout
              where the dots are painted, as points on the neutral mesh (a markers CSV)
  LGI index   what lgi build makes from a dataset and a marker layout; lgi reconstruct
              and lgi verify read it

exit status:
  0    success
  1    a check failed (lgi verify, including a non-finite error)
  2    bad input (the message names the file, line, frame, marker or option at fault; no
       partial output is left)
  3    an internal error (a bug; --debug anywhere on the command line prints the traceback)
  130  interrupted (Ctrl-C)
  143  terminated by SIGTERM (cleaned up like Ctrl-C)

example:
  lgi demo --out lgi-demo
  lgi reconstruct lgi-demo/index --bundles lgi-demo/bundles.csv --out recon --obj

Every command's options, outputs and an example: docs/cli.md (and `lgi COMMAND --help`). The \
command line is a contract that outside scripts call: options are added, never renamed or removed."""


class _Formatter(argparse.HelpFormatter):
    """Wraps each paragraph of a description or epilog on its own and keeps indented lines (examples, lists) as
    written, so an epilog's examples stay one command per line while prose still fits the terminal."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        import textwrap

        out: list[str] = []
        for block in text.split("\n"):
            if not block.strip() or block[0].isspace() or block.endswith(":"):
                out.append(indent + block if block.strip() else "")
            else:
                out.append(textwrap.fill(block, width, initial_indent=indent, subsequent_indent=indent))
        return "\n".join(out)


def _epilog(outputs: str | None, example: tuple[str, ...]) -> str:
    """A subcommand's epilog: what it writes (wrapped here: the formatter keeps indented lines as they are) and
    an example, one command per line."""
    import textwrap

    parts = [] if outputs is None else ["writes:\n" + textwrap.fill(outputs, 88, initial_indent="  ",
                                                                     subsequent_indent="  ")]
    parts.append("example:\n" + "\n".join(f"  {line}" for line in example))
    return "\n\n".join(parts)


def _command(sub: argparse._SubParsersAction, name: str, help: str, description: str,
             example: tuple[str, ...], outputs: str | None = None) -> argparse.ArgumentParser:
    return sub.add_parser(name, help=help, description=description, epilog=_epilog(outputs, example),
                          formatter_class=_Formatter)


def _quiet(g: argparse._ActionsContainer) -> None:
    g.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def _add_import(sub: argparse._SubParsersAction) -> None:
    """The ``lgi import`` command's parser."""
    s = _command(sub, "import", "import a folder of OBJ shapes into a shape dataset",
                 "Import a folder of OBJ shapes (one neutral plus shapes with its vertex order; quads, UV seams and "
                 "materials kept) into a shape dataset directory, removing rigid head motion. Positions are "
                 "converted to cm, the unit datasets are stored in.",
                 ("lgi import shapes/ --out datasets/actor --units cm --rigid-vertices auto",),
                 outputs="DATASET_DIR: the shape dataset (manifest.json, mesh.npz, deltas.npy; cm); with --flow, "
                         "OUT/dataset/ and, with --markers, OUT/index/, OUT/verification/ and OUT/report.md.")
    g = s.add_argument_group("inputs")
    g.add_argument("shapes_dir", metavar="SHAPES_DIR",
                   help="folder of .obj files: the neutral, the shapes, and any identity*.obj identity modes")
    groups = {"inputs": g, "method": s.add_argument_group("method")}
    add_flags(groups, ImportOptions)
    g = s.add_argument_group("outputs")
    g.add_argument("--out", required=True, metavar="DATASET_DIR", help="the shape dataset directory to write")
    _quiet(g)
    g = s.add_argument_group("scheduling")
    g.add_argument("--flow", action="store_true",
                   help="run the Prefect rebuild-dataset flow (cached stages, artifacts): OUT becomes a folder with "
                        "dataset/ and, with --markers, index/, verification/ and report.md")
    g.add_argument("--markers", metavar="MARKERS_CSV",
                   help="with --flow: also build and verify the index (without --flow: ignored, with a warning)")
    s.set_defaults(func=cmd_import)


def _add_synth(sub: argparse._SubParsersAction) -> None:
    """The ``lgi synth`` command's parser."""
    s = _command(sub, "synth", "write the synthetic actor: dataset, markers, performance, truth",
                 "Write the synthetic actor: DIR/dataset, DIR/markers.csv, DIR/bundles.csv (its performance), "
                 "DIR/jaw_rig.npz and DIR/truth.npz (ground-truth vertices (F, V, 3) float32 under 'vertices'); "
                 "with --hmc also head-mounted camera footage of the performance in DIR/hmc.",
                 ("lgi synth --out synth --vertices 20000 --frames 240 --seed 1",),
                 outputs="DIR/dataset/, DIR/markers.csv, DIR/bundles.csv, DIR/jaw_rig.npz, DIR/truth.npz; with --hmc, "
                         "DIR/hmc/ (cam0/, cam1/, calib/, the true cameras, helmet dots, true 2D dots, "
                         "lip_contours.csv); with --template, DIR/template/.")
    g = s.add_argument_group("outputs")
    g.add_argument("--out", required=True, metavar="DIR", help="folder to write")
    _quiet(g)
    add_flags({name: s.add_argument_group(name) for name in ("actor and performance",
                                                             "head-mounted camera footage")}, SynthOptions)
    s.set_defaults(func=cmd_synth)


def _add_track(sub: argparse._SubParsersAction) -> None:
    """The ``lgi track`` command's parser."""
    s = _command(sub, "track", "track painted dots in stereo HMC footage and write bundles",
                 "Detect dots, label the reference frame (rigid fit of the marker layout, or --labels), track with "
                 "anchor frames, triangulate, remove head motion; write the bundles file (cm) and a 2D tracks "
                 "table (Parquet) with reprojection errors.",
                 ("lgi track synth/hmc --calib calib.json --markers synth/markers.csv --dataset synth/dataset "
                  "--out shot.parquet",),
                 outputs="BUNDLES (cm, whatever --units the marker file is in; with each bundle's covariance, cm^2) "
                         "and the 2D tracks table (OUT's stem + "
                         ".tracks.parquet, or --tracks): per observation, reprojection error, source, triangulated or "
                         "one camera only.")
    g = s.add_argument_group("inputs")
    g.add_argument("footage_dir", metavar="FOOTAGE_DIR",
                   help="the footage: cam0/ and cam1/ frames (same names), or left*/right* images")
    g.add_argument("--calib", required=True, metavar="CALIB_JSON", help="the stereo calibration (lgi calibrate)")
    g.add_argument("--markers", required=True, metavar="MARKERS_CSV",
                   help="marker layout; its x,y,z columns give the neutral positions unless --dataset is given")
    groups = {"inputs": g, "tracking": s.add_argument_group("tracking"), "outputs": s.add_argument_group("outputs")}
    groups["outputs"].add_argument("--out", required=True, metavar="BUNDLES",
                                   help="bundles file to write (.csv or .parquet)")
    add_flags(groups, TrackFootageOptions)
    s.set_defaults(func=cmd_track)


def _add_bundles(sub: argparse._SubParsersAction) -> None:
    """The ``lgi bundles`` command's parser."""
    s = _command(sub, "bundles", "evaluate markers on dataset shapes (one frame per shape)",
                 "Write a bundles file with one frame per dataset shape, and BUNDLES.shapes.csv (the bundles "
                 "file's stem + .shapes.csv) mapping frames to shape names.",
                 ("lgi bundles synth/dataset --markers synth/markers.csv --out shapes.csv",),
                 outputs='BUNDLES (one frame per shape) and BUNDLES.shapes.csv (frame, shape).')
    g = s.add_argument_group("inputs")
    g.add_argument("dataset_dir", metavar="DATASET_DIR", help="the shape dataset (lgi import)")
    g.add_argument("--markers", required=True, metavar="MARKERS_CSV", help="the marker layout")
    g.add_argument("--shapes", metavar="PATTERN", help="only shapes matching these shell patterns (default: all)")
    g = s.add_argument_group("outputs")
    g.add_argument("--out", required=True, metavar="BUNDLES", help="bundles file to write (.csv or .parquet)")
    s.set_defaults(func=cmd_bundles)


def _add_build(sub: argparse._SubParsersAction) -> None:
    """The ``lgi build`` command's parser."""
    s = _command(sub, "build", "build the LGI index of a dataset for a marker layout",
                 "Build the local geometric index: per-bundle point clouds (pruned: INDEX_DIR/pruning.csv says why "
                 "each shape was dropped or merged), overlapping simplices, search grids, natural-neighbour "
                 "weights. See docs/indexing.md.",
                 ("lgi build synth/dataset --markers synth/markers.csv --jaw-rig synth/jaw_rig.npz --out synth/index",),
                 outputs="INDEX_DIR: the index, with bundles.csv (per bundle: its cloud and simplices) and pruning.csv"
                         " (why each shape was dropped or merged).")
    g = s.add_argument_group("inputs")
    g.add_argument("dataset_dir", metavar="DATASET_DIR", help="the shape dataset (lgi import, lgi synth)")
    g.add_argument("--markers", required=True, metavar="MARKERS_CSV", help="the marker layout")
    g = s.add_argument_group("jaw")
    g.add_argument("--jaw-rig", metavar="RIG_NPZ",
                   help="jaw rig (lgi rig; npz with 'pivot' (3,) cm and 'weights' (V,)): shapes are stored "
                        "unskinned and frames unskinned, indexed and skinned back (lgi synth writes the synthetic "
                        "actor's)")
    g = s.add_argument_group("outputs")
    g.add_argument("--out", required=True, metavar="INDEX_DIR", help="the index directory to write")
    _quiet(g)
    g = s.add_argument_group("pruning (lengths in dataset units, cm)")
    g.add_argument("--min-motion-rel", type=float, default=0.005, metavar="R",
                   help="drop a shape from a bundle's cloud if it moves the bundle less than R x the largest "
                        "motion (default %(default)s)")
    g.add_argument("--min-motion-abs", type=float, default=1e-4, metavar="D",
                   help="... or less than D cm (default %(default)s)")
    g.add_argument("--merge-tol", type=float, default=1e-4, metavar="D",
                   help="merge points closer than D cm (default %(default)s)")
    g = s.add_argument_group("simplices")
    g.add_argument("--subsets", type=int, default=4, metavar="N",
                   help="extra Delaunay tessellations of subsets (default %(default)s)")
    g.add_argument("--subset-fraction", type=float, default=0.6, metavar="F",
                   help="subset size, share of the cloud (default %(default)s)")
    g.add_argument("--knn", type=int, default=0, metavar="K",
                   help="k of the nearest-neighbour fans (default %(default)s = none)")
    g.add_argument("--min-quality", type=float, default=0.02, metavar="Q",
                   help="drop slivers below quality Q (default %(default)s)")
    g.add_argument("--max-edge-rel", type=float, default=0.6, metavar="E",
                   help="drop extra simplices longer than E x the cloud's extent (default %(default)s)")
    g.add_argument("--budget", type=int, default=20000, metavar="B",
                   help="simplices per bundle at most (default %(default)s)")
    g.add_argument("--region-radius", type=float, default=3.0, metavar="R",
                   help="natural-neighbour region: within R cm (cm-equivalent) of a bundle (default %(default)s)")
    g.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the subsets (default %(default)s)")
    s.set_defaults(func=cmd_build)


def _add_reconstruct(sub: argparse._SubParsersAction) -> None:
    """The ``lgi reconstruct`` command's parser."""
    s = _command(sub, "reconstruct", "reconstruct meshes from a bundles file",
                 "Reconstruct every frame of a shot: a global fit of the jaw and shape weights, refitted per "
                 "bundle over its natural neighbours, natural-neighbour blend, skinning, and a correction through "
                 "every bundle. Writes OUT_DIR/meshes.npz (vertices (F, V, 3) float32, frames, and jaw (F, 4) "
                 "with a rig), OUT_DIR/diagnostics.csv (per frame and bundle), OUT_DIR/per_frame.csv, "
                 "OUT_DIR/run.json (method, options, noise used and estimated; lgi review shows it) and, as asked, "
                 "OUT_DIR/obj/frame_NNNNN.obj, OUT_DIR/shot.usdc, OUT_DIR/per_frame.png. A run replaces "
                 "the outputs of an earlier one (and removes those it does not write, and an OUT_DIR/review or "
                 "OUT_DIR/compare folder of lgi review or lgi compare, which showed the earlier meshes); other "
                 "files in OUT_DIR are left alone, and a file lgi has no record of writing there "
                 "(OUT_DIR/.lgi-record.json) is never replaced.",
                 ("lgi reconstruct synth/index --bundles synth/bundles.csv --out synth/recon --obj --smooth 3",),
                 outputs="OUT_DIR/meshes.npz, OUT_DIR/diagnostics.csv, OUT_DIR/per_frame.csv, OUT_DIR/run.json; with "
                         "--obj OUT_DIR/obj/,"
                         " --usd OUT_DIR/shot.usdc (and OUT_DIR/shot.clips/ for a long shot), --plot "
                         "OUT_DIR/per_frame.png; with --observations "
                         "OUT_DIR/bundles_constrained.parquet.")
    g = s.add_argument_group("inputs")
    g.add_argument("index_dir", metavar="INDEX_DIR", help="the LGI index (lgi build)")
    g.add_argument("--bundles", required=True, metavar="BUNDLES",
                   help="the shot's bundles: CSV or Parquet table frame, marker, x, y, z (cm)")
    groups = {name: s.add_argument_group(name) for name in (*RECONSTRUCT_GROUPS[:-1], "scans", "scheduling")}
    groups["outputs"].add_argument("--out", required=True, metavar="OUT_DIR",
                                   help="folder for the reconstruction's files")
    add_flags(groups, ReconstructOptions)
    g = groups["outputs"]
    g.add_argument("--review", action="store_true",
                   help="also write the shot's review page into OUT_DIR/review (index.html; see lgi review)")
    _quiet(g)
    g = groups["scans"]
    g.add_argument("--scans", metavar="PAIRS_CSV",
                   help="a CSV of frame, scan (scan paths relative to the CSV): after the reconstruction each frame "
                        "is compared with its scan as lgi compare does, into OUT_DIR/compare, and with --review the "
                        "page gets the scan map; a scan that does not load or covers no face leaves the "
                        "reconstruction written and exits 2 naming it (default: none)")
    add_flags(groups, SHOT_SCAN_OPTIONS, "scans")
    g = groups["scheduling"]
    g.add_argument("--flow", action="store_true",
                   help="run the job as the Prefect reconstruct-shot flow (chunks of frames as tasks, "
                        "artifacts): the same options and the same files as without it")
    g.add_argument("--dask", metavar="ADDRESS",
                   help="with --flow: run the chunk tasks on Dask, a scheduler address (tcp://host:8786) or local:N "
                        "(a local cluster of N processes); the results do not depend on it")
    s.set_defaults(func=cmd_reconstruct)


def _add_verify(sub: argparse._SubParsersAction) -> None:
    """The ``lgi verify`` command's parser."""
    s = _command(sub, "verify", "reconstruct every dataset shape from its own bundles (paper 7.1)",
                 "The paper's verification: every dataset shape reconstructed from its own bundles; prints RMS and "
                 "max error per shape (mm) over the marked region and the whole mesh; exit 1 if any marked-region "
                 "RMS exceeds the tolerance (or is not finite).",
                 ("lgi verify synth/index --tolerance 0.01",),
                 outputs="no files: a per-shape table on stdout (RMS and max, mm, marked region and whole mesh); exit "
                         "1 when the check fails.")
    g = s.add_argument_group("inputs")
    g.add_argument("index_dir", metavar="INDEX_DIR", help="the LGI index (lgi build)")
    add_flags({"inputs": g, "check": s.add_argument_group("check")}, VerifyOptions)
    g = s.add_argument_group("outputs")
    _quiet(g)
    s.set_defaults(func=cmd_verify)


def _add_rig(sub: argparse._SubParsersAction) -> None:
    """The ``lgi rig`` command's parser."""
    s = _command(sub, "rig", "fit a jaw rig (hinge and skinning weights) from a dataset's jaw shapes",
                 "Fit the jaw hinge and linear-blend-skinning weights from shapes in which given vertices move "
                 "rigidly with the jaw (ICT: the lower teeth 19247:21450): the hinge from the opening shapes only, "
                 "each opening's hinge residual printed. Writes an npz for lgi build --jaw-rig; exit 2 when no "
                 "shape opens the jaw.",
                 ("lgi rig datasets/ict --jaw-vertices 19247:21450 --out ict-rig.npz",),
                 outputs="RIG_NPZ: the jaw rig (hinge pivot and skinning weights), for lgi build --jaw-rig and lgi "
                         "augment --jaw-rig.")
    g = s.add_argument_group("inputs")
    g.add_argument("dataset_dir", metavar="DATASET_DIR", help="the shape dataset (lgi import)")
    add_flags({"inputs": g}, RigOptions, "inputs")
    g = s.add_argument_group("outputs")
    g.add_argument("--out", required=True, metavar="RIG_NPZ", help="the jaw rig file to write (.npz)")
    s.set_defaults(func=cmd_rig)


def _add_rig_generate(sub: argparse._SubParsersAction) -> None:
    """The ``lgi rig-generate`` command's parser."""
    s = _command(sub, "rig-generate", "an actor-specific blendshape rig from a template rig (paper 7.7)",
                 "Reconstruct each template control (and combinations, for correctives) on the actor with LGI: "
                 "the template's displacements at the markers (scaled by the affine map between the neutrals "
                 "unless --transfer add; the jaw by its parameters when the index has a jaw rig) are added to the "
                 "actor's neutral bundles and fitted with the actor's shapes. Writes a shape dataset (shapes "
                 "tagged control / corrective) and, with --usd, a UsdSkel rig (correctives as blend shapes "
                 "carrying lgi:combination). See docs/rigs.md.",
                 ("lgi rig-generate --template datasets/template --index actor/index --out actor/rig "
                  "--correctives auto --usd actor/rig.usda",),
                 outputs="RIG_DIR: a shape dataset of the actor's controls (tag control) and correctives (tags "
                         "corrective, combination), each with its metadata; with --usd, the UsdSkel rig.")
    g = s.add_argument_group("inputs")
    g.add_argument("--template", required=True, metavar="TEMPLATE_DATASET",
                   help="the template rig: a shape dataset on the actor's mesh topology (lgi synth --template writes "
                        "one for the synthetic mesh; lgi import of a rig's OBJ shapes, ICT FaceKit's for one, for "
                        "an actor on that mesh)")
    g.add_argument("--index", required=True, metavar="INDEX_DIR", help="the actor's LGI index")
    groups = {"inputs": g, "method": s.add_argument_group("method"), "outputs": s.add_argument_group("outputs")}
    groups["outputs"].add_argument("--out", required=True, metavar="RIG_DIR", help="the actor's rig, as a shape "
                                   "dataset")
    groups["outputs"].add_argument("--usd", default=None, metavar="RIG.usda",
                                   help="also write the rig as UsdSkel: blend shapes and, with a jaw-rigged index, a "
                                        "jaw joint (default: none)")
    add_flags(groups, RigGenerateOptions)
    _quiet(groups["outputs"])
    s.set_defaults(func=cmd_rig_generate)


def _add_rig_solve(sub: argparse._SubParsersAction) -> None:
    """The ``lgi rig-solve`` command's parser."""
    s = _command(sub, "rig-solve", "a reconstructed shot as animation curves of the actor's rig",
                 "Fit the rig's control weights (in [0, 1], correctives driven by the product of their controls') to "
                 "each reconstructed frame over the face region (robust Gauss-Newton, warm-started), then clean the "
                 "curves over time (a second-difference penalty solved over the shot: no lag). A rig with a jaw "
                 "joint also gets the jaw's rotation and slide per frame. See docs/rigs.md.",
                 ("lgi rig-solve shot/recon --rig actor_rig --out shot/anim --usd shot/anim.usda "
                  "--rig-usd actor_rig.usda",),
                 outputs="OUT_DIR/curves.csv or .parquet (frame, control, value), residuals.csv (rig playback - "
                         "reconstruction, RMS and max mm per frame), vertex_error.npz/.png (where the rig falls "
                         "short), solve.json; with --usd, a UsdSkel animation layer over the rig's USD.")
    g = s.add_argument_group("inputs")
    g.add_argument("recon_dir", metavar="RECON_DIR", help="the reconstruction (lgi reconstruct's meshes.npz)")
    g.add_argument("--rig", required=True, metavar="RIG_DIR", help="the actor's rig dataset (lgi rig-generate)")
    g.add_argument("--rig-usd", default=None, metavar="RIG.usda",
                   help="the rig's USD (lgi rig-generate --usd), checked against RIG_DIR and sublayered by the "
                        "animation (default: none)")
    g = s.add_argument_group("outputs")
    g.add_argument("--out", required=True, metavar="OUT_DIR", help="folder for curves.csv, residuals.csv, ...")
    g.add_argument("--usd", default=None, metavar="ANIM.usda",
                   help="also write the shot as a UsdSkel animation of the rig (needs --rig-usd; default: none)")
    groups = {"outputs": g, "method": s.add_argument_group("method")}
    add_flags(groups, RigSolveOptions)
    _quiet(g)
    s.set_defaults(func=cmd_rig_solve)


def _add_augment(sub: argparse._SubParsersAction) -> None:
    """The ``lgi augment`` command's parser."""
    s = _command(sub, "augment", "add in-between shapes to a dataset",
                 "Add in-betweens: combinations of 2-3 compatible shapes at fixed weights, tagged with their "
                 "sources (opposites such as jawLeft+jawRight are skipped; mouthClose only with jawOpen), as "
                 "linear blends and/or simulated with a volume-preserving flesh model (the same combinations for "
                 "both). See docs/inbetweens.md.",
                 ("lgi augment synth/dataset --out synth/dataset2 --linear --budget 100 --markers synth/markers.csv",),
                 outputs="DATASET_DIR2: the dataset plus the in-betweens (tagged with their sources and method); with "
                         "--markers, augmentation.csv.")
    g = s.add_argument_group("inputs")
    g.add_argument("dataset_dir", metavar="DATASET_DIR", help="the shape dataset to add to")
    g.add_argument("--markers", metavar="MARKERS_CSV",
                   help="also report per bundle how many points the in-betweens added and kept (augmentation.csv)")
    groups = {"combinations": s.add_argument_group("combinations"), "method": s.add_argument_group("method")}
    add_flags(groups, AugmentOptions)
    groups["method"].add_argument("--jaw-rig", metavar="RIG_NPZ",
                                  help="with --simulate: the jaw carries the flesh's jaw side; lip contact")
    g = s.add_argument_group("outputs")
    g.add_argument("--out", required=True, metavar="DATASET_DIR2", help="the augmented dataset to write")
    _quiet(g)
    s.set_defaults(func=cmd_augment)


def _add_calibrate(sub: argparse._SubParsersAction) -> None:
    """The ``lgi calibrate`` command's parser."""
    s = _command(sub, "calibrate", "calibrate a stereo camera pair from chessboard or ChArUco images",
                 "Detect the board, calibrate both cameras (rejecting outlier views, saying why) and the stereo "
                 "extrinsics; print RMS, per-view errors and the baseline; write a documented JSON (and OpenCV "
                 "YAML).",
                 ("lgi calibrate synth/hmc/calib --board charuco:7x5:15:11:DICT_5X5_100 --fisheye --out calib.json",),
                 outputs="CALIB_JSON (per-camera intrinsics and distortion, stereo extrinsics, errors, rejected "
                         "views); with --yaml, the OpenCV YAML.")
    g = s.add_argument_group("inputs")
    g.add_argument("images_dir", metavar="IMAGES_DIR", help="left*/right* images, or cam0/ and cam1/ folders")
    groups = {"inputs": g, "lens model": s.add_argument_group("lens model (default: pinhole)"),
              "outputs": s.add_argument_group("outputs")}
    groups["outputs"].add_argument("--out", required=True, metavar="CALIB_JSON", help="the calibration to write (JSON)")
    add_flags(groups, CalibrateOptions)
    s.set_defaults(func=cmd_calibrate)


def _add_export(sub: argparse._SubParsersAction) -> None:
    """The ``lgi export`` command's parser."""
    s = _command(sub, "export", "export a reconstruction as USD and/or OpenEXR displacement maps",
                 "Write RECON_DIR/meshes.npz as an animated USD mesh (time samples, face-varying UVs; by default "
                 "cm with metersPerUnit 0.01, Y up) and/or per-frame displacement maps in UV space (OpenEXR, "
                 "float32, RGB = xyz displacement; the header names the units, up axis, neutral and frame). "
                 "--dcc, --up-axis and --units write the geometry in a DCC's own convention and say so in the "
                 "files.",
                 ("lgi export synth/recon --index synth/index --usd shot.usda --exr maps",
                  "lgi export synth/recon --index synth/index --usd shot.usdc --dcc blender"),
                 outputs="--usd FILE (animated mesh) and/or --exr DIR/frame_NNNNN.exr (one displacement map per "
                         "frame).")
    g = s.add_argument_group("inputs")
    g.add_argument("recon_dir", metavar="RECON_DIR", help="a reconstruction (lgi reconstruct's OUT_DIR)")
    g.add_argument("--index", required=True, metavar="INDEX_DIR", help="the index it was reconstructed with")
    g = s.add_argument_group("outputs")
    add_flags({"outputs": g}, ExportOptions)
    _quiet(g)
    s.set_defaults(func=cmd_export)


def _add_compare(sub: argparse._SubParsersAction) -> None:
    """The ``lgi compare`` command's parser."""
    s = _command(sub, "compare", "compare reconstructed frames with scans of any topology (distances in mm)",
                 "Point-to-surface distances both ways between reconstructed frames and scans of the same moments "
                 "(any topology; holes, hair and shoulders allowed): RMS, 95th percentile, maximum and Hausdorff "
                 "distance (mm) where the scan covers the face, and the covered share. See docs/compare.md.",
                 ("lgi compare synth/recon --index synth/index --frame 12 --scan scans/take3_f12.obj",
                  "lgi compare recon --index index --pairs scans.csv --units mm --align rigid --region face "
                  "--out recon/compare"),
                 outputs="the table on stdout; with --out DIR/summary.csv, summary.json, per-vertex distances "
                         "(Parquet) and heat maps (PNG).")
    g = s.add_argument_group("inputs")
    g.add_argument("recon_dir", metavar="RECON_DIR", help="a folder written by lgi reconstruct (its meshes.npz)")
    add_flags({"inputs": g, "method": s.add_argument_group("method"), "outputs": s.add_argument_group("outputs")},
              CompareOptions)
    s.set_defaults(func=cmd_compare)


def _add_bench(sub: argparse._SubParsersAction) -> None:
    """The ``lgi bench`` command's parser."""
    s = _command(sub, "bench", "compare LGI with the baselines on the same frames",
                 "Run LGI, the blendshape fits (with and without the jaw rig), RBF weights + smooth and smooth "
                 "interpolation on the synthetic held-out performance and, when ../shared/data has ICT FaceKit, "
                 "on an ICT actor with a rotating jaw, held-out ICT shapes and ICT with combination shapes; a "
                 "capture session (the synthetic actor's shapes plus 0, 150 or 400 captured poses, with and "
                 "without its jaw rig, and ICT with 150 captured frames); each with clean and noisy bundles. "
                 "Prints one table per set, writes accuracy.csv and heat maps (PNG). See docs/accuracy.md.",
                 ("lgi bench --out lgi-bench --frames 300 --no-ict",),
                 outputs='DIR/accuracy.csv and DIR/heatmaps_*.png; the tables on stdout.')
    g = s.add_argument_group("inputs")
    add_flags({"inputs": g}, BenchOptions, "inputs")
    g = s.add_argument_group("outputs")
    g.add_argument("--out", default="lgi-bench", metavar="DIR", help="tables and pictures (default %(default)s)")
    s.set_defaults(func=cmd_bench)


def _add_cache(sub: argparse._SubParsersAction) -> None:
    """The ``lgi cache`` command's parser."""
    s = _command(sub, "cache", "list or trim the rebuild's stage cache",
                 "List the stage results of a dataset rebuild's cache (OUT/.cache, or the rebuild's cache folder): "
                 "stage, key, size, last use; or remove old ones. Results in use by a running rebuild are left "
                 "alone.",
                 ("lgi cache ls rebuild-out", "lgi cache prune rebuild-out --keep 2 --older-than 30"),
                 outputs='no files: ls prints stage, key, size and last use; prune removes results.')
    g = s.add_argument_group("inputs")
    g.add_argument("action", choices=["ls", "prune"], metavar="ls|prune",
                   help="ls: list the results; prune: remove those --keep and --older-than say")
    g.add_argument("cache_dir", metavar="CACHE_DIR", help="the rebuild's OUT (its .cache) or the cache folder")
    add_flags({"prune": s.add_argument_group("prune")}, PruneOptions)
    s.set_defaults(func=cmd_cache)


def _add_demo(sub: argparse._SubParsersAction) -> None:
    """The ``lgi demo`` command's parser."""
    s = _command(sub, "demo", "run the main job end to end on the built-in synthetic actor",
                 "Build the synthetic actor, index it with its jaw rig, reconstruct its performance (frames not in "
                 "the dataset) with lgi reconstruct's defaults and compare with the truth; prints the figures "
                 "(speed, error against the truth in mm) and where the outputs are.",
                 ("lgi demo --out lgi-demo --vertices 5000 --frames 60",),
                 outputs="DIR/dataset/, DIR/markers.csv, DIR/bundles.csv, DIR/jaw_rig.npz, DIR/truth.npz (the "
                         "synthetic actor), DIR/index/, and the reconstruction: DIR/meshes.npz, DIR/diagnostics.csv, "
                         "DIR/per_frame.csv, DIR/run.json, and its review page DIR/review/.")
    g = s.add_argument_group("outputs")
    g.add_argument("--out", default="lgi-demo", metavar="DIR", help="output directory (default %(default)s)")
    _quiet(g)
    add_flags({"actor and performance": s.add_argument_group("actor and performance")}, DemoOptions)
    s.set_defaults(func=cmd_demo)


def _add_review(sub: argparse._SubParsersAction) -> None:
    """The ``lgi review`` command's parser."""
    s = _command(sub, "review", "write a shot's review page (3D, colour maps, markers, curves)",
                 "Write REVIEW_DIR/index.html and its data scripts: the reconstruction in 3D (orbit, zoom, pan; "
                 "play, step, slider, speed), colour maps in mm (distance to the truth, the correction's size, the "
                 "distance from another reconstruction, the distance to scans on the frames lgi compare measured, "
                 "where the actor's rig falls short of the shot after lgi rig-solve), "
                 "the markers coloured by their status per frame (the diagnostics row on hover or click), per-frame "
                 "curves and the run's summary. Open it from the file system: no server, no network. See "
                 "docs/review.md.",
                 ("lgi review lgi-demo --index lgi-demo/index --truth lgi-demo/truth.npz --out lgi-demo/review",
                  "lgi review recon --index index --scans recon/compare --out recon/review"),
                 outputs="REVIEW_DIR/index.html, viewer.js, review_meta.js, review_frames.js and frames/ "
                         "(overview.html, every Nth frame; block_NNNNN.html, the frames, which the page loads as they "
                         "are shown) (replaced as a whole).")
    g = s.add_argument_group("inputs")
    g.add_argument("recon_dir", metavar="RECON_DIR", help="a reconstruction (lgi reconstruct's OUT_DIR)")
    g.add_argument("--index", required=True, metavar="INDEX_DIR",
                   help="the index it was reconstructed with (required, no default)")
    g.add_argument("--truth", metavar="TRUTH_NPZ",
                   help="true surfaces, an npz with vertices (F, V, 3) in cm (lgi synth's truth.npz): adds the "
                        "distance-to-truth map (mm) and error curves (default: none)")
    g.add_argument("--compare", metavar="OTHER_RECON_DIR",
                   help="another reconstruction of the shot on the same mesh (e.g. --method blendshape): adds the "
                        "distance between the two (mm) as a colour map (default: none)")
    g.add_argument("--scans", metavar="COMPARE_DIR",
                   help="the folder lgi compare --out wrote for this reconstruction: adds the distance to the scan "
                        "(mm) as a colour map on the frames compared with one (vertices the scan does not cover in "
                        "grey) and marks those frames on the curves (default: none)")
    g.add_argument("--rig-solve", metavar="RIG_SOLVE_DIR",
                   help="the folder lgi rig-solve --out wrote for this reconstruction: adds where the rig falls short, "
                        "the distance from the rig's playback of the solved curves to the reconstruction (mm), as a "
                        "colour map per frame and its RMS as a curve (default: none)")
    g.add_argument("--rig", metavar="RIG_DIR",
                   help="with --rig-solve: the rig dataset (lgi rig-generate) its curves drive (default: the one "
                        "RIG_SOLVE_DIR/solve.json names)")
    g = s.add_argument_group("outputs")
    g.add_argument("--out", required=True, metavar="REVIEW_DIR",
                   help="the page's folder (replaced as a whole; required, no default)")
    g.add_argument("--fps", type=float, default=30.0, metavar="F",
                   help="the shot's frame rate, frames per second: playback at speed 1x (default %(default)s)")
    g.add_argument("--step", type=float, default=10.0, metavar="UM",
                   help="quantisation step of the positions the page shows, micrometres: they are within half of "
                        "it; finer steps make a larger page (default %(default)s; 0: the finest the shot's range "
                        "allows)")
    s.set_defaults(func=cmd_review)


def _add_layout(sub: argparse._SubParsersAction) -> None:
    """The ``lgi layout`` command's parser."""
    s = sub.add_parser("layout", help="design a marker layout by integer programming, or compare layouts",
                       description="Marker layouts: design one by integer programming (after Zell et al.), or "
                                   "measure one on held-out shapes. See docs/layout_design.md.",
                       epilog=_epilog(None, ("lgi layout design synth/dataset --count 60 --symmetric --out "
                                             "markers60.csv",
                                             "lgi layout evaluate synth/dataset --markers markers60.csv")),
                       formatter_class=_Formatter)
    lsub = s.add_subparsers(dest="layout_command", required=True, metavar="ACTION",
                            help="design or evaluate; `lgi layout ACTION --help` describes its options")
    d = _command(lsub, "design", "design a layout by integer programming (SciPy milp / HiGHS)",
                 "Choose COUNT marker positions on the dataset's neutral covering the motion of its shapes "
                 "(docs/layout_design.md); write a markers CSV for lgi build. Exit 2 when the request cannot be met "
                 "(count too high for the spacing: the message says how many fit).",
                 ("lgi layout design synth/dataset --count 60 --symmetric --min-spacing 8 --out markers60.csv",),
                 outputs='MARKERS_CSV: the layout, for lgi build.')
    g = d.add_argument_group("inputs")
    g.add_argument("dataset_dir", metavar="DATASET_DIR", help="the shape dataset")
    g.add_argument("--held-out", metavar="PATTERN",
                   help="shapes the design ignores (shell patterns or auto, as lgi layout evaluate --held-out), so "
                        "that a layout is evaluated on shapes it was not designed for (default: none)")
    g = d.add_argument_group("constraints")
    g.add_argument("--count", required=True, type=int, metavar="N", help="number of markers")
    g.add_argument("--symmetric", action="store_true",
                   help="markers in mirror pairs across the face's symmetry plane (x = c), selected together")
    g.add_argument("--min-spacing", type=float, default=8.0, metavar="MM",
                   help="smallest distance between two markers, mm (default %(default)s)")
    g.add_argument("--exclude", default="auto", metavar="SPEC",
                   help="where paint cannot go, comma-separated: auto (the dataset's eyes, inner lips, borders), "
                        "none, FIRST:LAST (vertex indices), boundary:MM, or a vertex index file (default %(default)s)")
    g.add_argument("--epsilon", type=float, default=0.5, metavar="E",
                   help="Zell's threshold: every shape gets a marker moving >= E x its largest motion "
                        "(default %(default)s; 0: off)")
    g = d.add_argument_group("scheduling")
    g.add_argument("--time-limit", type=float, default=60.0, metavar="SECONDS",
                   help="seconds for the solver; the best layout found is kept, with a warning (default %(default)s)")
    g = d.add_argument_group("outputs")
    g.add_argument("--out", required=True, metavar="MARKERS_CSV", help="the marker layout to write")
    d.set_defaults(func=cmd_layout_design)
    e = _command(lsub, "evaluate", "held-out error of a layout (LGI and the blendshape baseline)",
                 "Build the index for the layout on the dataset minus the held-out shapes, reconstruct each "
                 "held-out shape from its own bundles with LGI and with the blendshape fit, and print vertex RMS / "
                 "p95 / max (mm).",
                 ("lgi layout evaluate synth/dataset --markers synth/markers.csv --held-out 'smile*' "
                  "--out errors.csv",),
                 outputs='the table on stdout; with --out, the per-shape table (CSV).')
    g = e.add_argument_group("inputs")
    g.add_argument("dataset_dir", metavar="DATASET_DIR", help="the shape dataset")
    g.add_argument("--markers", required=True, metavar="MARKERS_CSV", help="the marker layout to measure")
    g.add_argument("--held-out", default="auto", metavar="PATTERN",
                   help="held-out shapes: shell patterns on names, comma-separated; every5: every fifth shape in the "
                        "dataset's order from the third; auto: the accuracy benchmark's six ICT shapes when the "
                        "dataset has them, else every5 (default %(default)s)")
    g = e.add_argument_group("outputs")
    g.add_argument("--out", metavar="CSV", help="also write the per-shape table (method, shape, rms, p95, max mm)")
    e.set_defaults(func=cmd_layout_evaluate)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lgi", description=DESCRIPTION, epilog=EPILOG, formatter_class=_Formatter)
    p.add_argument("--version", action="version", version=f"lgi {__version__}")
    p.add_argument("--debug", action="store_true",
                   help="on an error, also print the traceback (anywhere on the command line)")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND",
                           help="the job to run; `lgi COMMAND --help` describes its options")
    _add_import(sub)
    _add_synth(sub)
    _add_track(sub)
    _add_bundles(sub)
    _add_build(sub)
    _add_reconstruct(sub)
    _add_verify(sub)
    _add_rig(sub)
    _add_rig_generate(sub)
    _add_rig_solve(sub)
    _add_augment(sub)
    _add_calibrate(sub)
    _add_export(sub)
    _add_compare(sub)
    _add_bench(sub)
    _add_cache(sub)
    _add_demo(sub)
    _add_review(sub)
    _add_layout(sub)
    return p


class _WarningHandler(logging.Handler):
    """Prints the library's warnings (what it could not do as asked) as ``lgi CMD: warning: ...`` on stderr."""

    def __init__(self, command: str) -> None:
        super().__init__(logging.WARNING)
        self.command = command

    def emit(self, record: logging.LogRecord) -> None:
        print(f"lgi {self.command}: warning: {record.getMessage()}", file=sys.stderr)


def _in_chain(exc: BaseException | None, kind: type) -> BaseException | None:
    """The first exception of ``kind`` in ``exc``'s cause chain: numba's dispatcher wraps a Ctrl-C that lands in
    a compiled kernel in a SystemError, and flows and task runners wrap the errors of their tasks."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, kind):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _quiet_stdout() -> None:
    """Point stdout at /dev/null: a reader that went away (``lgi ... | head``) must not turn the flush at exit
    into an error."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated()


def main(argv: list[str] | None = None) -> int:
    """Run one ``lgi`` command; returns the exit status (README: 0 success, 1 a check failed, 2 bad input, 3 an
    internal error, 130 interrupted, 143 terminated by SIGTERM). No traceback reaches the user unless
    ``--debug`` is given."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    if debug:
        argv.remove("--debug")
    parser = build_parser()
    args = parser.parse_args(argv)
    lgi_log = logging.getLogger("lgi")
    for h in [h for h in lgi_log.handlers if isinstance(h, _WarningHandler)]:
        lgi_log.removeHandler(h)
    handler = _WarningHandler(args.command)
    lgi_log.addHandler(handler)
    if getattr(args, "flow", False):
        import os

        # A first run creates the local Prefect database, which takes longer than Prefect's default wait.
        os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
        if not debug:
            # The command prints its own report and errors; Prefect's console log would add a traceback for a
            # task that failed on bad input. PREFECT_LOGGING_LEVEL set by the user wins; the UI keeps the logs.
            os.environ.setdefault("PREFECT_LOGGING_LEVEL", "CRITICAL")
            # The ephemeral server's own services log too (an offline machine's failed telemetry is an ERROR).
            os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", "CRITICAL")
            # ... and so does docket, the server's task queue (a locked database on a first run, which it retries).
            logging.getLogger("docket").setLevel(logging.CRITICAL)
    name = f"lgi {args.command}"
    import signal

    try:
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    except ValueError:  # not the main thread (a caller embedding lgi): leave SIGTERM alone
        previous = None
    interrupted = None
    if getattr(args, "flow", False) and previous is not None:
        from lgi.orchestration import INTERRUPTED

        interrupted = INTERRUPTED
        interrupted.clear()

        def on_sigint(signum: int, frame: object) -> None:
            interrupted.set()
            raise KeyboardInterrupt

        previous_int = signal.signal(signal.SIGINT, on_sigint)
    try:
        code = _run(args, name, debug, interrupted)
        if interrupted is not None and interrupted.is_set() and code == 0:
            # Prefect swallowed the KeyboardInterrupt where it landed, and the run still completed.
            print(f"{name}: interrupted after the outputs of this run were written", file=sys.stderr)
            return 130
        return code
    finally:
        if interrupted is not None:
            # The caller's handler back (the entry point's, which after the run only notes a signal).
            signal.signal(signal.SIGINT, previous_int)
        lgi_log.removeHandler(handler)  # a caller running several commands in one process gets each its own
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _run(args: argparse.Namespace, name: str, debug: bool, interrupted=None) -> int:
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:
        _quiet_stdout()
        return 0 if not debug else 1
    except BaseException as exc:  # noqa: BLE001 - the one place that turns every failure into an exit status
        if isinstance(exc, SystemExit):
            raise
        if debug:
            import traceback

            traceback.print_exc()
        stop = _in_chain(exc, KeyboardInterrupt)
        if stop is None and interrupted is not None and interrupted.is_set():
            stop = KeyboardInterrupt()  # swallowed by Prefect where it landed: what failed after it is its effect
        if stop is not None:
            how = "terminated (SIGTERM)" if isinstance(stop, Terminated) else "interrupted"
            print(f"{name}: {how}; the outputs of this run were not written", file=sys.stderr)
            # The local Prefect server is torn down after this; a database connection cancelled with it is
            # logged by SQLAlchemy with its traceback (seen once in four interrupted flow runs), which is
            # noise once the run has been reported as stopped.
            logging.getLogger("sqlalchemy").setLevel(logging.CRITICAL)
            return 143 if isinstance(stop, Terminated) else 130
        err = _in_chain(exc, LgiError)
        if err is not None:
            print(f"{name}: error: {err}", file=sys.stderr)
            return 2
        if isinstance(exc, OSError):
            where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
            print(f"{name}: error: {where}{exc.strerror or exc}", file=sys.stderr)
            return 2
        print(f"{name}: internal error: {type(exc).__name__}: {exc} (a bug in lgi; run with --debug for the "
              "traceback and report it)", file=sys.stderr)
        return 3


if __name__ == "__main__":
    sys.exit(main())
