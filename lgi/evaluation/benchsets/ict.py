"""The ICT FaceKit sets: the data found and imported once, the rotating-jaw actor (``ict_jaw``), and ICT
shapes held out of the dataset (``ict_heldout``)."""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lgi.augment.combinations import linear_combinations, pick_combinations
from lgi.dataset.importing import import_obj_folder
from lgi.dataset.markers import MarkerLayout, read_layout
from lgi.dataset.shapes import ShapeDataset, ShapeMeta
from lgi.dataset.stabilise import rigid_fit
from lgi.errors import InputError
from lgi.evaluation.benchsets.core import BenchSet, _expression_weights, _finish, _jaw_motion
from lgi.paths import shared_data, shipped
from lgi.solve.jaw import JawRig, _euler, fit_rig

# ICT FaceKit vertex ranges (0-based; see the data folder's ABOUT.md).
ICT_FACE_VERTICES = 9409  # the face area 0-9408: the only part that carries markers
ICT_MOUTH_SOCKET = (11248, 13294)
ICT_LOWER_TEETH = np.arange(19247, 21451)
# Shapes no performance frame of the rotating-jaw actor uses: the jaw is the rig's (the linear jaw
# shapes would fight it), mouthClose only makes sense with the linear jawOpen, pupils are not skin.
ICT_NOT_PERFORMED = ("jawOpen", "jawLeft", "jawRight", "jawForward", "mouthClose", "PupilDilate_L", "PupilDilate_R")


def ict_dir_or_none() -> Path | None:
    """The ICT FaceKit folder (``$LGI_SHARED_DATA/ict-facekit``, else ``../shared/data/ict-facekit`` beside
    the repository, as the tests and ``lgi bench`` find it), or None when it is absent."""
    path = shared_data("ict-facekit")
    return path if (path / "generic_neutral_mesh.obj").is_file() else None


@functools.lru_cache(maxsize=2)
def _ict_cached(ict_dir: str) -> ShapeDataset:
    return import_obj_folder(ict_dir, rigid_vertices="none", show_progress=False)


def _ict_key(ict_dir: str | os.PathLike[str]) -> str:
    path = Path(ict_dir).resolve()
    if not (path / "generic_neutral_mesh.obj").is_file():
        raise InputError("ICT FaceKit not found (no generic_neutral_mesh.obj)", path=path)
    return str(path)


def _ict(ict_dir: str | os.PathLike[str]) -> ShapeDataset:
    """ICT imported as it is (importing takes ~10 s: cached; callers get their own copy)."""
    full = _ict_cached(_ict_key(ict_dir))
    return full.take(range(full.n_shapes))


def _ict_face_mask(n_vertices: int) -> np.ndarray:
    mask = np.zeros(n_vertices, bool)
    mask[:ICT_FACE_VERTICES] = True
    return mask


def _ict_lip_line(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """Face-area vertices sharing a triangle with the mouth socket: ICT's inner lip contour."""
    t = np.asarray(triangles)
    face = _ict_face_mask(n_vertices)
    sock = np.zeros(n_vertices, bool)
    sock[ICT_MOUTH_SOCKET[0]:ICT_MOUTH_SOCKET[1]] = True
    mixed = t[face[t].any(1) & sock[t].any(1)]
    return np.unique(mixed[face[mixed]])


def _ict_layout(triangles: np.ndarray) -> MarkerLayout:
    return read_layout(shipped("markers_ict.csv"), triangles)


@dataclass
class _JawActor:
    """ICT with a jaw that rotates (see :func:`jaw_actor_frames`)."""

    dataset: ShapeDataset  # ICT with jawOpen replaced by the rig's rotation
    rig: JawRig
    jaw_open_params: np.ndarray  # (4,) jawOpen's fitted parameters


def jaw_actor_frames(dataset: ShapeDataset, rig: JawRig, names: list[str], weights: np.ndarray, theta: np.ndarray,
                     correctives: np.ndarray | None = None, pair_index: np.ndarray | None = None) -> np.ndarray:
    """Frames of an actor whose rotating jaw carries unskinned expressions (the ICT sets' truth).

    ``x = skin(x0 + sum_k w_k s_k + sum_p w_a w_b c_p, theta)``: shapes ``s_k``, optional pair correctives
    ``c_p`` of pairs ``(a, b)``, jaw parameters ``theta`` applied by the rig's linear blend skinning.

    Parameters
    ----------
    dataset : ShapeDataset
        Holds the shapes ``names`` (cm).
    rig : JawRig
    names : list of K str
    weights : (F, K) float
    theta : (F, 4) float
        ``(open_deg, yaw_deg, roll_deg, forward_cm)`` per frame.
    correctives : (P, V, 3) float, cm, optional
        Each pair's corrective at weights (1, 1).
    pair_index : (P, 2) int, optional
        The pairs, as columns of ``weights``.

    Returns
    -------
    (F, V, 3) float64, cm
    """
    s = np.asarray(dataset.deltas[[dataset.index(n) for n in names]], np.float64)
    w_all = np.asarray(weights, np.float64)
    out = np.empty((len(w_all), dataset.n_vertices, 3))
    for f, (w, th) in enumerate(zip(w_all, theta, strict=True)):
        x = dataset.neutral + np.tensordot(w, s, axes=1)
        if correctives is not None and pair_index is not None:
            x += np.tensordot(w[pair_index[:, 0]] * w[pair_index[:, 1]], correctives, axes=1)
        out[f] = rig.skin(x, th)
    return out


@functools.lru_cache(maxsize=2)
def _jaw_actor_cached(ict_dir: str) -> _JawActor:
    full = _ict_cached(ict_dir)
    k = full.index("jawOpen")
    rig, params = fit_rig(full.neutral, full.deltas[[k]], ICT_LOWER_TEETH, full.triangles)
    rig = JawRig(np.asarray(rig.pivot, np.float64).copy(), np.asarray(rig.weights, np.float64).copy())
    ds = full.take(range(full.n_shapes))  # a copy: the cached import stays as read
    ds.deltas[k] = (rig.skin(full.neutral, params[0]) - full.neutral).astype(np.float32)
    ds.shape_meta = list(ds.shape_meta)
    ds.shape_meta[k] = ShapeMeta(source="jawOpen.obj: the fitted rig's rotation of the neutral at jawOpen's "
                                        "fitted parameters", tags=["jaw"], extra={"jaw": params[0].tolist()})
    ds.info = {**ds.info, "jaw_rig": {"fitted_from": "jawOpen", "jaw_vertices": [int(ICT_LOWER_TEETH[0]),
                                                                                  int(ICT_LOWER_TEETH[-1])],
                                      "pivot_cm": rig.pivot.tolist(), "jawOpen_params": params[0].tolist()}}
    return _JawActor(ds, rig, params[0].copy())


def _jaw_actor(ict_dir: str | os.PathLike[str]) -> _JawActor:
    a = _jaw_actor_cached(_ict_key(ict_dir))
    return _JawActor(a.dataset.take(range(a.dataset.n_shapes)), JawRig(a.rig.pivot.copy(), a.rig.weights.copy()),
                     a.jaw_open_params.copy())


def _performed(names: list[str]) -> list[str]:
    return [n for n in names if n not in ICT_NOT_PERFORMED]


def ict_jaw_set(ict_dir: str | os.PathLike[str], frames: int = 200, seed: int = 0) -> BenchSet:
    """An ICT-derived actor whose jaw truly rotates, performing expressions while the jaw moves.

    The rig is fitted (:func:`lgi.solve.jaw.fit_rig`) from ``jawOpen`` alone with the lower teeth as jaw
    vertices: a hinge and per-vertex weights, ``jawOpen`` at about 25 degrees. The dataset is ICT
    with ``jawOpen`` replaced by the rig's rotation of the neutral at those parameters, everything else
    as it is. Frames: ``x(t) = skin(x0 + sum_k w_k(t) s_k, theta(t))`` with 1-4 non-jaw shapes active at
    any time (smooth bumps over 20-60 frames, overlapping; no jaw shape, ``mouthClose`` or pupil) and
    the jaw opening 0-25 degrees with a yaw within 3 degrees (see ``_jaw_motion``); see
    :func:`jaw_actor_frames`. Errors over the face area.

    Parameters
    ----------
    ict_dir : path
        The ICT FaceKit folder (:func:`ict_dir_or_none`).
    frames : int
    seed : int
        Performance and noise seed.

    Returns
    -------
    BenchSet
        ``info`` has ``shapes`` (K names), ``weights`` (F, K) and ``jaw_open_params`` (4,).
    """
    actor = _jaw_actor(ict_dir)
    ds = actor.dataset
    rng = np.random.default_rng([seed, 2])
    names = _performed(ds.names)
    weights = _expression_weights(frames, names, rng)
    theta = _jaw_motion(frames, rng)
    truth = jaw_actor_frames(ds, actor.rig, names, weights, theta)
    mask = _ict_face_mask(ds.n_vertices)
    return _finish(
        "ict_jaw",
        f"An ICT actor whose jaw rotates about a fitted hinge, {frames} frames (seed {seed}): 1-4 "
        "overlapping non-jaw expressions rising and falling smoothly, carried by a jaw opening up to 25 "
        "degrees with a slight sideways turn.",
        ds, _ict_layout(ds.triangles), actor.rig, truth, mask, _ict_lip_line(ds.triangles, ds.n_vertices),
        (theta[:, 0], float(actor.jaw_open_params[0])), theta, seed,
        {"shapes": names, "weights": weights, "jaw_open_params": actor.jaw_open_params},
    )


def _teeth_opening(neutral: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(N,) opening (degrees) of the lower teeth's rigid motion in each of ``positions`` (N, V, 3)."""
    rest = np.asarray(neutral, np.float64)[ICT_LOWER_TEETH]
    # Least squares, not robust: the teeth have no outliers, and a robust fit is 5x slower.
    return np.array([_euler(rigid_fit(rest, np.asarray(p, np.float64)[ICT_LOWER_TEETH], robust=False).rotation)[0]
                     for p in positions])


def _nearest_neighbour_order(points: np.ndarray, start: int) -> np.ndarray:
    """(N,) a greedy path through ``points`` (N, D) from ``start``, always to the closest unvisited one."""
    n = len(points)
    d2 = np.sum(points**2, 1)
    dist = d2[:, None] + d2[None] - 2 * points @ points.T
    order = [start]
    left = np.ones(n, bool)
    left[start] = False
    for _ in range(n - 1):
        row = np.where(left, dist[order[-1]], np.inf)
        nxt = int(np.argmin(row))
        order.append(nxt)
        left[nxt] = False
    return np.asarray(order)


def ict_heldout_set(ict_dir: str | os.PathLike[str], n_combinations: int = 400, n_test: int = 60,
                    seed: int = 0) -> BenchSet:
    """ICT shapes held out of the dataset, and mixes involving them: the frames of
    :func:`lgi.evaluation.accuracy.ict_benchmark`.

    Dataset: ICT without :data:`lgi.evaluation.accuracy.ICT_HELD_OUT` plus ``n_combinations`` linear combinations of
    the remaining shapes. Frames: the held-out shapes at weight 1 and the first ``n_test`` mixes of 2-3
    ICT shapes at weights 0.3/0.6/0.9 that involve a held-out one (the same draw as the bench's, without
    materialising its 4000 candidates). They are independent poses; they are ordered as a greedy
    nearest-neighbour path from the frame closest to the neutral so that consecutive frames are alike.
    No rig; the openings for ``wide_open`` are the lower teeth's rigid rotation. Errors over the face
    area.

    Returns
    -------
    BenchSet
        ``info`` has ``frame_names`` (F,) and ``teeth_opening_deg`` (F,).
    """
    from lgi.evaluation.accuracy import ICT_HELD_OUT

    full = _ict(ict_dir)
    keep = [n for n in full.names if n not in ICT_HELD_OUT]
    train = linear_combinations(full.take([full.index(n) for n in keep]), n_combinations, seed=seed)
    picks = pick_combinations(full.names, 4000, (0.3, 0.6, 0.9), (2, 3), seed + 7)
    mixes = [c for c in picks
             if any(h + "*" in "+".join(f"{k}*{w:g}" for k, w in c.items()) for h in ICT_HELD_OUT)][:n_test]
    frame_names = list(ICT_HELD_OUT) + ["+".join(f"{k}*{w:g}" for k, w in c.items()) for c in mixes]
    deltas = [np.asarray(full.deltas[full.index(h)], np.float64) for h in ICT_HELD_OUT]
    for c in mixes:
        deltas.append(sum(w * np.asarray(full.deltas[full.index(k)], np.float64) for k, w in c.items()))
    truth = full.neutral[None] + np.stack(deltas)
    mask = _ict_face_mask(full.n_vertices)
    flat = (truth[:, mask] - full.neutral[mask]).reshape(len(truth), -1)
    order = _nearest_neighbour_order(flat, int(np.argmin(np.sum(flat**2, 1))))
    truth = truth[order]
    frame_names = [frame_names[i] for i in order]
    opening = _teeth_opening(full.neutral, truth)
    widest = float(_teeth_opening(full.neutral, full.neutral[None] + np.asarray(train.deltas, np.float64)).max())
    return _finish(
        "ict_heldout",
        f"{len(truth)} independent ICT poses (held-out shapes at weight 1 and mixes of 2-3 shapes at "
        "0.3/0.6/0.9 involving one), none in the dataset, ordered as a nearest-neighbour path.",
        train, _ict_layout(full.triangles), None, truth, mask, _ict_lip_line(full.triangles, full.n_vertices),
        (opening, widest), None, seed,
        {"frame_names": frame_names, "teeth_opening_deg": opening, "held_out": list(ICT_HELD_OUT)},
    )
