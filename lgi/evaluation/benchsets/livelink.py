"""The ICT set driven by real motion (``ict_livelink``): the combination actor of ``ict_combination`` performing a
window of a real Live Link Face (iPhone ARKit) take.

The takes are read from the shared data folder's ``real-performances/live-link-face`` (not in the repository): six
takes of one performer from alexdjulin/LiveLinkFace-CSV-Retarget-For-Motionbuilder, Copyright (c) 2021 Alexandre
Donciu-Julin, MIT licence.
"""

from __future__ import annotations

import os

import numpy as np

from lgi.errors import InputError
from lgi.evaluation.benchsets.combinations import _combination_actor
from lgi.evaluation.benchsets.core import (
    ICT_JAW_MAX_DEG,
    ICT_JAW_MAX_YAW_DEG,
    BenchSet,
    _check_off_dataset,
    _finish,
)
from lgi.evaluation.benchsets.ict import _ict_layout, _ict_lip_line
from lgi.evaluation.realmotion import ict_weights, load_live_link

LIVELINK_TAKE = "S07-001"
LIVELINK_START = 380  # two bursts of speech around a held rest (JawOpen 0.03-0.63)
LIVELINK_FRAMES = 300
# The curves neither a performed shape nor the jaw takes: the ICT sets never slide the jaw, MouthClose only makes
# sense with ICT's linear jawOpen (as ICT_NOT_PERFORMED), and ICT has no tongue.
LIVELINK_UNUSED_CURVES = ("JawForward", "MouthClose", "TongueOut")
LIVELINK_SOURCE = ("Live Link Face takes from alexdjulin/LiveLinkFace-CSV-Retarget-For-Motionbuilder, "
                   "Copyright (c) 2021 Alexandre Donciu-Julin, MIT licence")


def livelink_jaw(arkit_names: list[str], weights: np.ndarray, max_open: float = ICT_JAW_MAX_DEG,
                 max_yaw: float = ICT_JAW_MAX_YAW_DEG) -> np.ndarray:
    """(F, 4) jaw parameters from ARKit's jaw curves, on the scale of the ICT sets' jaw motion.

    Opening ``JawOpen * max_open`` (``JawOpen`` 1, ICT's ``jawOpen`` shape, is about the rig's 25 degrees) and yaw
    ``(JawLeft - JawRight) * max_yaw`` (positive yaw moves the chin to the performer's left, as ICT's ``jawLeft``
    does), each clipped to the ICT sets' limits (0-``max_open``, within ``max_yaw``); no roll, no slide
    (``JawForward`` is not used, as the ICT sets never slide the jaw). Unlike the random performances' yaw the
    curve's is not scaled by the opening: the performer's jaw moves sideways when closed too.
    """
    col = {n: k for k, n in enumerate(arkit_names)}
    w = np.asarray(weights, np.float64)
    opening = np.clip(w[:, col["JawOpen"]] * max_open, 0.0, max_open)
    yaw = np.clip((w[:, col["JawLeft"]] - w[:, col["JawRight"]]) * max_yaw, -max_yaw, max_yaw)
    return np.stack([opening, yaw, np.zeros(len(w)), np.zeros(len(w))], axis=1)


def ict_livelink_set(ict_dir: str | os.PathLike[str], real_dir: str | os.PathLike[str] | None = None,
                     take: str = LIVELINK_TAKE, start: int = LIVELINK_START, frames: int = LIVELINK_FRAMES,
                     seed: int = 0) -> BenchSet:
    """The combination actor of :func:`ict_combination_set` driven by real iPhone ARKit curves of another performer.

    The actor and its correctives are :func:`ict_combination_set`'s for ``seed``; the dataset a method may use is
    the actor's own shapes without the combination shapes (:func:`ict_jaw_set`'s shapes and rig), so the correctives
    are in no dataset shape and no linear fit, rigged or not, reproduces a frame where a pair acts. Frames:
    ``frames`` consecutive tracked rows of Live Link Face take ``take`` from row ``start`` (rows that lost tracking
    dropped first; about 30 fps, at the take's own rate: the curves' frame-to-frame jitter is the captured motion
    and is kept). Each ICT shape takes the curve of its name (:func:`lgi.evaluation.realmotion.ict_weights`;
    ``BrowInnerUp`` and ``CheekPuff`` drive both sides), clipped to [0, 1]; ``cheekRaiser_L/R`` have no curve and
    stay 0; the jaw shapes, ``mouthClose`` and the pupils are not performed (as in the other ICT sets): the jaw is
    the rig's rotation from ``JawOpen``, ``JawLeft`` and ``JawRight`` (:func:`livelink_jaw`), and ``JawForward``,
    ``MouthClose`` and ``TongueOut`` are not used. ``x(t) = skin(x0 + sum_k w_k s_k + sum_p w_a w_b c_p, theta(t))``
    (:func:`jaw_actor_frames`): the real curves hold many shapes at once, so the pair correctives act on most
    frames. (With :func:`ict_combination_set`'s combination shapes in the dataset the rigged fit would be exact:
    each corrective is a combination shape less its two shapes, at weight ``w_a w_b``.) Errors over the face area;
    wide open as :func:`ict_combination_set`.

    Parameters
    ----------
    ict_dir : path
        The ICT FaceKit folder (:func:`ict_dir_or_none`).
    real_dir : path, optional
        The real-performances folder; default :func:`lgi.evaluation.realmotion.real_performances_dir_or_none`.
    take : str
        A take in ``live-link-face/`` (``S07-001``, ``S88-001``, ``apfel``, ``facial``, ``alex_rom_3``, ...).
    start, frames : int
        The window, in tracked rows of the take.
    seed : int
        The actor's correctives (as :func:`ict_combination_set`) and the tracking noise.

    Returns
    -------
    BenchSet
        ``info`` has ``take``, ``start``, ``frames``, ``fps`` (the window's median rate), ``times_s`` (F,) from
        the window's start, ``source`` (attribution), ``unused_curves``, ``shapes`` (K), ``weights`` (F, K),
        ``pairs``, ``pair_index``, ``correctives`` (P, V, 3) float32 cm, ``pair_active`` (F,) bool (a pair's
        product above 0.01) and ``jaw_open_params``.

    Raises
    ------
    InputError
        No such take, or a window outside it.
    """
    arkit, times, curves = load_live_link(take, real_dir)
    if start < 0 or frames < 1 or start + frames > len(curves):
        raise InputError(f"take {take} has {len(curves)} tracked frames: frames {start}-{start + frames - 1} "
                         "are not all in it")
    window = slice(start, start + frames)
    curves, times = curves[window], times[window] - times[start]
    ca, _ = _combination_actor(ict_dir, seed)
    ds = ca.jaw.dataset
    weights = np.clip(ict_weights(arkit, curves, ca.names), 0.0, 1.0)
    theta = livelink_jaw(arkit, curves)
    truth = ca.frames(weights, theta)
    _check_off_dataset("ict_livelink", truth, ds, ca.mask)
    idx = ca.pair_index
    pair_active = (weights[:, idx[:, 0]] * weights[:, idx[:, 1]] > 0.01).any(1)
    fps = float(1.0 / np.median(np.diff(times))) if frames > 1 else float("nan")
    actor = ca.jaw
    return _finish(
        "ict_livelink",
        f"ICT with rotating jaw and combination correctives, driven by real iPhone ARKit curves of another "
        f"performer (Live Link Face take {take}, frames {start}-{start + frames - 1} at {fps:.0f} fps).",
        ds, _ict_layout(ds.triangles), actor.rig, truth, ca.mask, _ict_lip_line(ds.triangles, ds.n_vertices),
        (theta[:, 0], float(actor.jaw_open_params[0])), theta, seed,
        {"take": take, "start": int(start), "frames": int(frames), "fps": fps, "times_s": times,
         "source": LIVELINK_SOURCE, "unused_curves": list(LIVELINK_UNUSED_CURVES), "shapes": ca.names,
         "weights": weights, "pairs": ca.pairs, "pair_index": idx, "correctives": ca.correctives.astype(np.float32),
         "pair_active": pair_active, "jaw_open_params": actor.jaw_open_params},
    )
