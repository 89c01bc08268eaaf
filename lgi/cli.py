"""The ``lgi`` command line. Its interface is a contract (documented in the README): add, never break."""

from __future__ import annotations

import argparse
import logging
import sys

from lgi import __version__
from lgi.errors import InputError, LgiError, Terminated


def _import_options(args: argparse.Namespace):
    from lgi.jobs.dataset import ImportOptions

    return ImportOptions(neutral=args.neutral, include=args.include, exclude=args.exclude,
                         rigid_vertices=args.rigid_vertices, units=args.units, deltas=args.deltas,
                         identity=args.identity)


def cmd_import(args: argparse.Namespace) -> int:
    from lgi.jobs.dataset import import_dataset, import_report

    opts = _import_options(args)
    if args.flow:
        from lgi.jobs.dataset import check_rebuild
        from lgi.orchestration.rebuild import rebuild_dataset
        from lgi.pipeline.stages import rebuild_report

        check_rebuild(args.shapes_dir, args.out, opts, args.markers)  # before Prefect starts

        s = rebuild_dataset(args.shapes_dir, args.out, markers=args.markers, **opts.to_json())
        for line in rebuild_report(s):
            print(line)
        return 0 if "verification" not in s or s["verification"]["passed"] else 1
    if args.markers:
        raise InputError("--markers builds and verifies an index: it needs --flow (or run lgi build and lgi verify)")
    for line in import_report(import_dataset(args.shapes_dir, args.out, opts, show_progress=not args.quiet)):
        print(line)
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from lgi.jobs.synthetic import SynthOptions, synth_report, write_synthetic

    opts = SynthOptions(vertices=args.vertices, frames=args.frames, seed=args.seed, hmc=args.hmc, lens=args.lens,
                        image_size=args.image_size, dot_noise=args.dot_noise, board_views=args.board_views,
                        rig_flex=args.rig_flex, contour_noise=args.contour_noise, actor=args.actor,
                        slip=args.slip)
    for line in synth_report(write_synthetic(args.out, opts, show_progress=not args.quiet), opts):
        print(line)
    return 0


def cmd_track(args: argparse.Namespace) -> int:
    from lgi.jobs.capture import TrackFootageOptions, track, track_report

    opts = TrackFootageOptions(tracks=args.tracks, dataset=args.dataset, units=args.units, labels=args.labels,
                               reference_frame=args.reference_frame, helmet=args.helmet, gate=args.gate,
                               dot_size=args.dot_size, index=args.index)
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
    from lgi.jobs.index import build, build_report

    summary = build(args.dataset_dir, args.markers, args.out, _index_options(args), args.jaw_rig,
                    show_progress=not args.quiet)
    for line in build_report(summary):
        print(line)
    return 0


def _reconstruct_options(args: argparse.Namespace):
    from lgi.jobs.reconstruct import ReconstructOptions

    return ReconstructOptions(temporal_weight=args.temporal_weight, spatial_weight=args.spatial_weight,
                              smooth=args.smooth, jaw_smooth=args.jaw_smooth, noise=args.noise, method=args.method,
                              jaw=args.jaw, max_gap=args.max_gap, bilateral=args.bilateral, obj=args.obj,
                              usd=args.usd, plot=args.plot, fps=args.fps, chunk_size=args.chunk_size,
                              observations=args.observations, calib=args.calib, contours=args.contours,
                              far_field=args.far_field)


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from lgi.jobs.reconstruct import check_output, preflight, reconstruct, report_lines

    opts = _reconstruct_options(args)
    if args.dask and not args.flow:
        raise InputError("--dask runs the flow's chunk tasks on Dask: it needs --flow")
    if args.flow:
        check_output(args.out, (args.index_dir, args.bundles, opts.jaw, opts.observations, opts.calib,
                                opts.contours))
        preflight(args.index_dir, args.bundles, opts)  # bad input is refused here, before Prefect starts
        from lgi.orchestration.reconstruct import reconstruct_shot

        summary = reconstruct_shot(args.index_dir, args.bundles, args.out, dask_address=args.dask, **opts.to_json())
    else:
        summary = reconstruct(args.index_dir, args.bundles, args.out, opts, show_progress=not args.quiet)
    for line in report_lines(summary):
        print(line)
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    from lgi.jobs.index import VerifyOptions, verify, verify_report

    table, summary = verify(args.index_dir, VerifyOptions(tolerance=args.tolerance, shapes=args.shapes,
                                                          spatial_weight=args.spatial_weight),
                            show_progress=not args.quiet)
    for line in verify_report(table, summary):
        print(line)
    return 0 if summary["passed"] else 1


def cmd_augment(args: argparse.Namespace) -> int:
    from lgi.jobs.dataset import AugmentOptions, augment_dataset, augment_report

    opts = AugmentOptions(linear=args.linear, simulate=args.simulate, budget=args.budget,
                          levels=AugmentOptions.parse_list(args.levels, float, "--levels"),
                          orders=AugmentOptions.parse_list(args.orders, int, "--orders"), seed=args.seed,
                          include=args.include, requires=args.requires, thickness=args.thickness,
                          iterations=args.iterations)
    s = augment_dataset(args.dataset_dir, args.out, opts, args.jaw_rig, args.markers, show_progress=not args.quiet)
    for line in augment_report(s):
        print(line)
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from lgi.jobs.capture import CalibrateOptions, calibrate, calibrate_report

    opts = CalibrateOptions(board=args.board, rational=args.rational, fisheye=args.fisheye, yaml=args.yaml)
    for line in calibrate_report(calibrate(args.images_dir, args.out, opts)):
        print(line)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from lgi.jobs.export import ExportOptions, export, export_report

    opts = ExportOptions(usd=args.usd, exr=args.exr, exr_size=args.exr_size, fps=args.fps)
    for line in export_report(export(args.recon_dir, args.index, opts, show_progress=not args.quiet), opts):
        print(line)
    return 0


def cmd_rig(args: argparse.Namespace) -> int:
    from lgi.jobs.index import RigOptions, fit_jaw_rig, rig_report

    for line in rig_report(fit_jaw_rig(args.dataset_dir, args.out, RigOptions(args.jaw_vertices, args.shapes))):
        print(line)
    return 0


def cmd_rig_generate(args: argparse.Namespace) -> int:
    from lgi.jobs.rig import RigGenerateOptions, generate_rig, rig_generate_report

    opts = RigGenerateOptions(correctives=args.correctives, transfer=args.transfer, controls=args.controls,
                              coverage_mm=args.coverage, fit_mm=args.fit)
    for line in rig_generate_report(generate_rig(args.template, args.index, args.out, opts, usd=args.usd,
                                                 show_progress=not args.quiet)):
        print(line)
    return 0


def cmd_rig_solve(args: argparse.Namespace) -> int:
    from lgi.jobs.rig_solve import RigSolveOptions, rig_solve, rig_solve_report

    opts = RigSolveOptions(smooth=args.smooth, vertices=args.vertices, robust=args.robust, fps=args.fps)
    for line in rig_solve_report(rig_solve(args.recon_dir, args.rig, args.out, opts, usd=args.usd,
                                           rig_usd=args.rig_usd, show_progress=not args.quiet)):
        print(line)
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from lgi.jobs.bench import BenchOptions, bench

    bench(args.out, BenchOptions(frames=args.frames, noise=args.noise, ict=args.ict, no_ict=args.no_ict))
    return 0


def cmd_cache(args: argparse.Namespace) -> int:
    from lgi.jobs.cache import PruneOptions, cache_report, list_cache, prune_cache

    if args.action == "ls":
        lines = cache_report(list_cache(args.cache_dir))
    else:
        opts = PruneOptions(keep=args.keep, older_than=args.older_than)
        lines = cache_report(prune_cache(args.cache_dir, opts), removed=True)
    for line in lines:
        print(line)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from lgi.jobs.synthetic import DemoOptions, demo

    demo(args.out, DemoOptions(vertices=args.vertices, frames=args.frames, seed=args.seed),
         show_progress=not args.quiet)
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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lgi", description="Facial performance capture by Local Geometric Indexing.")
    p.add_argument("--version", action="version", version=f"lgi {__version__}")
    p.add_argument("--debug", action="store_true",
                   help="on an error, also print the traceback (anywhere on the command line)")
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
    s.add_argument("--flow", action="store_true",
                   help="run the Prefect rebuild-dataset flow (cached stages, artifacts): OUT becomes a folder with "
                        "dataset/ and, with --markers, index/ and verification/")
    s.add_argument("--markers", metavar="MARKERS_CSV", help="with --flow: also build and verify the index")
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
    s.add_argument("--actor", type=int, default=0, metavar="SEED",
                   help="another actor: proportions and expression details drawn from SEED (default 0: the default "
                        "actor), same mesh topology")
    s.add_argument("--hmc", action="store_true",
                   help="also render head-mounted camera footage into DIR/hmc (frames, board views, true cameras)")
    s.add_argument("--lens", choices=["fisheye", "pinhole"], default="fisheye", help="HMC lens model (fisheye)")
    s.add_argument("--image-size", default="1280x1024", metavar="WxH", help="HMC image size (1280x1024)")
    s.add_argument("--dot-noise", type=float, default=0.3, metavar="PX",
                   help="random offset of each painted dot per camera and frame, px (0.3)")
    s.add_argument("--board-views", type=int, default=15, metavar="N", help="calibration board views (15)")
    s.add_argument("--rig-flex", type=float, default=0.0, metavar="DEG",
                   help="turn camera 1 by this angle during the shot, after calibration (0; see lgi track --helmet)")
    s.add_argument("--contour-noise", type=float, default=0.0, metavar="PX",
                   help="Gaussian noise of the true lip contours in DIR/hmc/lip_contours.csv, px (0)")
    s.add_argument("--slip", choices=["smooth", "jolts"], default="smooth",
                   help="how the helmet moves on the head during the shot: smooth (a slow drift of up to 1 deg and "
                        "1.5 mm) or jolts (that drift plus sudden shifts of 0.5-1.5 deg and 1-3 mm over 1-3 frames, "
                        "each then held, and a vibration of about 0.02 deg / 0.03 mm) (default: smooth)")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=cmd_synth)

    s = sub.add_parser("track", help="track painted dots in stereo HMC footage and write bundles",
                       description="Detect dots, label the reference frame (rigid fit of the marker layout, or "
                                   "--labels), track with anchor frames, triangulate, remove head motion; write the "
                                   "bundles file and a 2D tracks table (Parquet) with reprojection errors.")
    s.add_argument("footage_dir", metavar="FOOTAGE_DIR", help="cam0/ and cam1/ frames (same names), or left*/right*")
    s.add_argument("--calib", required=True, metavar="CALIB_JSON", help="lgi calibrate's output")
    s.add_argument("--markers", required=True, metavar="CSV",
                   help="marker layout; its x,y,z columns give the neutral positions unless --dataset is given")
    s.add_argument("--out", required=True, metavar="BUNDLES", help="bundles file (.csv or .parquet)")
    s.add_argument("--index", metavar="INDEX_DIR", default=None,
                   help="the actor's LGI index (lgi build): solve each frame's head pose with the face (the jaw and "
                        "the shape weights) instead of assuming the least-moving markers rigid; the bundles are then "
                        "in the index's head frame (default: none, the stable-marker fit)")
    s.add_argument("--dataset", metavar="DIR", help="dataset whose neutral places the markers (and sets the units)")
    s.add_argument("--units", default="cm", choices=["mm", "cm", "m"],
                   help="units of the marker file's positions without --dataset (cm); the bundles are written "
                        "in cm, as datasets are stored")
    s.add_argument("--labels", metavar="CSV", help="reference-frame labels: camera,x,y,marker")
    s.add_argument("--reference-frame", type=int, default=0, metavar="F", help="frame to label (0)")
    s.add_argument("--gate", type=float, default=12.0, metavar="PX", help="tracking search radius (12 px)")
    s.add_argument("--dot-size", type=float, default=9.0, metavar="PX",
                   help="typical painted dot diameter in the images (9 px): sets the detector's scale")
    s.add_argument("--tracks", metavar="PARQUET", help="2D tracks table (default OUT's stem + .tracks.parquet)")
    s.add_argument("--helmet", metavar="CSV",
                   help="markers fixed on the helmet (name,x,y,z in mm, calibration frame): refine the extrinsics "
                        "for this shot from them")
    s.set_defaults(func=cmd_track)

    s = sub.add_parser("bundles", help="evaluate markers on dataset shapes (one frame per shape)",
                       description="Write a bundles file with one frame per dataset shape, and OUT.shapes.csv "
                                   "mapping frames to shape names.")
    s.add_argument("dataset_dir", metavar="DATASET_DIR")
    s.add_argument("--markers", required=True, metavar="MARKERS_CSV")
    s.add_argument("--out", required=True, metavar="BUNDLES", help=".csv or .parquet")
    s.add_argument("--shapes", metavar="PATTERN", help="only shapes matching these shell patterns")
    s.set_defaults(func=cmd_bundles)

    s = sub.add_parser("build", help="build the LGI index of a dataset for a marker layout",
                       description="Build the local geometric index: per-bundle point clouds (pruned), overlapping "
                                   "simplices, search grids, natural-neighbour weights. See docs/indexing.md.")
    s.add_argument("dataset_dir", metavar="DATASET_DIR")
    s.add_argument("--markers", required=True, metavar="MARKERS_CSV")
    s.add_argument("--out", required=True, metavar="INDEX_DIR")
    g = s.add_argument_group("pruning (lengths in dataset units)")
    g.add_argument("--min-motion-rel", type=float, default=0.005, metavar="R",
                   help="drop a shape from a bundle's cloud if it moves the bundle less than R x the largest "
                        "motion (default 0.005)")
    g.add_argument("--min-motion-abs", type=float, default=1e-4, metavar="D", help="... or less than D (1e-4)")
    g.add_argument("--merge-tol", type=float, default=1e-4, metavar="D", help="merge points closer than D (1e-4)")
    g = s.add_argument_group("simplices")
    g.add_argument("--subsets", type=int, default=4, metavar="N", help="extra Delaunay tessellations of subsets (4)")
    g.add_argument("--subset-fraction", type=float, default=0.6, metavar="F", help="subset size (0.6)")
    g.add_argument("--knn", type=int, default=0, metavar="K", help="k of the nearest-neighbour fans (0 = none)")
    g.add_argument("--min-quality", type=float, default=0.02, metavar="Q", help="drop slivers below Q (0.02)")
    g.add_argument("--max-edge-rel", type=float, default=0.6, metavar="E",
                   help="drop extra simplices longer than E x the cloud's extent (0.6)")
    g.add_argument("--budget", type=int, default=20000, metavar="B", help="simplices per bundle at most (20000)")
    g.add_argument("--region-radius", type=float, default=3.0, metavar="R",
                   help="natural-neighbour region: within R (cm-equivalent) of a bundle (3.0)")
    g.add_argument("--seed", type=int, default=0)
    s.add_argument("--jaw-rig", metavar="RIG_NPZ",
                   help="jaw rig (npz with 'pivot' (3,) cm and 'weights' (V,)): shapes are stored unskinned and "
                        "frames unskinned, indexed and skinned back (lgi synth writes the synthetic actor's)")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=cmd_build)

    s = sub.add_parser("reconstruct", help="reconstruct meshes from a bundles file",
                       description="Write OUT_DIR/meshes.npz (vertices (F, V, 3) float32, frames), "
                                   "OUT_DIR/diagnostics.csv, OUT_DIR/per_frame.csv and, as asked, "
                                   "OUT_DIR/obj/frame_NNNNN.obj, OUT_DIR/shot.usdc, OUT_DIR/per_frame.png. "
                                   "A run replaces the outputs of an earlier one (and removes those it does "
                                   "not write); other files in OUT_DIR are left alone.")
    s.add_argument("index_dir", metavar="INDEX_DIR")
    s.add_argument("--bundles", required=True, metavar="BUNDLES")
    s.add_argument("--out", required=True, metavar="OUT_DIR")
    s.add_argument("--obj", action="store_true", help="also write one OBJ per frame")
    s.add_argument("--temporal-weight", type=float, default=0.02, metavar="MM",
                   help="preference for the previous frame's shapes, in mm of neighbour misfit (0.02; 0 = none)")
    s.add_argument("--spatial-weight", type=float, default=1e-3, metavar="MM",
                   help="tie-break toward shapes the neighbours agree on, in mm (1e-3; 0 = none)")
    s.add_argument("--smooth", type=int, default=1, metavar="WINDOW",
                   help="central moving average of each bundle's shape weights over WINDOW frames (1 = none)")
    s.add_argument("--far-field", default="5:15", metavar="START:END|off",
                   help="mm from the nearest marker over the skin: beyond START, a bundle whose weights predict the "
                        "markers beyond its neighbourhood clearly worse than the frame's global fit gives way to "
                        "that fit, wholly beyond END; local geometry carried far from every marker can "
                        "extrapolate (5:15; off = the bundles' weights everywhere)")
    s.add_argument("--noise", default="auto", metavar="MM|auto",
                   help="bundle noise per coordinate: 0 = exact bundles (the surface passes through each); above 0 "
                        "they are measurements: each marker's trajectory is smoothed (window chosen per marker by "
                        "Stein's unbiased risk estimate) and fitted, not interpolated; auto (default): estimated "
                        "from the shot's trajectories and reported")
    s.add_argument("--method", default="local", choices=["local", "simplex"],
                   help="local (default): a global fit of the jaw and shape weights, refitted per bundle over its "
                        "natural neighbours and its containing simplices' shapes; simplex: the paper's choice among "
                        "containing simplices only")
    s.add_argument("--jaw-smooth", type=int, default=None, metavar="WINDOW",
                   help="moving average of the jaw parameters (default: --smooth)")
    s.add_argument("--jaw", default="auto", metavar="auto|none|FILE",
                   help="with a jaw-rigged index: estimate the jaw per frame (auto) or read it from a CSV "
                        "(frame, open_deg, yaw_deg, roll_deg, forward_cm); 'none' needs an index without a rig")
    s.add_argument("--max-gap", type=int, default=0, metavar="N",
                   help="bridge a marker's missing runs of up to N frames by interpolating between the frames "
                        "around (0 = off, the default: a hidden marker's weights are fitted to its seen neighbours "
                        "in its own frame, which follows fast motion that interpolation misses)")
    s.add_argument("--flow", action="store_true",
                   help="run the job as the Prefect reconstruct-shot flow (chunks of frames as tasks, "
                        "artifacts): the same options and the same files as without it")
    s.add_argument("--chunk-size", type=int, default=60, metavar="N",
                   help="frames per task with --flow (60; the results do not depend on it)")
    s.add_argument("--dask", metavar="ADDRESS",
                   help="with --flow: run the chunk tasks on Dask, a scheduler address (tcp://host:8786) or local:N "
                        "(a local cluster of N processes); the results do not depend on it")
    s.add_argument("--usd", action="store_true", help="also write OUT_DIR/shot.usdc (animated mesh, see --fps)")
    s.add_argument("--fps", type=float, default=30.0, help="USD time codes per second (30)")
    s.add_argument("--plot", action="store_true", help="also write OUT_DIR/per_frame.png")
    s.add_argument("--observations", metavar="TRACKS.parquet",
                   help="the 2D tracks table of lgi track: a marker seen by one camera where the bundles lack it is "
                        "put on its viewing ray, at the depth a first reconstruction without it gives, and the shot "
                        "is reconstructed again through it (twice the solve time); writes "
                        "OUT_DIR/bundles_constrained.parquet and a constraint column in the diagnostics")
    s.add_argument("--calib", metavar="CALIB.json",
                   help="with --observations: the stereo calibration (default: the rig lgi track stored in the "
                        "table, refined by helmet dots if it was)")
    s.add_argument("--contours", metavar="CONTOURS.csv",
                   help="lip contours traced per frame and camera (frame, camera, curve, point, x, y; curve "
                        "upper_inner or lower_inner; px): the lip region is deformed so that the mesh's inner lip "
                        "edges meet them, keeping the bundles (needs --observations for the head pose and rig); "
                        "adds contour_px_before/after to the diagnostics")
    s.add_argument("--bilateral", metavar="SIGMA_FRAMES:SIGMA_MM[:SIGMA_SPACE_MM]",
                   help="bilateral filter of the bundles before solving: in time, and with the third value also "
                        "over the nearest markers (e.g. 1.5:0.5:10)")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=cmd_reconstruct)

    s = sub.add_parser("verify", help="reconstruct every dataset shape from its own bundles (paper 7.1)",
                       description="Print per-shape errors (RMS and max, mm); exit 1 if any RMS exceeds the tolerance.")
    s.add_argument("index_dir", metavar="INDEX_DIR")
    s.add_argument("--tolerance", type=float, default=0.01, metavar="MM", help="RMS tolerance in mm (0.01)")
    s.add_argument("--shapes", metavar="PATTERN", help="only shapes matching these shell patterns")
    s.add_argument("--spatial-weight", type=float, default=1e-3, metavar="MM")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=cmd_verify)

    s = sub.add_parser("rig", help="fit a jaw rig (hinge and skinning weights) from a dataset's jaw shapes",
                       description="Fit the jaw hinge and linear-blend-skinning weights from shapes in which given "
                                   "vertices move rigidly with the jaw (ICT: the lower teeth 19247:21450). Writes "
                                   "an npz for lgi build --jaw-rig.")
    s.add_argument("dataset_dir", metavar="DATASET_DIR")
    s.add_argument("--jaw-vertices", required=True, metavar="FIRST:LAST|FILE",
                   help="vertices moving rigidly with the jaw: an inclusive range or an index file")
    s.add_argument("--shapes", default="jaw*", metavar="PATTERN",
                   help="the jaw shapes (default 'jaw*'); the hinge is fitted from the openings among them (the jaw "
                        "vertices rotate about the lateral x axis), the others only get their jaw parameters")
    s.add_argument("--out", required=True, metavar="RIG_NPZ")
    s.set_defaults(func=cmd_rig)

    s = sub.add_parser("rig-generate", help="an actor-specific blendshape rig from a template rig (paper 7.7)",
                       description="Reconstruct each template control (and combinations, for correctives) on the "
                                   "actor with LGI: the template's displacements at the markers (scaled by the "
                                   "affine map between the neutrals unless --transfer add; the jaw by its "
                                   "parameters when the index has a jaw rig) are added to the actor's neutral "
                                   "bundles and fitted with the actor's shapes. Writes a shape dataset (shapes "
                                   "tagged control / corrective) and, with --usd, a UsdSkel rig (correctives as "
                                   "blend shapes carrying lgi:combination).")
    s.add_argument("--template", required=True, metavar="TEMPLATE_DATASET",
                   help="the template rig: a shape dataset on the actor's mesh topology")
    s.add_argument("--index", required=True, metavar="INDEX_DIR", help="the actor's LGI index")
    s.add_argument("--out", required=True, metavar="RIG_DIR", help="the actor's rig, as a shape dataset")
    s.add_argument("--correctives", default=None, metavar="PAIRS|auto",
                   help="combinations a+b[+c] (comma-separated) or 'auto' (the template's combination shapes, or "
                        "else up to 24 pairs moving the same markers); the template's combination shape (its parts "
                        "in any order) is used when it has one, else the sum of the parts")
    s.add_argument("--transfer", choices=["scale", "add"], default="scale",
                   help="template displacements scaled by the affine map between the neutrals (default) or added")
    s.add_argument("--controls", default=None, metavar="PATTERN",
                   help="template shapes to use as controls (shell patterns; default: every name without '+')")
    s.add_argument("--coverage", type=float, default=2.0, metavar="MM",
                   help="a combination whose bundles lie farther than this outside the actor's dataset takes the "
                        "template's corrective, transferred, and is reported (default 2; inf: always reconstruct)")
    s.add_argument("--fit", type=float, default=0.5, metavar="MM",
                   help="fit the actor's shapes to the transferred bundles as measurements with this noise, so the "
                        "template's own detail at the markers is not copied (default 0.5; 0: interpolate exactly)")
    s.add_argument("--usd", default=None, metavar="RIG.usda", help="also write the rig as UsdSkel blend shapes")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=cmd_rig_generate)

    s = sub.add_parser(
        "rig-solve", help="a reconstructed shot as animation curves of the actor's rig",
        description="Fit the rig's control weights (in [0, 1], correctives driven by the product of their controls') "
                    "to each reconstructed frame over the face region (robust Gauss-Newton, warm-started), then "
                    "clean the curves over time (a second-difference penalty solved over the shot: no lag). Writes "
                    "OUT_DIR/curves.csv (frame, control, value), residuals.csv (rig playback - reconstruction, RMS "
                    "and max mm per frame), vertex_error.npz/.png (where the rig falls short) and solve.json; with "
                    "--usd, a UsdSkel animation layer over the rig's USD.",
        epilog="example: lgi rig-solve shot/recon --rig actor_rig --out shot/anim --usd shot/anim.usda "
               "--rig-usd actor_rig.usda")
    s.add_argument("recon_dir", metavar="RECON_DIR", help="the reconstruction (lgi reconstruct's meshes.npz)")
    s.add_argument("--rig", required=True, metavar="RIG_DIR", help="the actor's rig dataset (lgi rig-generate)")
    s.add_argument("--out", required=True, metavar="OUT_DIR", help="folder for curves.csv, residuals.csv, ...")
    s.add_argument("--usd", default=None, metavar="ANIM.usda",
                   help="also write the shot as a UsdSkel animation of the rig (needs --rig-usd; default: none)")
    s.add_argument("--rig-usd", default=None, metavar="RIG.usda",
                   help="the rig's USD (lgi rig-generate --usd), checked against RIG_DIR and sublayered by the "
                        "animation (default: none)")
    s.add_argument("--smooth", type=float, default=4.0, metavar="FRAMES",
                   help="temporal regularisation: the period in frames whose wiggles the curves' penalty halves "
                        "(zero-phase, so no lag; default 4; 0: each frame fitted on its own)")
    s.add_argument("--vertices", type=int, default=4000, metavar="N",
                   help="face vertices fitted per frame, an even subsample (default 4000; 0: every vertex the rig "
                        "moves)")
    s.add_argument("--robust", type=float, default=3.0, metavar="TIMES",
                   help="Huber threshold in multiples of each frame's median vertex residual (default 3; 0: plain "
                        "least squares)")
    s.add_argument("--fps", type=float, default=30.0, metavar="FPS",
                   help="time codes per second of the USD animation (default 30)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar (default: shown)")
    s.set_defaults(func=cmd_rig_solve)

    s = sub.add_parser("augment", help="add in-between shapes to a dataset",
                       description="Add in-betweens: combinations of 2-3 compatible shapes at fixed weights, "
                                   "tagged with their sources (opposites such as jawLeft+jawRight are skipped; "
                                   "mouthClose only with jawOpen), as linear blends and/or simulated with a "
                                   "volume-preserving flesh model (the same combinations for both).")
    s.add_argument("dataset_dir", metavar="DATASET_DIR")
    s.add_argument("--out", required=True, metavar="DATASET_DIR2")
    s.add_argument("--linear", action="store_true", help="linear combinations of dataset shapes")
    s.add_argument("--simulate", action="store_true",
                   help="physically simulated in-betweens (volumetric flesh, volume kept, lips kept apart)")
    s.add_argument("--budget", type=int, default=200, metavar="N",
                   help="combinations to add at most, per method (200)")
    s.add_argument("--jaw-rig", metavar="RIG_NPZ", help="--simulate: the jaw carries the flesh's jaw side; lip contact")
    s.add_argument("--thickness", type=float, default=0.8, metavar="D",
                   help="--simulate: flesh thickness in dataset units (0.8)")
    s.add_argument("--iterations", type=int, default=60, metavar="N", help="--simulate: solver iterations (60)")
    s.add_argument("-q", "--quiet", action="store_true")
    s.add_argument("--levels", default="0.25,0.5,0.75,1", metavar="W,...", help="weights a source may take")
    s.add_argument("--orders", default="2,3", metavar="K,...", help="sources per combination")
    s.add_argument("--include", metavar="PATTERN", help="only these source shapes")
    s.add_argument("--requires", metavar="SHAPE=PARTNER,...",
                   help="shapes that appear only with a partner (default mouthClose=jawOpen)")
    s.add_argument("--markers", metavar="MARKERS_CSV",
                   help="also report per bundle how many points the in-betweens added and kept (augmentation.csv)")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=cmd_augment)

    s = sub.add_parser("calibrate", help="calibrate a stereo camera pair from chessboard or ChArUco images",
                       description="Detect the board, calibrate both cameras (rejecting outlier views, saying why) "
                                   "and the stereo extrinsics; write a documented JSON (and OpenCV YAML).")
    s.add_argument("images_dir", metavar="IMAGES_DIR", help="left*/right* images, or cam0/ and cam1/ folders")
    s.add_argument("--board", required=True, metavar="BOARD",
                   help="chessboard:COLSxROWS:SQUARE_MM (inner corners) or charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT "
                        "(squares; e.g. charuco:7x5:15:11:DICT_5X5_100)")
    s.add_argument("--out", required=True, metavar="CALIB_JSON")
    s.add_argument("--yaml", metavar="FILE", help="also write OpenCV YAML (K0, dist0, K1, dist1, R, T)")
    s.add_argument("--rational", action="store_true", help="OpenCV's rational distortion model (wide lenses)")
    s.add_argument("--fisheye", action="store_true", help="fisheye (equidistant) lens model")
    s.set_defaults(func=cmd_calibrate)

    s = sub.add_parser("export", help="export a reconstruction as USD and/or OpenEXR displacement maps",
                       description="Write RECON_DIR/meshes.npz as an animated USD mesh (time samples, UVs) and/or "
                                   "per-frame displacement maps in UV space (OpenEXR, float32, RGB = xyz, cm).")
    s.add_argument("recon_dir", metavar="RECON_DIR")
    s.add_argument("--index", required=True, metavar="INDEX_DIR", help="the index it was reconstructed with")
    s.add_argument("--usd", metavar="FILE", help=".usdc (binary) or .usda (text)")
    s.add_argument("--exr", metavar="DIR", help="one frame_NNNNN.exr per frame")
    s.add_argument("--exr-size", type=int, default=512, metavar="N", help="map width and height (512)")
    s.add_argument("--fps", type=float, default=30.0, help="USD time codes per second (30)")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=cmd_export)

    s = sub.add_parser("bench", help="compare LGI with the baselines on the same frames",
                       description="Run LGI, the blendshape fits (with and without the jaw rig), RBF weights + "
                                   "smooth and smooth interpolation on the synthetic held-out performance and, when "
                                   "../shared/data has ICT FaceKit, on an ICT actor with a rotating jaw, held-out ICT "
                                   "shapes and ICT with combination shapes; a capture session (the synthetic actor's "
                                   "shapes plus 0, 150 or 400 captured poses, with and without its jaw rig, and ICT "
                                   "with 150 captured frames); each with clean and noisy bundles. "
                                   "Prints one table per set, writes accuracy.csv and heat maps (PNG).")
    s.add_argument("--out", default="lgi-bench", metavar="DIR", help="tables and pictures (default ./lgi-bench)")
    s.add_argument("--frames", type=int, default=300, metavar="F", help="synthetic performance length (300)")
    s.add_argument("--noise", type=float, default=0.3, metavar="MM",
                   help="bundle noise of the noisy sets, per coordinate (0.3; 5 %% of marker-frames also missing)")
    s.add_argument("--ict", metavar="DIR", help="ICT FaceKit folder (default ../shared/data/ict-facekit)")
    s.add_argument("--no-ict", action="store_true", help="synthetic sets only (the performance and its sessions)")
    s.set_defaults(func=cmd_bench)

    s = sub.add_parser("cache", help="list or trim the rebuild's stage cache",
                       description="List the stage results of a dataset rebuild's cache (OUT/.cache, or the "
                                   "rebuild's --cache-dir), or remove old ones. Results in use by a running "
                                   "rebuild are left alone.")
    s.add_argument("action", choices=["ls", "prune"])
    s.add_argument("cache_dir", metavar="CACHE_DIR", help="the rebuild's OUT (its .cache) or the cache folder")
    s.add_argument("--keep", type=int, metavar="N", help="prune: keep the N most recently used results of each stage")
    s.add_argument("--older-than", type=float, metavar="DAYS", help="prune: remove results unused for DAYS days")
    s.set_defaults(func=cmd_cache)

    s = sub.add_parser("demo", help="run the main job end to end on the built-in synthetic actor",
                       description="Build the synthetic actor and run the pipeline on its performance; "
                                   "prints figures and where the outputs are.")
    s.add_argument("--out", default="lgi-demo", metavar="DIR", help="output directory (default ./lgi-demo)")
    s.add_argument("--vertices", type=int, default=20000, metavar="N")
    s.add_argument("--frames", type=int, default=240, metavar="F")
    s.add_argument("--seed", type=int, default=0, metavar="S")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=cmd_demo)

    s = sub.add_parser("layout", help="design a marker layout by integer programming, or compare layouts",
                       description="Marker layouts: design one by integer programming (after Zell et al.), or "
                                   "measure one on held-out shapes. See docs/layout_design.md.")
    lsub = s.add_subparsers(dest="layout_command", required=True, metavar="ACTION")
    d = lsub.add_parser("design", help="design a layout by integer programming (SciPy milp / HiGHS)",
                        description="Choose COUNT marker positions on the dataset's neutral covering the motion of "
                                    "its shapes (docs/layout_design.md); write a markers CSV for lgi build. Exit 2 "
                                    "when the request cannot be met (count too high for the spacing).")
    d.add_argument("dataset_dir", metavar="DATASET_DIR")
    d.add_argument("--count", required=True, type=int, metavar="N", help="number of markers")
    d.add_argument("--out", required=True, metavar="MARKERS_CSV")
    d.add_argument("--symmetric", action="store_true",
                   help="markers in mirror pairs across the face's symmetry plane (x = c), selected together")
    d.add_argument("--min-spacing", type=float, default=8.0, metavar="MM",
                   help="smallest distance between two markers, mm (default 8)")
    d.add_argument("--exclude", default="auto", metavar="SPEC",
                   help="where paint cannot go, comma-separated: auto (the dataset's eyes, inner lips, borders), "
                        "none, FIRST:LAST (vertex indices), boundary:MM, or a vertex index file (default auto)")
    d.add_argument("--held-out", metavar="PATTERN",
                   help="shapes the design ignores (shell patterns or auto, as lgi layout evaluate --held-out), so "
                        "that a layout is evaluated on shapes it was not designed for (default: none)")
    d.add_argument("--epsilon", type=float, default=0.5, metavar="E",
                   help="Zell's threshold: every shape gets a marker moving >= E x its largest motion (0.5; 0: off)")
    d.add_argument("--time-limit", type=float, default=60.0, metavar="S",
                   help="seconds for the solver; the best layout found is kept (60)")
    d.set_defaults(func=cmd_layout_design)
    e = lsub.add_parser("evaluate", help="held-out error of a layout (LGI and the blendshape baseline)",
                        description="Build the index for the layout on the dataset minus the held-out shapes, "
                                    "reconstruct each held-out shape from its own bundles with LGI and with the "
                                    "blendshape fit, and print vertex RMS / p95 / max (mm).")
    e.add_argument("dataset_dir", metavar="DATASET_DIR")
    e.add_argument("--markers", required=True, metavar="MARKERS_CSV")
    e.add_argument("--held-out", default="auto", metavar="PATTERN",
                   help="held-out shapes: shell patterns on names, comma-separated; every5: every fifth shape in the "
                        "dataset's order from the third; auto (default): the accuracy benchmark's six ICT shapes when "
                        "the dataset has them, else every5")
    e.add_argument("--out", metavar="CSV", help="also write the per-shape table (method, shape, rms, p95, max mm)")
    e.set_defaults(func=cmd_layout_evaluate)
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
            return 143 if isinstance(stop, Terminated) else 130
        err = _in_chain(exc, LgiError)
        if err is not None:
            print(f"{name}: error: {err}", file=sys.stderr)
            return 2
        if isinstance(exc, OSError):
            where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
            print(f"{name}: error: {where}{exc.strerror or exc}", file=sys.stderr)
            return 2
        if isinstance(exc, ValueError):
            print(f"{name}: error: {exc}", file=sys.stderr)
            return 2
        print(f"{name}: internal error: {type(exc).__name__}: {exc} (a bug in lgi; run with --debug for the "
              "traceback and report it)", file=sys.stderr)
        return 3


if __name__ == "__main__":
    sys.exit(main())
