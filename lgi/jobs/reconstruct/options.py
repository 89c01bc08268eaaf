"""The reconstruct job's options (the ``lgi reconstruct`` flags) and their checks, with the files an option names
(the ``--jaw`` parameter file)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lgi.errors import InputError
from lgi.jobs import options_from_dict
from lgi.units import MM_PER_CM

#: Options whose values below the least are taken as the least (no smoothing, no bridging), as they always were.
_NONE_BELOW = ("smooth", "jaw_smooth", "max_gap")


@dataclass(frozen=True)
class ReconstructOptions:
    """Options of the reconstruct job (the ``lgi reconstruct`` flags; see its ``--help``).

    Attributes
    ----------
    temporal_weight : float, mm
        Preference for the previous frame's shapes (0 = none).
    spatial_weight : float, mm
        Tie-break toward the shapes the neighbours agree on (0 = none).
    smooth : int
        Moving average of each bundle's shape weights over this many frames (1 = none; below 1 is taken as 1).
    jaw_smooth : int or None
        Moving average of the jaw parameters (None: ``smooth``; below 1 is taken as 1).
    noise : float (mm) or "auto"
        Bundle noise per coordinate; 0 = exact bundles.
    method : "local", "simplex" or "blendshape"
        Where a bundle's weights come from: refitted over its natural neighbours ("local"), or the paper's
        choice among the containing simplices only ("simplex"); "blendshape": no LGI, the rigged bounded
        blendshape fit of the benchmarks' baseline (:mod:`lgi.jobs.reconstruct.blendshape`).
    jaw : "auto", "none" or a CSV path
        With a rigged index: estimate the jaw per frame, or read it (frame, open_deg, yaw_deg, roll_deg,
        forward_cm); "none" needs an index without a rig.
    max_gap : int
        Bridge missing runs of up to this many frames (0 = off; below 0 is taken as 0).
    bilateral : str or None
        ``SIGMA_FRAMES:SIGMA_MM[:SIGMA_SPACE_MM]``: bilateral filter of the bundles before solving.
    obj : bool
        Also write one OBJ mesh per frame, ``obj/frame_NNNNN.obj``.
    usd : bool
        Also write the animated mesh as ``shot.usdc`` (``fps`` time codes per second; a shot of over
        :data:`~lgi.export.clips.USD_CLIP_FRAMES` frames keeps them in value clips, ``shot.clips/``).
    plot : bool
        Also write ``per_frame.png``: per frame, the largest distance to the bundles before the correction and
        the bundles projected, missing or bridged.
    fps : float
        USD time codes per second.
    dcc : str or None
        Write ``shot.usdc`` in a DCC's convention (maya, houdini, blender, unreal:
        :class:`lgi.export.convention.Convention`; default lgi's, Y up and cm). The other outputs stay lgi's.
    up_axis : str or None
        The up axis of ``shot.usdc``, Y or Z, over ``dcc``'s.
    units : str or None
        The units of ``shot.usdc``, cm or m, over ``dcc``'s.
    chunk_size : int
        Frames per task when the job runs as a flow (scheduling only: results do not depend on it).
    observations : str or None
        The tracks table of ``lgi track`` (Parquet): a marker seen by one camera where the shot has no bundle
        is put on its viewing ray, at the depth a first reconstruction without it gives, and the shot is
        reconstructed again through it (:mod:`lgi.capture.observations`).
    calib : str or None
        Stereo calibration for ``observations`` (default: the rig stored in the tracks table).
    contours : str or None
        Lip contours traced per frame and camera (CSV ``frame, camera, curve, point, x, y``, px): the lip
        region is deformed so that the mesh's inner lip edges meet them (:mod:`lgi.solve.contours`); needs
        ``observations`` (its head poses and rig).
    far_field : str
        ``START:END`` in mm of distance from the nearest marker (over the skin, UV-geodesic): beyond START
        a bundle whose weights predict the markers beyond its neighbourhood clearly worse than the frame's
        global fit gives way to that fit, wholly so beyond END; "off": the bundles' weights everywhere.
    """

    temporal_weight: float = 0.02
    spatial_weight: float = 1e-3
    smooth: int = 1
    jaw_smooth: int | None = None
    noise: float | str = "auto"
    method: str = "local"
    jaw: str = "auto"
    max_gap: int = 0
    bilateral: str | None = None
    obj: bool = False
    usd: bool = False
    plot: bool = False
    fps: float = 30.0
    dcc: str | None = None
    up_axis: str | None = None
    units: str | None = None
    chunk_size: int = 60
    observations: str | None = None
    calib: str | None = None
    contours: str | None = None
    far_field: str = "5:15"

    def __post_init__(self) -> None:
        def bad(flag: str, why: str) -> InputError:
            return InputError(f"--{flag.replace('_', '-')} {why}")

        for name in ("temporal_weight", "spatial_weight"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise bad(name, f"must be a finite number of mm >= 0, not {v!r}")
        # Upper bounds: a smoothing window past 1001 frames (33 s at 30 fps) is not smoothing any more.
        for name, least, most in (("smooth", 1, 1001), ("jaw_smooth", 1, 1001), ("max_gap", 0, 1_000_000),
                                  ("chunk_size", 1, 1_000_000)):
            v = getattr(self, name)
            if v is None and name == "jaw_smooth":
                continue
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise bad(name, f"must be a whole number in [{least}, {most}], not {v!r}")
            if v < least and name in _NONE_BELOW:
                # The first release took any window <= 1 as no smoothing and any gap <= 0 as no bridging, and
                # scripts pass 0: those values stay accepted (the command line is a contract), as what they meant.
                object.__setattr__(self, name, least)
            elif not least <= v <= most:
                raise bad(name, f"must be a whole number in [{least}, {most}], not {v!r}")
        if self.noise != "auto":
            try:
                value = float(self.noise)
            except (TypeError, ValueError):
                raise bad("noise", f"takes a number of mm or 'auto', not {self.noise!r}") from None
            if not math.isfinite(value) or value < 0:
                raise bad("noise", f"must be a finite number of mm >= 0, not {self.noise!r}")
        if self.method not in ("local", "simplex", "blendshape"):
            raise bad("method", f"takes 'local', 'simplex' or 'blendshape', not {self.method!r}")
        if not isinstance(self.fps, (int, float)) or not math.isfinite(self.fps) or self.fps <= 0:
            raise bad("fps", f"must be a positive number, not {self.fps!r}")
        if self.calib and not self.observations:
            raise bad("calib", "turns the observations of --observations into rays: give the tracks table too")
        if self.contours and not self.observations:
            raise bad("contours", "are seen through the head pose and cameras of the tracks table: give "
                                  "--observations too")
        self.bilateral_sigmas()
        self.far_field_cm()
        self.convention  # noqa: B018 - checks the values

    @property
    def convention(self):
        """The scene convention of ``shot.usdc``."""
        from lgi.export.convention import Convention

        return Convention.of(self.dcc, self.up_axis, self.units)

    def bilateral_sigmas(self) -> tuple[float, float, float | None] | None:
        """(sigma_frames, sigma_cm, sigma_space_cm or None) of ``bilateral``, or None."""
        if not self.bilateral:
            return None
        try:
            vals = [float(v) for v in str(self.bilateral).split(":")]
            if len(vals) not in (2, 3) or not all(math.isfinite(v) and v > 0 for v in vals):
                raise ValueError
        except ValueError:
            raise InputError("--bilateral takes SIGMA_FRAMES:SIGMA_MM[:SIGMA_SPACE_MM], positive numbers, "
                             f"got {self.bilateral!r}") from None
        return vals[0], vals[1] / MM_PER_CM, vals[2] / MM_PER_CM if len(vals) == 3 else None

    def far_field_cm(self) -> tuple[float, float] | None:
        """(start, end) cm of ``far_field``, or None for "off"."""
        return parse_far_field(self.far_field)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any] | None) -> ReconstructOptions:
        """Options from a dict (a flow's parameters); unknown keys are refused by name."""
        return options_from_dict(cls, d, "reconstruct")


def parse_far_field(text: str | None) -> tuple[float, float] | None:
    """``--far-field`` (``START:END`` mm, or "off") as (start, end) cm, or None."""
    if text is None or str(text).strip().lower() == "off":
        return None
    try:
        vals = [float(v) for v in str(text).split(":")]
        if len(vals) != 2 or not all(math.isfinite(v) for v in vals) or not 0 <= vals[0] < vals[1]:
            raise ValueError
    except ValueError:
        raise InputError("--far-field takes START:END in mm with 0 <= START < END (or off), "
                         f"got {text!r}") from None
    return vals[0] / MM_PER_CM, vals[1] / MM_PER_CM


def read_jaw_file(path: str | Path, frames: np.ndarray) -> np.ndarray:
    """(F, 4) jaw parameters for ``frames`` from a CSV with columns frame, open_deg, yaw_deg, roll_deg,
    forward_cm."""
    from lgi.io.csvio import read_table
    from lgi.solve.jaw import PARAM_NAMES

    p = Path(path)
    df = read_table(p, "jaw parameter file", ("frame", *PARAM_NAMES), numeric=("frame", *PARAM_NAMES))
    whole = df["frame"].to_numpy() == np.round(df["frame"].to_numpy())
    if not whole.all():
        r = int(np.flatnonzero(~whole)[0])
        raise InputError(f"frame {df['frame'].iloc[r]:g} is not a whole number", path=p, line=r + 2)
    df["frame"] = df["frame"].astype(np.int64)
    dup = df["frame"][df["frame"].duplicated()]
    if len(dup):
        raise InputError("frame listed twice", path=p, frame=int(dup.iloc[0]), line=int(dup.index[0]) + 2)
    # Far outside any jaw's range: degrees where radians were meant, or another file.
    for col, limit in (("open_deg", 90.0), ("yaw_deg", 45.0), ("roll_deg", 45.0), ("forward_cm", 5.0)):
        out = np.abs(df[col].to_numpy()) > limit
        if out.any():
            r = int(np.flatnonzero(out)[0])
            raise InputError(f"{col} {df[col].iloc[r]:g} is outside a jaw's range (|{col}| <= {limit:g})", path=p,
                             line=r + 2, frame=int(df["frame"].iloc[r]))
    df = df.set_index("frame")
    absent = [int(f) for f in frames if int(f) not in df.index]
    if absent:
        raise InputError(f"no jaw parameters for {len(absent)} frames", path=p, frame=absent[0])
    vals = df.loc[[int(f) for f in frames], PARAM_NAMES].to_numpy(float)
    if not np.all(np.isfinite(vals)):
        r = int(np.flatnonzero(~np.all(np.isfinite(vals), axis=1))[0])
        raise InputError("non-finite jaw parameter", path=p, frame=int(frames[r]))
    return vals
