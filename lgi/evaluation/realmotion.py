"""Real facial motion for benchmarks and tests: Live Link Face (iPhone ARKit) curves and optical facial mocap.

The data is not in the repository: it is read from the shared data folder's ``real-performances``
(:func:`real_performances_dir_or_none`; its ``ABOUT.md`` describes the files and their rules). Nothing read
here, nor anything derived from it, may be written into the repository.

* ``live-link-face/*.csv``: six takes of one performer recorded with Epic's Live Link Face app, from
  alexdjulin/LiveLinkFace-CSV-Retarget-For-Motionbuilder (Copyright (c) 2021 Alexandre Donciu-Julin, MIT
  licence). :func:`load_live_link` reads a take's 52 ARKit curves; :func:`ict_weights` maps them onto ICT
  FaceKit's shapes by name.
* ``facial-mocap/*.npz``: optical facial motion capture of one actor, 41 labelled markers, from
  bigoMay/AnimFace (Miguel Ramos Carretero, "Efficient Facial Animation Integrating Euclidean and Geodesic
  Distance-Based Algorithms into Radial Basis Function Interpolation", Bournemouth University, 2019), licensed
  CC BY-SA 4.0 (https://creativecommons.org/licenses/by-sa/4.0/): anything derived from it is shared under the
  same licence. :func:`load_mocap` reads a take, :func:`stabilise_to_head` removes the head's motion,
  :func:`add_noise` adds noise of a known size (the trajectories were already filtered by the capture system,
  so they carry real motion but little noise of their own) and :func:`neighbour_pairs` gives neighbouring
  markers for coherence checks.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from lgi.dataset.stabilise import kabsch
from lgi.errors import InputError
from lgi.paths import shared_data

# ARKit's 52 blendshape curves (the order of ARKit's enum; Live Link Face writes them in another order, so columns
# are always mapped by name).
ARKIT_NAMES = (
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft", "EyeSquintLeft",
    "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight", "EyeLookOutRight", "EyeLookUpRight",
    "EyeSquintRight", "EyeWideRight", "JawForward", "JawLeft", "JawRight", "JawOpen", "MouthClose", "MouthFunnel",
    "MouthPucker", "MouthLeft", "MouthRight", "MouthSmileLeft", "MouthSmileRight", "MouthFrownLeft",
    "MouthFrownRight", "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft", "MouthStretchRight",
    "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper", "MouthPressLeft", "MouthPressRight",
    "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft", "MouthUpperUpRight", "BrowDownLeft",
    "BrowDownRight", "BrowInnerUp", "BrowOuterUpLeft", "BrowOuterUpRight", "CheekPuff", "CheekSquintLeft",
    "CheekSquintRight", "NoseSneerLeft", "NoseSneerRight", "TongueOut",
)
# Curves that keep their name apart from the first letter (no _L/_R split), and those driving both sides.
_ARKIT_UNSIDED = ("MouthLeft", "MouthRight", "JawLeft", "JawRight", "JawForward")
_ARKIT_BOTH_SIDES = ("BrowInnerUp", "CheekPuff")
ARKIT_NOT_IN_ICT = ("TongueOut",)
ICT_WITHOUT_CURVE = ("cheekRaiser_L", "cheekRaiser_R", "PupilDilate_L", "PupilDilate_R")
LIVE_LINK_FRAME_RATE = 60.0  # the timecode's FF field counts at 60 (the takes are recorded at about 30 fps)

# The mocap markers taken as rigid with the head: the three forehead markers and the nose bridge. They are the
# least deforming of the 41 (the brows, eyelids, nose tip and nostrils all move with expressions); the forehead
# still slides a little with brow raises (EyebrowsMoCap), so their residual after a rigid fit is small, not zero.
HEAD_MARKERS = ("ForeHead_M", "ForeHead_L", "ForeHead_R", "NoseTop")
MOCAP_RATE_HZ = 60.0


def real_performances_dir_or_none() -> Path | None:
    """The real-performances folder (``$LGI_SHARED_DATA/real-performances``, else
    ``../shared/data/real-performances`` beside the repository, as :func:`lgi.evaluation.benchsets.ict_dir_or_none`
    finds ICT), or None when it is absent."""
    path = shared_data("real-performances")
    return path if (path / "ABOUT.md").is_file() else None


def _folder(sub: str, folder: str | os.PathLike[str] | None) -> Path:
    base = Path(folder) if folder is not None else real_performances_dir_or_none()
    if base is None:
        raise InputError("the real performances were not found: set LGI_SHARED_DATA to the shared data folder "
                         "(looked for ../shared/data/real-performances)")
    return base / sub


def _find(sub: str, name: str | os.PathLike[str], suffix: str, folder: str | os.PathLike[str] | None) -> Path:
    path = Path(name)
    if not path.is_file():
        path = _folder(sub, folder) / (path.name if path.suffix == suffix else path.name + suffix)
    if not path.is_file():
        raise InputError(f"no such {sub} take", path=path)
    return path


# ---------------------------------------------------------------------------------------------- Live Link Face
def arkit_to_ict(name: str) -> tuple[str, ...]:
    """The ICT FaceKit shapes an ARKit curve drives (ABOUT.md's mapping): the first letter lower-cased and a
    trailing ``Left``/``Right`` written ``_L``/``_R`` (``EyeBlinkLeft`` -> ``eyeBlink_L``); ``MouthLeft``,
    ``MouthRight``, ``JawLeft``, ``JawRight`` and ``JawForward`` keep their names; ``BrowInnerUp`` and
    ``CheekPuff`` drive both sides; ``TongueOut`` drives nothing (empty)."""
    if name in ARKIT_NOT_IN_ICT:
        return ()
    low = name[0].lower() + name[1:]
    if name in _ARKIT_UNSIDED:
        return (low,)
    if name in _ARKIT_BOTH_SIDES:
        return (low + "_L", low + "_R")
    for side, tag in (("Left", "_L"), ("Right", "_R")):
        if low.endswith(side):
            return (low[: -len(side)] + tag,)
    return (low,)


def _timecode_seconds(code: str) -> float:
    """``HH:MM:SS:FF.fff`` (FF counted at 60) as seconds."""
    h, m, s, ff = code.split(":")
    return int(h) * 3600.0 + int(m) * 60.0 + int(s) + float(ff) / LIVE_LINK_FRAME_RATE


def load_live_link(take: str | os.PathLike[str], folder: str | os.PathLike[str] | None = None
                   ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """A Live Link Face take's ARKit curves, rows that lost tracking (``BlendShapeCount`` 0) left out.

    Parameters
    ----------
    take : str or path
        A CSV file, or a take's name in ``live-link-face/`` (``"S07-001"`` or ``"S07-001.csv"``).
    folder : path, optional
        The real-performances folder; default :func:`real_performances_dir_or_none`.

    Returns
    -------
    names : list of 52 str
        :data:`ARKIT_NAMES`, the columns of ``weights``.
    times : (T,) float64, s
        From the timecode, starting at 0.
    weights : (T, 52) float64
        The curves as recorded (in [0, 1], occasionally a little above 1), mapped by column name.

    Raises
    ------
    InputError
        No such take, or a curve missing from it.
    """
    path = _find("live-link-face", take, ".csv", folder)
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    header = rows[0]
    missing = [n for n in ARKIT_NAMES if n not in header]
    if missing or "BlendShapeCount" not in header or "Timecode" not in header:
        raise InputError(f"not a Live Link Face CSV: missing columns {missing or ['Timecode/BlendShapeCount']}",
                         path=path)
    cols = [header.index(n) for n in ARKIT_NAMES]
    count, tc = header.index("BlendShapeCount"), header.index("Timecode")
    kept = [r for r in rows[1:] if r and int(float(r[count])) > 0]
    weights = np.array([[float(r[c]) for c in cols] for r in kept], np.float64).reshape(len(kept), len(cols))
    times = np.array([_timecode_seconds(r[tc]) for r in kept], np.float64)
    return list(ARKIT_NAMES), times - (times[0] if len(times) else 0.0), weights


def ict_weights(arkit_names: list[str], weights: np.ndarray, ict_names: list[str]) -> np.ndarray:
    """ARKit curves as weights of ICT shapes ``ict_names`` (:func:`arkit_to_ict`); a shape no curve drives stays 0.

    Parameters
    ----------
    arkit_names : list of N str
    weights : (T, N) float
    ict_names : list of K str

    Returns
    -------
    (T, K) float64, the curves as they are (not clipped)
    """
    w = np.asarray(weights, np.float64)
    out = np.zeros((len(w), len(ict_names)))
    col = {n: k for k, n in enumerate(ict_names)}
    for j, a in enumerate(arkit_names):
        for n in arkit_to_ict(a):
            if n in col:
                out[:, col[n]] = w[:, j]
    return out


# ---------------------------------------------------------------------------------------------- facial mocap
def load_mocap(name: str | os.PathLike[str], folder: str | os.PathLike[str] | None = None
               ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """A facial-mocap take: 41 labelled markers at 60 Hz, Maya's axes (Y up), head not stabilised.

    Parameters
    ----------
    name : str or path
        An npz file, or a take's name in ``facial-mocap/`` (``"JawMoCap"`` or ``"JawMoCap.npz"``; also
        ``JawMoCap``, ``CheeksMoCap``, ``EyebrowsMoCap``, ``NoseMoCap``).
    folder : path, optional
        The real-performances folder; default :func:`real_performances_dir_or_none`.

    Returns
    -------
    names : list of M str
    times : (T,) float64, s
    positions : (T, M, 3) float64, cm
    """
    path = _find("facial-mocap", name, ".npz", folder)
    with np.load(path, allow_pickle=False) as d:
        names = [str(n) for n in d["names"]]
        times = np.asarray(d["time_s"], np.float64)
        xyz = np.asarray(d["xyz_cm"], np.float64)
    if xyz.shape != (len(times), len(names), 3):
        raise InputError(f"xyz_cm has shape {xyz.shape}, expected ({len(times)}, {len(names)}, 3)", path=path)
    return names, times, xyz


class Stabilised(NamedTuple):
    """Trajectories with the head's rigid motion removed (:func:`stabilise_to_head`)."""

    positions: np.ndarray  # (T, M, 3) float64, cm, in the reference's frame
    rotations: np.ndarray  # (T, 3, 3): stabilised = raw @ R.T + t
    translations: np.ndarray  # (T, 3), cm
    residual_cm: np.ndarray  # (T,) RMS distance of the head markers from their reference after the fit
    head: np.ndarray  # (H,) int, the head markers' columns


def _fit_all(raw: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    fits = [kabsch(p, ref) for p in raw]
    return np.stack([r for r, _ in fits]), np.stack([t for _, t in fits])


def stabilise_to_head(names: list[str], positions: np.ndarray, markers: tuple[str, ...] = HEAD_MARKERS,
                      reference: str = "first") -> Stabilised:
    """Trajectories rigidly stabilised to the head: per frame, the least-squares rigid fit (Kabsch) of the head
    markers onto their reference, applied to every marker.

    The head markers (default :data:`HEAD_MARKERS`: ``ForeHead_M``, ``ForeHead_L``, ``ForeHead_R`` and the nose
    bridge ``NoseTop``) are the mocap's least deforming ones. On ``JawMoCap`` they stay within about 0.3 mm RMS
    of their first-frame positions (0.8 mm on ``CheeksMoCap`` and ``NoseMoCap``, 1.7 mm on ``EyebrowsMoCap``,
    where brow raises slide the forehead), against 7-20 mm of head drift.

    Parameters
    ----------
    names : list of M str
    positions : (T, M, 3) float, cm
    markers : tuple of str
        The markers taken as rigid (at least three, not collinear).
    reference : ``"first"`` or ``"mean"``
        The head markers' first-frame positions, or their mean shape (the frames aligned to the first frame,
        averaged, and aligned again to that average).

    Returns
    -------
    Stabilised
    """
    missing = [m for m in markers if m not in names]
    if missing or len(markers) < 3:
        raise InputError(f"head markers {missing} not among the mocap's markers" if missing
                         else "at least three head markers are needed")
    if reference not in ("first", "mean"):
        raise InputError(f"reference must be 'first' or 'mean', not {reference!r}")
    x = np.asarray(positions, np.float64)
    head = np.array([names.index(m) for m in markers])
    raw = x[:, head]
    ref = raw[0]
    rot, tr = _fit_all(raw, ref)
    if reference == "mean":
        ref = np.mean(raw @ rot.transpose(0, 2, 1) + tr[:, None], axis=0)
        rot, tr = _fit_all(raw, ref)
    out = x @ rot.transpose(0, 2, 1) + tr[:, None]
    residual = np.sqrt(np.mean(np.sum((out[:, head] - ref) ** 2, 2), 1))
    return Stabilised(out, rot, tr, residual, head)


def add_noise(positions: np.ndarray, sigma: float | np.ndarray, seed: int,
              rotation: np.ndarray | None = None) -> np.ndarray:
    """Trajectories with Gaussian noise of a known size: isotropic, or per axis in a given frame.

    Parameters
    ----------
    positions : (..., 3) float, cm
    sigma : float or (3,) float, cm
        Standard deviation per coordinate, or per axis of the noise frame.
    seed : int
    rotation : (3, 3) float, optional
        The noise frame: its columns are the axes ``sigma`` refers to, in the positions' coordinates (a depth
        axis along a camera's view, say). Default the positions' own axes. The noise is ``R @ (sigma * z)``
        with ``z`` standard normal, so ``noise @ R`` has standard deviation ``sigma`` per column.

    Returns
    -------
    (..., 3) float64, cm; NaN stays NaN
    """
    x = np.asarray(positions, np.float64)
    s = np.broadcast_to(np.asarray(sigma, np.float64), (3,))
    if (s < 0).any():
        raise InputError(f"noise sigma must be non-negative, got {s.tolist()}")
    rng = np.random.default_rng([seed, 6007])
    local = rng.normal(size=x.shape) * s
    if rotation is not None:
        r = np.asarray(rotation, np.float64)
        if r.shape != (3, 3) or not np.allclose(r.T @ r, np.eye(3), atol=1e-6):
            raise InputError("rotation must be a (3, 3) orthonormal matrix")
        local = local @ r.T
    return x + local


def neighbour_pairs(rest: np.ndarray, k: int = 4) -> np.ndarray:
    """Natural-neighbour-like marker pairs: each marker with its ``k`` nearest at rest, made symmetric.

    Parameters
    ----------
    rest : (M, 3) float
        The markers at rest (e.g. a take's first frame, or its stabilised mean).
    k : int

    Returns
    -------
    (P, 2) int, ``i < j``, sorted, each pair once; every marker is in at least ``k`` pairs
    """
    from scipy.spatial import cKDTree

    p = np.asarray(rest, np.float64)
    k = min(k, len(p) - 1)
    if k < 1:
        return np.zeros((0, 2), np.int64)
    _, nn = cKDTree(p).query(p, k + 1)
    pairs = {(min(i, int(j)), max(i, int(j))) for i, row in enumerate(nn) for j in row[1:]}
    return np.array(sorted(pairs), np.int64).reshape(-1, 2)
