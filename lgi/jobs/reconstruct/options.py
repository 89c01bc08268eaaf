"""The reconstruct job's options (the ``lgi reconstruct`` flags) and their checks, with the files an option names
(the ``--jaw`` parameter file)."""

from __future__ import annotations

import argparse
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lgi.errors import InputError
from lgi.export.clips import USD_CLIP_FRAMES
from lgi.export.convention import convention_option
from lgi.jobs import options_from_dict
from lgi.options import declared, option, same_as
from lgi.solve.settings import FAR_FIELD, SolverSettings
from lgi.units import MM_PER_CM

#: Options whose values below the least are taken as the least (no smoothing, no bridging), as they always were.
_NONE_BELOW = ("smooth", "jaw_smooth", "max_gap")


def window(text: str) -> int:
    """``--smooth``/``--jaw-smooth`` WINDOW: a whole number of frames. ``auto`` (the default of an early release,
    when noisy shots were smoothed here; they are now smoothed per marker, see --noise) is taken as 1."""
    if text.strip().lower() == "auto":
        return 1
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a whole number of frames expected, not {text!r}") from None


#: The help sections of ``lgi reconstruct``'s options, in the order its help lists them.
GROUPS = ("outputs", "method", "noise and time", "jaw", "constraints from the cameras", "scheduling")


@declared
@dataclass(frozen=True)
class ReconstructOptions:
    """Options of the reconstruct job: the ``lgi reconstruct`` flags, and the reconstruct-shot flow's parameters
    (:mod:`lgi.options`)."""

    temporal_weight: float = same_as(SolverSettings, "temporal_weight")
    spatial_weight: float = same_as(SolverSettings, "spatial_weight")
    smooth: int = option(
        1, "central moving average of each bundle's shape weights over WINDOW frames (default %(default)s = none; "
        "0 and below also mean none, and 'auto' means 1)", group="noise and time", metavar="WINDOW", parse=window,
        units="frames")
    jaw_smooth: int | None = option(
        None, "moving average of the jaw parameters over WINDOW frames (default: --smooth's window)",
        group="noise and time", metavar="WINDOW", parse=window, units="frames")
    noise: float | str = option(
        "auto", "bundle noise per coordinate, mm: 0 = exact bundles (the surface passes through each); above 0 they "
        "are measurements: each marker's trajectory is smoothed (windows chosen per marker and axis by Stein's "
        "unbiased risk estimate), each bundle keeps its local geometry as far as the noise allows, and the surface "
        "passes between the bundles by the share of each residual that is the face; auto: the bundles' "
        "covariances when the file has them (lgi track writes them), else estimated per axis from the shot's "
        "trajectories and reported (default %(default)s)", group="noise and time", metavar="MM|auto", units="mm")
    method: str = option(
        "local", "local: a global fit of the jaw and shape weights, refitted per bundle over its natural "
        "neighbours and its containing simplices' shapes; simplex: the paper's choice among containing simplices "
        "only; blendshape: no LGI, the rigged bounded blendshape fit (jaw and weights per frame, then skinned; "
        "the benchmarks' baseline), the same outputs, for lgi review --compare (the LGI options --noise, "
        "--smooth, --far-field... do not apply) (default %(default)s)", group="method",
        choices=("local", "simplex", "blendshape"))
    jaw: str = option(
        "auto", "with a jaw-rigged index: estimate the jaw per frame (auto) or read it from a CSV (frame, open_deg, "
        "yaw_deg, roll_deg, forward_cm); 'none' needs an index without a rig (default %(default)s)", group="jaw",
        metavar="auto|none|FILE")
    max_gap: int = option(
        0, "bridge a marker's missing runs of up to N frames by interpolating between the frames around (default "
        "%(default)s = off: a hidden marker's weights are fitted to its seen neighbours in its own frame, which "
        "follows fast motion that interpolation misses)", group="noise and time", metavar="N", units="frames")
    bilateral: str | None = option(
        None, "bilateral filter of the bundles before solving: in time (frames, mm), and with the third value also "
        "over the nearest markers (mm), e.g. 1.5:0.5:10 (default: off)", group="noise and time",
        metavar="SIGMA_FRAMES:SIGMA_MM[:SIGMA_SPACE_MM]")
    obj: bool = option(False, "also write one OBJ per frame, OUT_DIR/obj/frame_NNNNN.obj", group="outputs")
    usd: bool = option(
        False, "also write OUT_DIR/shot.usdc (animated mesh, see --fps; a shot of over "
        f"{USD_CLIP_FRAMES} frames keeps them in value clips, OUT_DIR/shot.clips/)", group="outputs")
    plot: bool = option(False, "also write OUT_DIR/per_frame.png", group="outputs")
    fps: float = option(30.0, "USD time codes per second (default %(default)s)", group="outputs", metavar="F")
    dcc: str | None = convention_option("dcc", "shot.usdc", "outputs")
    up_axis: str | None = convention_option("up_axis", "shot.usdc", "outputs")
    units: str | None = convention_option("units", "shot.usdc", "outputs")
    chunk_size: int = option(
        60, "with --flow: frames per task (default %(default)s; the results do not depend on it)",
        group="scheduling", metavar="N", units="frames")
    observations: str | None = option(
        None, "the 2D tracks table of lgi track: a marker seen by one camera where the bundles lack it is put on "
        "its viewing ray, at the depth a first reconstruction without it gives, and the shot is reconstructed "
        "again through it (twice the solve time); writes OUT_DIR/bundles_constrained.parquet and a constraint "
        "column in the diagnostics", group="constraints from the cameras", metavar="TRACKS_PARQUET")
    calib: str | None = option(
        None, "with --observations: the stereo calibration (default: the rig lgi track stored in the table, "
        "refined by helmet dots if it was)", group="constraints from the cameras", metavar="CALIB_JSON")
    contours: str | None = option(
        None, "lip contours traced per frame and camera (frame, camera, curve, point, x, y; curve upper_inner or "
        "lower_inner; px): the lip region is deformed so that the mesh's inner lip edges meet them, keeping the "
        "bundles (needs --observations for the head pose and rig); adds contour_px_before/after to the "
        "diagnostics", group="constraints from the cameras", metavar="CONTOURS_CSV")
    far_field: str = option(
        f"{FAR_FIELD[0] * MM_PER_CM:g}:{FAR_FIELD[1] * MM_PER_CM:g}",
        "mm from the nearest marker over the skin: beyond START, a bundle whose weights predict the markers "
        "beyond its neighbourhood clearly worse than the frame's global fit gives way to that fit, wholly beyond "
        "END; off = the bundles' weights everywhere (default %(default)s)", group="method",
        metavar="START:END|off", units="mm")

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
