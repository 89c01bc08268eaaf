"""The compare job: reconstructed frames against scans of the same moments, whatever the scans' topology.

``lgi compare`` calls :func:`compare` with a :class:`CompareOptions`; the measures are
:mod:`lgi.evaluation.compare` (what they mean: ``docs/compare.md``).

The reconstruction's ``meshes.npz`` holds vertices only; the triangles come from ``--index`` (the index the shot
was reconstructed with, or its dataset) or, without it, from the frame's OBJ that ``lgi reconstruct --obj`` wrote
into ``RECON_DIR/obj/``.

Regions (``--region``), one of:

* ``all``: every vertex (default);
* ``face``: the measured face area (the synthetic actor: ``|x| <= 7.5``, ``|y| <= 10`` cm; ICT: vertices 0-9408;
  any other mesh: every vertex), as ``lgi layout evaluate`` measures;
* ``marked``: the vertices the markers constrain (within the index's region radius of a bundle; needs an index);
* ``lips``: within 1.5 cm of the inner lip line (the synthetic actor and ICT), as the accuracy benchmark;
* ``FIRST:LAST``: a range of vertex indices (0-based, inclusive);
* a vertex index file (JSON list, text or ``.npy``, as ``lgi import --rigid-vertices`` reads).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lgi.errors import InputError
from lgi.io.atomic import reads
from lgi.jobs import options_from_dict
from lgi.options import Subset, declared, option
from lgi.units import MM_PER_CM

if TYPE_CHECKING:
    import pandas as pd

log = logging.getLogger(__name__)

#: What ``--out`` holds (replaced as a whole by each run).
OUTPUTS = ("summary.csv", "summary.json", "vertex_distances.parquet", "scan_distances.parquet", "heatmaps")
OUTPUT_CONTENTS = {"heatmaps": ("*.png",)}
REGIONS = ("all", "face", "marked", "lips")
#: The folder, inside a reconstruction's, where the reconstruct-shot flow writes its comparison with scans (a
#: re-run of the reconstruction removes it: it measured the earlier meshes).
IN_SHOT = "compare"
#: Row fields in summary.json only (not summary.csv columns).
JSON_ONLY = ("transform_cm", "vertices_sha256")
#: Below this share of the region covered a warning says the scan hardly overlaps the frame.
LOW_COVERAGE = 0.1


@declared
@dataclass(frozen=True)
class CompareOptions:
    """Options of ``lgi compare`` (:mod:`lgi.options`); ``frames`` are ``meshes.npz``'s frame numbers, paired
    with ``scans`` in order, or given with their scans in the ``pairs`` CSV."""

    frames: tuple[int, ...] = option(
        (), "a frame number of the reconstruction; repeat, one per --scan, in the same order (default: none; give "
        "pairs this way or with --pairs)", group="inputs", metavar="F", parse=int, append=True, name="--frame")
    scans: tuple[str, ...] = option(
        (), "a scan of that frame's moment (.obj, .ply, .stl or .off; in --units); repeat, one per --frame "
        "(default: none)", group="inputs", metavar="SCAN", append=True, name="--scan")
    pairs: str | None = option(
        None, "instead of --frame/--scan: a CSV with columns frame, scan (paths relative to the CSV's folder) "
        "(default: none)", group="inputs", metavar="CSV")
    index: str | None = option(
        None, "the index (or dataset) the shot was reconstructed with: the mesh's triangles (default: "
        "RECON_DIR/obj/frame_NNNNN.obj, written by lgi reconstruct --obj)", group="inputs", metavar="INDEX_DIR")
    align: str = option(
        "none", "rigid: first move the scan onto the reconstruction by ICP over the covered region, and report "
        "the transform; none: compare as given (default %(default)s)", group="method", choices=("none", "rigid"))
    region: str = option(
        "all", "vertices to measure: all, face (the face area), marked (what the markers constrain; needs "
        "--index), lips (the synthetic actor and ICT), FIRST:LAST (0-based vertex indices, inclusive) or a vertex "
        "index file (JSON list, text or .npy) (default %(default)s)", group="method", metavar="REGION")
    gate_mm: float = option(
        10.0, "closest points farther than this, mm, count as not covered (reconstruction) or outside (scan) "
        "(default %(default)s)", group="method", metavar="MM", name="--gate", units="mm")
    units: str = option(
        "cm", "units of the scan files, converted to cm like the reconstruction (default %(default)s)",
        group="inputs", choices=("mm", "cm", "m", "in"))
    out: str | None = option(
        None, "also write summary.csv/.json, per-vertex distances (Parquet) and heat maps (PNG) here (default: "
        "print only)", group="outputs", metavar="DIR")

    def __post_init__(self) -> None:
        from lgi.units import check_units

        object.__setattr__(self, "frames", tuple(self.frames or ()))
        object.__setattr__(self, "scans", tuple(str(s) for s in (self.scans or ())))
        check_units(self.units, "--units")
        if self.align not in ("none", "rigid"):
            raise InputError(f"--align must be none or rigid, not {self.align!r}")
        if isinstance(self.gate_mm, bool) or not isinstance(self.gate_mm, (int, float)) \
                or not math.isfinite(self.gate_mm) or self.gate_mm <= 0:
            raise InputError(f"--gate must be a positive number of mm, not {self.gate_mm!r}")
        if self.pairs and (self.frames or self.scans):
            raise InputError("give either --pairs CSV or --frame/--scan pairs, not both")
        if not self.pairs:
            if not self.frames or len(self.frames) != len(self.scans):
                raise InputError(f"give one --scan per --frame (got {len(self.frames)} --frame and "
                                 f"{len(self.scans)} --scan), or --pairs CSV")
        if not str(self.region).strip():
            raise InputError(f"--region is empty: give {', '.join(REGIONS)}, FIRST:LAST or a vertex index file")

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["frames"], d["scans"] = list(self.frames), list(self.scans)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any] | None) -> CompareOptions:
        return options_from_dict(cls, d, "compare")


def read_pairs(path: str | Path) -> list[tuple[int, Path]]:
    """``(frame, scan path)`` rows of a pairs CSV (columns ``frame, scan``; scan paths relative to its folder)."""
    from lgi.io.csvio import read_table

    df = read_table(path, "pairs file", ("frame", "scan"), numeric=("frame",))
    out = []
    for r, (f, s) in enumerate(zip(df["frame"], df["scan"], strict=True)):
        if f != int(f):
            raise InputError(f"frame {f!r} is not a whole number", path=path, line=r + 2)
        if not str(s).strip():
            raise InputError("empty scan path", path=path, line=r + 2)
        scan = Path(str(s).strip())
        out.append((int(f), scan if scan.is_absolute() else Path(path).parent / scan))
    return out


@dataclass
class Topology:
    """The reconstruction's mesh: ``triangles`` (T, 3) int64, ``neutral`` (V, 3) float64 cm or None,
    ``name`` (the dataset's name, for named regions), ``marked`` (V,) bool or None, ``source`` (where it came
    from)."""

    triangles: np.ndarray
    neutral: np.ndarray | None
    name: str | None
    marked: np.ndarray | None
    source: str
    n_vertices: int


def load_topology(recon_dir: str | Path, index: str | Path | None, frame: int) -> Topology:
    """The triangles of a reconstruction: from ``index`` (an LGI index or a shape dataset directory), else from
    ``recon_dir/obj/frame_NNNNN.obj`` (``lgi reconstruct --obj``)."""
    from lgi.dataset.mesh import triangulate

    if index is not None:
        d = Path(index)
        mpath = d / "manifest.json"
        if not mpath.is_file():
            raise InputError("--index: not an LGI index or shape dataset directory (no manifest.json)", path=d)
        try:
            fmt = json.loads(mpath.read_text()).get("format")
        except (json.JSONDecodeError, UnicodeDecodeError, AttributeError):
            fmt = None
        from lgi.dataset.shapes import FORMAT as DATASET_FORMAT

        if fmt == DATASET_FORMAT:
            from lgi.dataset.shapes import ShapeDataset

            ds = ShapeDataset.load(d, mmap=True)
            return Topology(ds.triangles.astype(np.int64), np.asarray(ds.neutral, np.float64), ds.info.get("name"),
                            None, f"dataset {d}", ds.n_vertices)
        from lgi.index.build import LGIIndex

        idx = LGIIndex.load(d)
        a = idx.arrays
        tri = triangulate(a["face_vertices"], a["face_offsets"])[0].astype(np.int64)
        marked = np.asarray(a["nn_region"], bool) if "nn_region" in a else None
        return Topology(tri, np.asarray(a["neutral"], np.float64), idx.manifest.get("dataset_info", {}).get("name"),
                        marked, f"index {d}", idx.n_vertices)
    obj = Path(recon_dir) / "obj" / f"frame_{frame:05d}.obj"
    if not obj.is_file():
        raise InputError("the reconstruction holds vertices only (no obj/ from lgi reconstruct --obj): pass --index "
                         "INDEX_DIR, the index it was reconstructed with (or its dataset)", path=recon_dir)
    from lgi.io.obj import read_obj

    mesh = read_obj(obj)
    tri = triangulate(mesh.face_vertices, mesh.face_offsets)[0].astype(np.int64)
    return Topology(tri, None, None, None, f"OBJ {obj}", mesh.n_vertices)


def region_mask(spec: str, topo: Topology, vertices: np.ndarray) -> tuple[np.ndarray, str]:
    """(V,) bool of ``--region`` (module docstring) and its description; ``vertices`` (V, 3) cm stand in for the
    neutral when the topology came from an OBJ."""
    from types import SimpleNamespace

    nv = topo.n_vertices
    neutral = topo.neutral if topo.neutral is not None else np.asarray(vertices, np.float64)
    ds = SimpleNamespace(neutral=neutral, triangles=topo.triangles, n_vertices=nv,
                         info={"name": topo.name})
    spec = str(spec).strip()
    if spec == "all":
        return np.ones(nv, bool), "every vertex"
    if spec == "face":
        from lgi.jobs.layout import measured_region

        return measured_region(ds)
    if spec == "marked":
        if topo.marked is None:
            raise InputError("--region marked needs --index INDEX_DIR (the index knows what the markers constrain)")
        return topo.marked.copy(), "the vertices the markers constrain (the index's region)"
    if spec == "lips":
        from lgi.evaluation.benchsets.core import lip_region
        from lgi.evaluation.benchsets.ict import _ict_lip_line
        from lgi.evaluation.benchsets.synthetic import _synthetic_lip_line
        from lgi.jobs.layout import ICT_N_VERTICES, SYNTHETIC_NAME, measured_region

        if topo.name == SYNTHETIC_NAME:
            line = _synthetic_lip_line(neutral)
        elif nv == ICT_N_VERTICES:
            line = _ict_lip_line(topo.triangles, nv)
        else:
            raise InputError("--region lips knows the synthetic actor's and ICT's lips only: give the lip vertices "
                             "as FIRST:LAST or a vertex index file")
        return lip_region(neutral, line, measured_region(ds)[0]), "within 1.5 cm of the inner lip line"
    from lgi.jobs.layout import region_mask as layout_region

    if spec in ("auto", "none") or spec.startswith("boundary:"):
        raise InputError(f"--region {spec!r}: give {', '.join(REGIONS)}, FIRST:LAST or a vertex index file")
    return layout_region(ds, spec, "--region")


def checked_pairs(options: CompareOptions) -> list[tuple[int, Path]]:
    """The ``(frame, scan path)`` pairs of ``options`` (``--pairs`` CSV or ``--frame``/``--scan``), each scan file
    there; what can be checked before the reconstruction exists (the flows call it before reconstructing)."""
    o = options
    pairs = read_pairs(o.pairs) if o.pairs else [(int(f), Path(s)) for f, s in zip(o.frames, o.scans, strict=True)]
    for _, s in pairs:
        if not s.is_file():
            raise InputError("scan not found", path=s)
    return pairs


def check_outputs(recon_dir: str | Path, options: CompareOptions, pairs: list[tuple[int, Path]]) -> None:
    """Refuse, before any work, an ``--out`` that cannot hold the outputs or would replace an input."""
    from lgi.io.atomic import check_job_folder

    o = options
    if o.out:
        check_job_folder(o.out, OUTPUTS, OUTPUT_CONTENTS, [recon_dir, o.index, o.pairs, *(s for _, s in pairs)])


def remove_outputs(folder: str | Path) -> None:
    """Remove ``folder`` if it holds only what :func:`compare` wrote there (a flow re-run without scans: the
    earlier run's distances were measured on other meshes); a folder holding anything else is left alone, with a
    warning."""
    from lgi.io.atomic import remove_recorded

    remove_recorded(Path(folder), OUTPUTS, "earlier scan comparison")


def heatmap_names(pairs: list[tuple[int, Path]]) -> list[str]:
    """The heat map file of each ``(frame, scan)`` pair, ``frame_NNNNN_SCANSTEM.png``; a name that an earlier pair
    has (two scans of one frame with one stem: ``a/scan.obj``, ``b/scan.ply``) gets ``_2``, ``_3``, ... so that no
    picture replaces another."""
    names, seen = [], set()
    for frame, scan in pairs:
        base = f"frame_{frame:05d}_{Path(scan).stem}"
        name, k = base, 1
        while name in seen:
            k += 1
            name = f"{base}_{k}"
        seen.add(name)
        names.append(f"{name}.png")
    return names


@reads("recon_dir")
def compare(recon_dir: str | Path, options: CompareOptions) -> dict[str, Any]:
    """``lgi compare``: each (frame, scan) pair measured; with ``options.out``, the tables and heat maps written
    there (all at the end, atomically: nothing on failure). Returns the summary (:func:`compare_report`)."""
    import pandas as pd

    from lgi.evaluation.compare import compare_frame, frame_fingerprint, read_scan, rotation_deg, stats_mm
    from lgi.io.npz import load_meshes

    o = options
    pairs = checked_pairs(o)
    check_outputs(recon_dir, o, pairs)
    src = Path(recon_dir) / "meshes.npz"
    if not src.is_file():
        raise InputError("no meshes.npz (run lgi reconstruct first)", path=recon_dir)
    z = load_meshes(src, required=("vertices", "frames"))
    vertices, frames = z["vertices"], np.asarray(z["frames"]).astype(np.int64)
    if vertices.ndim != 3 or vertices.shape[2] != 3 or len(frames) != len(vertices):
        raise InputError(f"vertices of shape {vertices.shape} and {len(frames)} frames: not a reconstruction",
                         path=src)
    row = {int(f): i for i, f in enumerate(frames)}
    for f, _ in pairs:
        if f not in row:
            raise InputError(f"frame {f} is not in the reconstruction (frames {frames.min()}-{frames.max()})",
                             path=src)
    topo = load_topology(recon_dir, o.index, pairs[0][0])
    if topo.n_vertices != vertices.shape[1]:
        raise InputError(f"the reconstruction has {vertices.shape[1]} vertices, the mesh of {topo.source} "
                         f"{topo.n_vertices}: give the index it was reconstructed with", path=src)
    region, region_text = region_mask(o.region, topo, vertices[row[pairs[0][0]]])
    if not region.any():
        raise InputError(f"--region {o.region!r} holds no vertex")
    gate = o.gate_mm / MM_PER_CM
    rows, vertex_tables, scan_tables, pictures = [], [], [], []
    for (f, scan_path), picture in zip(pairs, heatmap_names(pairs), strict=True):
        v = np.asarray(vertices[row[f]], np.float64)
        if not np.all(np.isfinite(v)):
            raise InputError("non-finite vertex positions", path=src, frame=f)
        scan = read_scan(scan_path, o.units)
        try:
            res = compare_frame(v, topo.triangles, scan, region, gate, o.align)
        except InputError as exc:
            if exc.path is not None:
                raise
            raise InputError(exc.message, path=scan_path, frame=f) from None
        n_cov = int(res.covered.sum())
        if n_cov == 0:
            raise InputError(f"the scan covers no part of the face: no vertex of frame {f} ({region_text}) is within "
                             f"{o.gate_mm:g} mm of the scan's surface away from its border (wrong scan, frame, "
                             f"units (--units {o.units}) or coordinate frame?)", path=scan_path)
        share = n_cov / int(region.sum())
        if share < LOW_COVERAGE:
            log.warning(f"{scan_path}: covers only {share * 100:.1f} % of frame {f}'s region")
        fwd = stats_mm(res.distance[res.covered])
        back = stats_mm(res.scan_distance[res.inside])
        r: dict[str, Any] = {
            "frame": f, "scan": str(scan_path), "align": o.align, "region_vertices": int(region.sum()),
            "covered": n_cov, "covered_share": share, **fwd,
            "mean_signed_mm": float(np.mean(res.signed[res.covered]) * MM_PER_CM),
            "scan_points": len(scan.vertices), "inside": int(res.inside.sum()),
            "inside_share": float(res.inside.mean()),
            **{f"scan_{k}": val for k, val in back.items()},
            "hausdorff_mm": float(np.nanmax([fwd["max_mm"], back["max_mm"]])),
            "rotation_deg": rotation_deg(res.transform),
            "translation_mm": float(np.linalg.norm(res.transform[:3, 3]) * MM_PER_CM),
            "icp_steps": res.icp_steps, "transform_cm": res.transform.tolist(),
            "vertices_sha256": frame_fingerprint(vertices[row[f]]),
            "heatmap": f"heatmaps/{picture}" if o.out else "",
        }
        rows.append(r)
        if o.out:
            idx = np.flatnonzero(region)
            vertex_tables.append(pd.DataFrame({
                "frame": f, "scan": str(scan_path), "vertex": idx,
                "distance_mm": (res.distance[idx] * MM_PER_CM).astype(np.float32),
                "signed_mm": (res.signed[idx] * MM_PER_CM).astype(np.float32), "covered": res.covered[idx]}))
            scan_tables.append(pd.DataFrame({
                "frame": f, "scan": str(scan_path), "scan_vertex": scan.file_index,
                "distance_mm": (res.scan_distance * MM_PER_CM).astype(np.float32), "inside": res.inside}))
            pictures.append((picture, v, np.where(res.covered, res.distance * MM_PER_CM, 0.0),
                             res.covered, f"frame {f} vs {scan_path.name}\nRMS {fwd['rms_mm']:.3f}, p95 "
                             f"{fwd['p95_mm']:.3f}, max {fwd['max_mm']:.3f} mm ({share * 100:.0f} % covered)"))
    s: dict[str, Any] = {"recon": str(Path(recon_dir).resolve()), "topology": topo.source, "region": region_text,
                         "gate_mm": o.gate_mm, "align": o.align, "pairs": rows}
    if o.out:
        _write(o.out, rows, vertex_tables, scan_tables, pictures, topo.triangles)
        s["out"] = str(Path(o.out).resolve())
    return s


def _write(out: str | Path, rows: list[dict[str, Any]], vertex_tables: list[pd.DataFrame],
           scan_tables: list[pd.DataFrame], pictures: list, triangles: np.ndarray) -> None:
    import pandas as pd

    from lgi.evaluation.render import heatmap_row
    from lgi.io.atomic import job_outputs

    with job_outputs(out, OUTPUTS, OUTPUT_CONTENTS) as stage:
        table = pd.DataFrame([{k: v for k, v in r.items() if k not in JSON_ONLY} for r in rows])
        table.to_csv(stage / "summary.csv", index=False, float_format="%.6g")
        (stage / "summary.json").write_text(json.dumps(rows, indent=1))
        pd.concat(vertex_tables, ignore_index=True).to_parquet(stage / "vertex_distances.parquet", index=False)
        pd.concat(scan_tables, ignore_index=True).to_parquet(stage / "scan_distances.parquet", index=False)
        (stage / "heatmaps").mkdir()
        for name, v, values, covered, title in pictures:
            # Only whole covered triangles are painted; a scan covering scattered vertices alone gets the whole mesh.
            mask = covered if np.all(covered[triangles], axis=1).any() else None
            heatmap_row(stage / "heatmaps" / name, v, triangles, {"distance to the scan": values},
                        mask=mask, label="distance (mm)", title=title)


def compare_report(s: dict[str, Any]) -> list[str]:
    """The summary as the lines ``lgi compare`` prints."""
    lines = [f"reconstruction {s['recon']} on the mesh of {s['topology']}; region: {s['region']}; gate "
             f"{s['gate_mm']:g} mm; alignment: {s['align']}",
             "frame  scan                      covered   RMS mm   p95 mm   max mm | scan inside  RMS mm   max mm | "
             "Hausdorff mm"]
    for r in s["pairs"]:
        name = Path(r["scan"]).name
        lines.append(f"{r['frame']:>5}  {name[:24]:<24} {r['covered_share'] * 100:6.1f} % {r['rms_mm']:8.3f} "
                     f"{r['p95_mm']:8.3f} {r['max_mm']:8.3f} | {r['inside_share'] * 100:9.1f} % "
                     f"{r['scan_rms_mm']:7.3f} {r['scan_max_mm']:8.3f} | {r['hausdorff_mm']:8.3f}")
        if r["align"] == "rigid":
            lines.append(f"       scan moved by {r['rotation_deg']:.3f} deg and {r['translation_mm']:.3f} mm "
                         f"({r['icp_steps']} ICP steps; the 4x4 transform, cm, in summary.json with --out)")
    if "out" in s:
        lines.append(f"tables and heat maps in {s['out']}: summary.csv, summary.json, vertex_distances.parquet, "
                     "scan_distances.parquet, heatmaps/")
    return lines


#: The comparison options a reconstruction with scans takes (``lgi reconstruct --scan-gate``, the flow's
#: ``scan_gate``, for ``lgi compare --gate``).
SHOT_SCAN_OPTIONS = Subset(CompareOptions, "scan_", ("units", "align", "region", "gate_mm"), "with --scans: ")


def shot_scan_options(scans: str | list | None, index_dir: str, out: str, **scan: Any) -> CompareOptions | None:
    """The compare job's options for a reconstruction's ``scans`` (a pairs CSV, or ``[frame, scan]`` pairs),
    writing into ``out/compare`` (``lgi reconstruct --scans`` and the reconstruct-shot flow's ``scans``), with
    the options ``scan`` of :data:`SHOT_SCAN_OPTIONS` (by field name); None without scans."""
    if scans is None or (isinstance(scans, (list, tuple)) and not scans):
        return None
    common = dict(index=index_dir, out=str(Path(out) / IN_SHOT), **scan)
    if isinstance(scans, (str, Path)):
        return CompareOptions(pairs=str(scans), **common)
    try:
        frames, files = zip(*((int(f), str(s)) for f, s in scans), strict=True)
    except (TypeError, ValueError):
        raise InputError(f"scans: give a pairs CSV or a list of [frame, scan] pairs, not {scans!r}") from None
    return CompareOptions(frames=frames, scans=files, **common)


def scan_inputs(options: CompareOptions | None) -> tuple[Path | str, ...]:
    """What a reconstruction with ``options``' scans reads besides its own inputs (the pairs CSV and the scan
    files), for its output check: a scan inside OUT (OUT/obj/frame_NNNNN.obj) would be overwritten or removed by
    the reconstruction, and then compared with itself."""
    if options is None:
        return ()
    return tuple(p for p in (options.pairs, *(s for _, s in checked_pairs(options))) if p)


def check_scan_frames(pairs: list[tuple[int, Path]], frames, options: CompareOptions) -> None:
    """Refuse a scan of a frame the shot does not have, before the reconstruction."""
    have = {int(f) for f in frames}
    for f, scan in pairs:
        if f not in have:
            raise InputError(f"scan {scan} is of frame {f}, which the shot's bundles do not have (frames "
                             f"{min(have)}-{max(have)})", path=options.pairs or scan)


def compare_shot(recon_dir: str | Path, options: CompareOptions, pairs: list[tuple[int, Path]], logger=None,
                 run=None) -> dict[str, Any]:
    """The compare job on a shot just reconstructed. A scan that fails (bad input found only now: it does not
    load, it covers no part of the face) is logged as an error and returned as ``status: failed`` with the
    message, its pair ``failed`` and the others ``not measured`` (the job writes all or nothing): the
    reconstruction is sound and stays. A bug still raises.

    ``run(recon_dir, options)`` runs the job (default :func:`compare`; the flow passes its task); ``logger``
    (the flow's run logger) gets the failure and the report, None: nothing logged (the command line prints
    them itself)."""
    from lgi.errors import LgiError

    try:
        result = (run or compare)(recon_dir, options)
    except LgiError as exc:
        if logger is not None:
            logger.error("scan comparison failed (the reconstruction in %s is kept): %s", recon_dir, exc)
        return {"status": "failed", "error": str(exc), "out": None,
                "pairs": [{"frame": f, "scan": str(s), "status": "failed" if str(s) == getattr(exc, "path", None)
                           else "not measured"} for f, s in pairs]}
    for line in compare_report(result) if logger is not None else ():
        logger.info(line)
    return {"status": "done", "error": "", "out": result["out"], "pairs": result["pairs"]}
