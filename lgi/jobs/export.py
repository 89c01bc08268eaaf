"""The export job: a reconstruction as an animated USD mesh and/or OpenEXR displacement maps."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lgi.errors import InputError
from lgi.export.clips import USD_CLIP_FRAMES
from lgi.export.convention import Convention, convention_option
from lgi.io.atomic import reads
from lgi.options import declared, option

#: What a displacement map folder holds: a folder holding anything else is not replaced by one.
EXR_ENTRIES = ("frame_*.exr",)


@declared
@dataclass(frozen=True)
class ExportOptions:
    """Options of ``lgi export`` (:mod:`lgi.options`): a USD file and/or a folder of EXR maps, in the scene
    convention of ``dcc``, ``up_axis`` and ``units`` (:class:`lgi.export.convention.Convention`)."""

    usd: str | None = option(
        None, "animated mesh: .usdc (binary) or .usda (text); a shot of over "
        f"{USD_CLIP_FRAMES} frames keeps them in value clips beside it, in NAME.clips/ (FILE without its "
        "extension)", group="outputs", metavar="FILE")
    exr: str | None = option(None, "displacement maps: one frame_NNNNN.exr per frame", group="outputs",
                             metavar="DIR")
    exr_size: int = option(512, "map width and height, texels (default %(default)s)", group="outputs",
                           metavar="N", units="texels")
    fps: float = option(30.0, "USD time codes per second (default %(default)s)", group="outputs", metavar="F")
    dcc: str | None = convention_option("dcc", "the written geometry", "outputs")
    up_axis: str | None = convention_option("up_axis", "the written geometry", "outputs")
    units: str | None = convention_option("units", "the written geometry", "outputs")

    def __post_init__(self) -> None:
        for flag, path in (("--usd", self.usd), ("--exr", self.exr)):
            if isinstance(path, str) and not path.strip():
                raise InputError(f"{flag}: the output path is empty: give a file or folder")
        if not (self.usd or self.exr):
            raise InputError("nothing to export: give --usd FILE and/or --exr DIR")
        if isinstance(self.exr_size, bool) or not isinstance(self.exr_size, int) or not 8 <= self.exr_size <= 16384:
            raise InputError(f"--exr-size must be a whole number of texels in [8, 16384], not {self.exr_size!r}")
        if not isinstance(self.fps, (int, float)) or not math.isfinite(self.fps) or self.fps <= 0:
            raise InputError(f"--fps must be a positive number, not {self.fps!r}")
        if self.usd and Path(self.usd).suffix.lower() not in (".usd", ".usda", ".usdc"):
            raise InputError("--usd takes a .usd, .usda or .usdc file name", path=self.usd)
        self.convention  # noqa: B018 - checks the values

    @property
    def convention(self) -> Convention:
        return Convention.of(self.dcc, self.up_axis, self.units)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@reads("recon_dir")
def export(recon_dir: str | Path, index_dir: str | Path, options: ExportOptions,
           show_progress: bool = False) -> dict[str, Any]:
    """``lgi export``: write ``recon_dir/meshes.npz`` as USD and/or EXR maps (each output atomic; the USD is
    written last, so none appears if the maps fail)."""
    from lgi.export import clips
    from lgi.export.blender import for_blender, script_path, write_blender_script
    from lgi.export.formats import displacement_map, exr_header, write_exr, write_usd
    from lgi.index.build import LGIIndex
    from lgi.io.arrays import nonfinite_frames
    from lgi.io.atomic import atomic_dir, check_distinct, check_not_in_store, check_output
    from lgi.io.npz import load_meshes
    from lgi.progress import progress

    o = options
    script = script_path(o.usd) if o.usd and for_blender(o.convention) else None
    check_distinct({"--usd": o.usd, "--exr": o.exr, "the Blender script": script})
    if o.usd:
        check_output(o.usd, "file", inputs=[recon_dir, index_dir])
        check_not_in_store(o.usd, "--usd")
    if script:
        check_output(script, "file", inputs=[recon_dir, index_dir])
    if o.exr:
        check_output(o.exr, "dir", inputs=[recon_dir, index_dir], owned=EXR_ENTRIES, what="lgi displacement map folder")
        check_not_in_store(o.exr, "--exr")
    src = Path(recon_dir) / "meshes.npz"
    if not src.is_file():
        raise InputError("no meshes.npz (run lgi reconstruct first)", path=recon_dir)
    z = load_meshes(src, required=("vertices", "frames"))
    vertices, frames = z["vertices"], z["frames"]
    index = LGIIndex.load(index_dir)
    a = index.arrays
    if vertices.ndim != 3 or vertices.shape[1:] != (index.n_vertices, 3) or len(frames) != len(vertices):
        raise InputError(f"vertices of shape {vertices.shape} and {len(frames)} frames do not fit the index's "
                         f"{index.n_vertices} vertices", path=src)
    if o.usd and len(frames) > clips.USD_CLIP_FRAMES:
        # Checked before any map is written: a long shot's USD also replaces its clip folder.
        check_output(clips.usd_clip_dir(o.usd), "dir", inputs=[recon_dir, index_dir], owned=clips.USD_CLIP_CONTENTS,
                     what="lgi USD clip folder")
    bad = nonfinite_frames(vertices)
    if len(bad):
        raise InputError("non-finite vertex positions", path=src, frame=int(frames[bad[0]]))
    s: dict[str, Any] = {"frames": len(frames)}
    if o.exr:
        if "uvs" not in a:
            raise InputError("the mesh has no texture coordinates: no displacement maps", path=index_dir)
        x0 = np.asarray(a["neutral"], np.float64)
        conv = o.convention
        header = exr_header(conv, Path(index_dir).resolve().name, x0, o.fps)
        with atomic_dir(o.exr, EXR_ENTRIES, "lgi displacement map folder") as tmp:
            for f, v in progress(list(zip(frames, vertices, strict=True)), "displacement maps",
                                 disable=not show_progress):
                d = v - x0
                img, _ = displacement_map(d if conv.native else conv.points(d, np.float64), a["face_vertices"],
                                          a["face_offsets"], a["uvs"], a["face_uvs"], o.exr_size)
                write_exr(tmp / f"frame_{int(f):05d}.exr", img, {**header, "lgi:frame": int(f)})
        s["exr"] = str(Path(o.exr).resolve())
    if o.usd:
        write_usd(o.usd, vertices, a["face_vertices"], a["face_offsets"], a.get("uvs"), a.get("face_uvs"),
                  frames, fps=o.fps, convention=o.convention)
        s["usd"] = str(Path(o.usd).resolve())
        if script:
            s["blender_script"] = str(write_blender_script(o.usd, o.fps, int(frames[0]), int(frames[-1])).resolve())
    return s


def export_report(s: dict[str, Any], options: ExportOptions) -> list[str]:
    lines = []
    c = options.convention
    if "exr" in s:
        lines.append(f"displacement maps: {s['exr']} ({s['frames']} x {options.exr_size}^2 RGB float32, {c.units}, "
                     f"{c.up} up)")
    if "usd" in s:
        lines.append(f"USD: {s['usd']} ({s['frames']} time samples at {options.fps:g} fps, {c.units}, {c.up} up)")
    if "blender_script" in s:
        lines.append(f"Blender: run {s['blender_script']} in Blender to import it with its frame rate")
    return lines
