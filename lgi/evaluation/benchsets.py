"""The accuracy benchmark's test sets: every method is measured on the same frames.

Each builder returns a :class:`BenchSet`: a dataset (what a method may use), a marker layout, the jaw
rig that goes with the dataset (or None), and a sequence of test frames that are *not* dataset shapes,
with their bundles clean and as a tracker would give them (noise and gaps). Everything is
deterministic for a given seed.

Sets (:data:`SET_NAMES`):

* ``synthetic`` (:func:`synthetic_set`): the built-in synthetic actor's random performance;
* ``ict_jaw`` (:func:`ict_jaw_set`): an ICT-derived actor whose jaw truly rotates (a rig fitted to
  ``jawOpen``), with expressions carried by the rotating jaw;
* ``ict_heldout`` (:func:`ict_heldout_set`): ICT shapes left out of the dataset and mixes involving
  them (the frames of :func:`lgi.evaluation.accuracy.ict_benchmark`);
* ``ict_combination`` (:func:`ict_combination_set`): the rotating-jaw actor whose overlapping shape
  pairs get a corrective when they act together, as captured combination shapes have;
* ``session_0``, ``session_150``, ``session_400`` (:func:`session_set`): a capture session, the synthetic
  actor's 47 shapes plus 0, 150 or 400 captured poses of another performance, tested on a held-out
  performance;
* ``ict_session`` (:func:`ict_session_set`): the frames of ``ict_combination`` against the rotating-jaw
  actor's shapes plus 150 captured frames of another performance of that actor (its correctives
  included), so the truth is nonlinear beyond what the base shapes span.

Conventions shared by all sets:

* noisy bundles (:func:`tracking_noise`): Gaussian noise of 0.3 mm per coordinate, then markers lost
  for runs of 1-6 consecutive frames until 5 % of marker-frames are NaN rows;
* lips (:func:`lip_region`): the measured vertices within 1.5 cm (straight-line distance on the
  neutral) of the lip line, the inner lip contour from mouth corner to mouth corner;
* wide open (:func:`wide_open_threshold`): the jaw opened more than min(15 deg, 60 % of the dataset's
  widest opening).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lgi.dataset.markers import MarkerLayout
from lgi.dataset.shapes import ShapeDataset, ShapeMeta
from lgi.errors import InputError
from lgi.solve.jaw import JawRig

SET_NAMES = ("synthetic", "ict_jaw", "ict_heldout", "ict_combination", "session_0", "session_150", "session_400",
             "session_0_norig", "session_150_norig", "session_400_norig", "ict_session")

NOISE_CM = 0.03  # 0.3 mm per coordinate: a good head-mounted stereo rig's triangulation noise
MISSING_FRACTION = 0.05
MAX_GAP_FRAMES = 6
LIP_RADIUS_CM = 1.5
WIDE_OPEN_DEG = 15.0
WIDE_OPEN_FRACTION = 0.6

# ICT FaceKit vertex ranges (0-based; see the data folder's ABOUT.md).
ICT_FACE_VERTICES = 9409  # the face area 0-9408: the only part that carries markers
ICT_MOUTH_SOCKET = (11248, 13294)
ICT_LOWER_TEETH = np.arange(19247, 21451)
# Shapes no performance frame of the rotating-jaw actor uses: the jaw is the rig's (the linear jaw
# shapes would fight it), mouthClose only makes sense with the linear jawOpen, pupils are not skin.
ICT_NOT_PERFORMED = ("jawOpen", "jawLeft", "jawRight", "jawForward", "mouthClose", "PupilDilate_L", "PupilDilate_R")
ICT_JAW_MAX_DEG = 25.0
ICT_JAW_MAX_YAW_DEG = 3.0
# A frame closer than this (RMS over the measured vertices) to a dataset shape is that shape as stored (float32
# deltas round at about 1e-6 cm). Not larger: a shot frame moving the jaw alone lies on the one-parameter family
# of jaw-only scans, and one of session_150's small test variants (5000 vertices) lands 0.0007 mm from one.
OFF_DATASET_CM = 1e-5
SCAN_PERFORMANCE_FRAMES = 600  # the session's own performance, the scans are taken from
SESSION_SCANS = (0, 150, 400)


@dataclass
class BenchSet:
    """One test set of the accuracy benchmark.

    Attributes
    ----------
    name : str
        One of :data:`SET_NAMES`.
    description : str
        One sentence saying what the frames are.
    dataset : ShapeDataset
        What a method may use (shapes in cm); no test frame is one of its shapes.
    layout : MarkerLayout
        The markers, on ``dataset``'s canonical triangulation.
    rig : JawRig or None
        The jaw rig that goes with the dataset (None when the set has no articulated jaw).
    triangles : (T, 3) int32
        The canonical triangulation of the mesh.
    truth : (F, V, 3) float64, cm
        True vertex positions of the frames, a sequence.
    bundles : (F, M, 3) float64, cm
        ``layout.evaluate(truth)``: clean bundles.
    noisy : (F, M, 3) float64, cm
        ``bundles`` with tracking noise and gaps (NaN rows), see :func:`tracking_noise`.
    mask : (V,) bool
        Vertices errors are measured on (the face area).
    lips : (V,) bool
        Measured vertices near the lip line (subset of ``mask``), see :func:`lip_region`.
    wide_open : (F,) bool
        Frames with the jaw opened beyond :func:`wide_open_threshold`.
    true_jaw : (F, 4) float64 or None
        The frames' jaw parameters ``(open_deg, yaw_deg, roll_deg, forward_cm)`` (:mod:`lgi.solve.jaw`) where
        the frames were made with a rig.
    info : dict
        How the frames were made (seed, thresholds, per-frame shape weights ...), per set.
    """

    name: str
    description: str
    dataset: ShapeDataset
    layout: MarkerLayout
    rig: JawRig | None
    triangles: np.ndarray
    truth: np.ndarray
    bundles: np.ndarray
    noisy: np.ndarray
    mask: np.ndarray
    lips: np.ndarray
    wide_open: np.ndarray
    true_jaw: np.ndarray | None
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.truth.shape[0])

    @property
    def n_markers(self) -> int:
        return len(self.layout)


# ---------------------------------------------------------------------------------------------- shared
def tracking_noise(bundles: np.ndarray, seed: int, noise_cm: float = NOISE_CM,
                   missing: float = MISSING_FRACTION, max_gap: int = MAX_GAP_FRAMES) -> np.ndarray:
    """Bundles as a tracker gives them: noisy, with markers lost for a few frames at a time.

    Gaussian noise of ``noise_cm`` per coordinate; then random (marker, start frame) runs of 1 to
    ``max_gap`` consecutive frames are blanked (NaN rows) until ``missing`` of all marker-frames are.

    Parameters
    ----------
    bundles : (F, M, 3) float, cm
    seed : int
    noise_cm : float
        Standard deviation per coordinate, cm.
    missing : float
        Fraction of marker-frames to blank.
    max_gap : int
        Longest run of consecutive missing frames of one marker.

    Returns
    -------
    (F, M, 3) float64, cm
    """
    rng = np.random.default_rng([seed, 7919])
    b = np.asarray(bundles, np.float64)
    noisy = b + rng.normal(scale=noise_cm, size=b.shape)
    n_frames, n_markers = b.shape[:2]
    gone = np.zeros((n_frames, n_markers), bool)
    target = int(round(missing * n_frames * n_markers))
    count = 0
    while count < target:
        m = int(rng.integers(n_markers))
        start = int(rng.integers(n_frames))
        # The last run is cut short so the fraction lands on the target rather than past it.
        length = min(int(rng.integers(1, max_gap + 1)), target - count)
        run = gone[start:start + length, m]
        count += int((~run).sum())
        run[:] = True
    noisy[gone] = np.nan
    return noisy


def lip_region(neutral: np.ndarray, lip_line: np.ndarray, mask: np.ndarray,
               radius: float = LIP_RADIUS_CM) -> np.ndarray:
    """Measured vertices within ``radius`` of the lip line on the neutral.

    Parameters
    ----------
    neutral : (V, 3) float, cm
    lip_line : (L,) int
        Vertices of the inner lip contour, corner to corner (both lips).
    mask : (V,) bool
        The measured vertices; the region is a subset of them.
    radius : float
        Straight-line distance on the neutral, cm (1.5 cm takes in both lips and the mouth corners'
        surroundings, not the nose or the chin).

    Returns
    -------
    (V,) bool
    """
    from scipy.spatial import cKDTree

    x0 = np.asarray(neutral, np.float64)
    d, _ = cKDTree(x0[np.asarray(lip_line)]).query(x0, distance_upper_bound=radius * 1.0001)
    return (d <= radius) & np.asarray(mask, bool)


def wide_open_threshold(widest_deg: float) -> float:
    """Opening (degrees) beyond which a frame counts as wide open: ``min(15, 0.6 * widest_deg)``.

    ``widest_deg`` is the dataset's widest opening: an actor who opens less still has wide-open frames.
    """
    return float(min(WIDE_OPEN_DEG, WIDE_OPEN_FRACTION * widest_deg))


def _finish(name: str, description: str, dataset: ShapeDataset, layout: MarkerLayout, rig: JawRig | None,
            truth: np.ndarray, mask: np.ndarray, lip_line: np.ndarray, opening_deg: np.ndarray,
            widest_deg: float, true_jaw: np.ndarray | None, seed: int, info: dict[str, Any]) -> BenchSet:
    """Assemble a set: bundles, noisy bundles, lips and wide-open frames from the truth."""
    truth = np.asarray(truth, np.float64)
    bundles = layout.evaluate(truth)
    threshold = wide_open_threshold(widest_deg)
    ds = dataset
    ds.info = {**ds.info, "benchset": name}
    return BenchSet(
        name=name, description=description, dataset=ds, layout=layout, rig=rig, triangles=ds.triangles,
        truth=truth, bundles=bundles, noisy=tracking_noise(bundles, seed), mask=np.asarray(mask, bool),
        lips=lip_region(ds.neutral, lip_line, mask), wide_open=np.asarray(opening_deg) > threshold,
        true_jaw=None if true_jaw is None else np.asarray(true_jaw, np.float64),
        info={"seed": seed, "wide_open_deg": threshold, "widest_opening_deg": float(widest_deg), **info},
    )


def _raised_cosine(t: np.ndarray, start: float, duration: float) -> np.ndarray:
    """(F,) a bump rising from 0 at ``start`` to 1 and back to 0 at ``start + duration`` (frames)."""
    u = np.clip((t - start) / duration, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(2 * np.pi * u)


def _chain(frames: int, rng: np.random.Generator, durations: tuple[float, float], step: tuple[float, float],
           cover_start: bool) -> list[tuple[float, float]]:
    """Event windows ``(start, duration)`` in frames along one track, at most two at a time.

    Each event starts ``step`` (a fraction of the previous one's duration) after the previous one's start;
    a step below 1 overlaps them, above 1 leaves a gap. No event starts before the one two back has
    ended, and each ends after the previous one, so at most two are active at once; with steps below 1
    every frame is inside one (``cover_start`` also covers frame 0).
    """
    events: list[tuple[float, float]] = []
    d = rng.uniform(*durations)
    s = -rng.uniform(0.2, 0.6) * d if cover_start else rng.uniform(0, d)
    while s < frames:
        if events:
            prev_end = events[-1][0] + events[-1][1]
            # Long enough to outlast the previous event, so events never nest.
            d = rng.uniform(max(durations[0], prev_end - s + 10.0), max(durations[1], prev_end - s + 10.0))
        events.append((s, d))
        nxt = s + rng.uniform(*step) * d
        if len(events) >= 2:
            nxt = max(nxt, events[-2][0] + events[-2][1] + 1.0)
        s = nxt
    return events


def _overlaps(a: tuple[float, float], b: tuple[float, float]) -> bool:
    return a[0] < b[0] + b[1] and b[0] < a[0] + a[1]


def _assign_shapes(windows: list[tuple[float, float]], names: list[str], rng: np.random.Generator,
                   busy: list[tuple[tuple[float, float], list[str]]], forbid_together: set[frozenset[str]]
                   ) -> list[str]:
    """A shape for every window: never one already active then, opposite to one active then (augment's
    rules), or forming a ``forbid_together`` pair with one active then. ``busy`` grows with the picks."""
    from lgi.augment.combinations import compatible

    picks = []
    for w in windows:
        # Unique: one shape may be in two windows that overlap this one but not each other.
        active = sorted({n for win, ns in busy if _overlaps(w, win) for n in ns})
        ok = [n for n in names if n not in active and compatible([n, *active], requires={})
              and not any(frozenset((n, a)) in forbid_together for a in active)]
        pick = str(rng.choice(ok))
        picks.append(pick)
        busy.append((w, [pick]))
    return picks


def _expression_weights(frames: int, names: list[str], rng: np.random.Generator,
                        busy: list[tuple[tuple[float, float], list[str]]] | None = None,
                        forbid_together: set[frozenset[str]] | None = None, tracks: int = 2) -> np.ndarray:
    """(F, K) smooth weights in [0, 1] of shapes ``names``: 1-2 per track at any time.

    Track one is a chain of overlapping bumps (20-60 frames, peaks 0.5-1), so every frame has an
    expression; track two leaves gaps. Bumps overlap, so the weights' sum is often above 1.
    """
    t = np.arange(frames, dtype=np.float64)
    busy = [] if busy is None else busy
    windows = _chain(frames, rng, (20.0, 60.0), (0.5, 0.85), cover_start=True)
    if tracks >= 2:
        windows += _chain(frames, rng, (20.0, 60.0), (0.6, 1.4), cover_start=False)
    picks = _assign_shapes(windows, names, rng, busy, forbid_together or set())
    w = np.zeros((frames, len(names)))
    col = {n: k for k, n in enumerate(names)}
    for (s, d), n in zip(windows, picks, strict=True):
        w[:, col[n]] += rng.uniform(0.5, 1.0) * _raised_cosine(t, s, d)
    return np.clip(w, 0.0, 1.0)


def _jaw_motion(frames: int, rng: np.random.Generator, max_open: float = ICT_JAW_MAX_DEG,
                max_yaw: float = ICT_JAW_MAX_YAW_DEG) -> np.ndarray:
    """(F, 4) smooth jaw parameters: openings in [0, ``max_open``] deg and a small yaw, no roll or slide.

    Openings are raised-cosine bumps (20-60 frames, peaks 0.4-1 ``max_open``, at least one above
    0.8 ``max_open``) one after another with gaps of up to half their length (the jaw rests closed
    there). The yaw is a slow sinusoid of amplitude up to ``max_yaw`` scaled by the opening's fraction
    of ``max_open``, so a closed jaw is exactly the neutral's.
    """
    t = np.arange(frames, dtype=np.float64)
    windows = _chain(frames, rng, (20.0, 60.0), (1.0, 1.5), cover_start=False)
    peaks = rng.uniform(0.4 * max_open, max_open, len(windows))
    if peaks.max() < 0.8 * max_open:
        # A set whose jaw never opens wide would not test what it is for.
        peaks[int(np.argmax([min(s + d, frames) - max(s, 0) for s, d in windows]))] = rng.uniform(
            0.8 * max_open, max_open)
    opening = np.zeros(frames)
    for (s, d), p in zip(windows, peaks, strict=True):
        opening += p * _raised_cosine(t, s, d)
    opening = np.clip(opening, 0.0, max_open)
    amp = rng.uniform(0.5, 1.0) * max_yaw
    period, phase = rng.uniform(60.0, 160.0), rng.uniform(0, 2 * np.pi)
    yaw = amp * np.sin(2 * np.pi * t / period + phase) * opening / max_open
    return np.stack([opening, yaw, np.zeros(frames), np.zeros(frames)], axis=1)


def _smooth_over_mesh(values: np.ndarray, triangles: np.ndarray, passes: int) -> np.ndarray:
    """(V,) values averaged ``passes`` times with their mesh neighbours (half self, half neighbours)."""
    import scipy.sparse as sp

    t = np.asarray(triangles)
    n = len(values)
    adj = sp.coo_matrix((np.ones(6 * len(t)), (t[:, [0, 1, 2, 1, 2, 0]].ravel(), t[:, [1, 2, 0, 0, 1, 2]].ravel())),
                        shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    deg = np.maximum(np.asarray(adj.sum(1)).ravel(), 1)
    v = np.asarray(values, np.float64)
    for _ in range(passes):
        v = 0.5 * v + 0.5 * (adj @ v) / deg
    return v


def min_shape_distance(truth: np.ndarray, dataset: ShapeDataset, mask: np.ndarray,
                       include_neutral: bool = True) -> np.ndarray:
    """How far each frame is from the dataset: the smallest RMS vertex distance to the neutral or a shape.

    Parameters
    ----------
    truth : (F, V, 3) float, cm
    dataset : ShapeDataset
    mask : (V,) bool
        Vertices compared.
    include_neutral : bool
        Whether the neutral counts as a dataset point (False: the shapes only; inf without shapes).

    Returns
    -------
    (F,) float64, cm
    """
    x = (np.asarray(truth, np.float64)[:, mask] - dataset.neutral[mask]).reshape(len(truth), -1)
    d = np.asarray(dataset.deltas[:, mask], np.float64).reshape(dataset.n_shapes, -1)
    x2 = np.sum(x**2, 1)
    d2 = np.sum(d**2, 1)
    sq = x2[:, None] + d2[None] - 2 * (x @ d.T)
    if include_neutral:
        sq = np.concatenate([x2[:, None], sq], axis=1)
    if sq.shape[1] == 0:
        return np.full(len(x), np.inf)
    return np.sqrt(np.maximum(sq.min(1), 0.0) / mask.sum())


def _check_off_dataset(name: str, truth: np.ndarray, dataset: ShapeDataset, mask: np.ndarray) -> None:
    """Refuse a set one of whose frames is a dataset shape (within :data:`OFF_DATASET_CM` RMS over ``mask``): a
    method could then look it up instead of reconstructing it.

    The neutral is not a shape: frames at rest are allowed (the random performances have some), even where a
    scan taken at the tail of an expression is as close to the neutral as they are.

    Raises
    ------
    RuntimeError
        Naming the frames and their distances.
    """
    d = min_shape_distance(truth, dataset, mask, include_neutral=False)
    to_neutral = np.sqrt(np.mean(np.sum((np.asarray(truth, np.float64)[:, mask] - dataset.neutral[mask]) ** 2, 2), 1))
    near = np.flatnonzero((d < OFF_DATASET_CM) & (to_neutral >= OFF_DATASET_CM))
    if near.size:
        raise RuntimeError(f"set {name}: frames {near[:10].tolist()} are dataset shapes (RMS distance "
                           f"{(d[near[:10]] * 10).round(5).tolist()} mm)")


def _spread(candidates: np.ndarray, n: int) -> np.ndarray:
    """``n`` of ``candidates`` (sorted frame numbers) spread evenly over them, first and last included.

    Raises
    ------
    InputError
        More asked for than there are candidates.
    """
    if n > len(candidates):
        raise InputError(f"{n} scans asked for but the scan performance has only {len(candidates)} frames to "
                         "take them from")
    if n <= 0:
        return np.zeros(0, np.int64)
    pick = np.unique(np.round(np.linspace(0, len(candidates) - 1, n)).astype(np.int64))
    return np.asarray(candidates, np.int64)[pick]


# ---------------------------------------------------------------------------------------------- synthetic
def synthetic_set(frames: int = 300, seed: int = 1, n_vertices: int = 20000) -> BenchSet:
    """The built-in synthetic actor's random performance (:mod:`lgi.synthetic.actor`).

    Dataset: :func:`lgi.synthetic.actor.make_dataset` (47 shapes); rig: the actor's true one; frames:
    :func:`lgi.synthetic.actor.random_performance` (``frames``, ``seed``) evaluated in float64 (where no control is
    active, ~7 % of frames, the frame is the neutral); errors over every vertex (as
    :func:`lgi.evaluation.accuracy.synthetic_benchmark`); lips around the mouth slit. Wide open: beyond 13.2 degrees
    (60 % of the dataset's 22).

    Parameters
    ----------
    frames : int
    seed : int
        Performance and noise seed.
    n_vertices : int
        At least this many vertices (see :func:`lgi.synthetic.actor.make_actor`).
    """
    from lgi.synthetic import actor as synth
    actor = synth.make_actor(n_vertices)
    ds = synth.make_dataset(actor)
    layout, _ = synth.default_layout(actor)
    acts = synth.random_performance(frames, seed=seed)
    truth = np.stack([actor.evaluate(a) for a in acts])
    true_jaw = actor.jaw_parameters(acts)
    lip_line = _synthetic_lip_line(actor.neutral)
    widest = max(m.extra["jaw"][0] for m in ds.shape_meta)
    return _finish(
        "synthetic",
        f"The synthetic actor's random performance of {frames} frames (seed {seed}): smooth, overlapping "
        "expression events and a jaw rotating about its hinge, evaluated by the nonlinear model, so no frame "
        "is one of the 47 dataset shapes (frames with no control active are the neutral).",
        ds, layout, synth.jaw_rig(actor), truth, np.ones(actor.n_vertices, bool), lip_line, true_jaw[:, 0],
        widest, true_jaw, seed, {"activations": acts, "controls": list(synth.CONTROLS),
                                 "at_rest": ~(acts > 0).any(1)},
    )


def _synthetic_lip_line(neutral: np.ndarray) -> np.ndarray:
    """The synthetic actor's mouth slit row, corner to corner (its lower-lip duplicates included)."""
    from lgi.synthetic import actor as synth

    x0 = np.asarray(neutral)
    return np.flatnonzero((np.abs(x0[:, 1] - synth.MOUTH_Y) < 1e-6)
                          & (np.abs(x0[:, 0]) <= synth.MOUTH_HALF_WIDTH + 1e-6))


def session_set(n_scans: int, frames: int = 160, seed: int = 3, scan_seed: int = 1,
                n_vertices: int = 20000, rig: bool = True) -> BenchSet:
    """The synthetic actor with a capture session's scans in the dataset: does LGI use captured poses?

    Dataset: the 47 shapes of :func:`lgi.synthetic.actor.make_dataset` plus ``n_scans`` captured poses,
    the actor's true (nonlinear) evaluation at frames of another performance,
    :func:`lgi.synthetic.actor.random_performance` (600 frames, ``scan_seed``): of its frames with any
    control active, ``n_scans`` spread evenly (:func:`_spread`). The scans are named ``scan_NNNN`` (the frame
    number) and tagged ``scan`` (their metadata also has the activations, the true jaw and ``frame``).
    Rig: the actor's true one. Frames: ``random_performance(frames, seed)`` evaluated in float64, a
    different performance; frames with no control active are the neutral. Errors over every vertex;
    lips and wide open (60 % of the 47 shapes' widest opening) as :func:`synthetic_set`.

    Parameters
    ----------
    n_scans : int
        Captured poses added to the dataset (0: the 47 shapes alone).
    frames : int
        Length of the test shot.
    seed : int
        Test shot and noise seed.
    scan_seed : int
        Seed of the performance the scans are taken from.
    n_vertices : int
        At least this many vertices (see :func:`lgi.synthetic.actor.make_actor`).
    rig : bool
        With the actor's jaw rig (False: none, as a session without a jaw rig is reconstructed; the set is
        then named ``session_{n_scans}_norig``).

    Returns
    -------
    BenchSet
        Named ``session_{n_scans}`` (``_norig``); ``info`` has ``scan_seed``, ``scan_frames`` (n_scans,) int,
        ``activations`` (F, C) of the shot, ``controls`` and ``at_rest`` (F,) bool.

    Raises
    ------
    InputError
        More scans than the scan performance has frames with a control active.
    """
    from lgi.synthetic import actor as synth

    actor = synth.make_actor(n_vertices)
    base_names, base_acts = synth.default_dataset_activations()
    session = synth.random_performance(SCAN_PERFORMANCE_FRAMES, seed=scan_seed)
    scan_frames = _spread(np.flatnonzero((session > 0).any(1)), n_scans)
    names = base_names + [f"scan_{f:04d}" for f in scan_frames]
    ds = synth.make_dataset(actor, names, np.concatenate([base_acts, session[scan_frames]]))
    for m, f in zip(ds.shape_meta[len(base_names):], scan_frames, strict=True):
        m.tags = [*m.tags, "scan"]
        m.extra = {**m.extra, "frame": int(f)}
    layout, _ = synth.default_layout(actor)
    acts = synth.random_performance(frames, seed=seed)
    truth = np.stack([actor.evaluate(a) for a in acts])
    mask = np.ones(actor.n_vertices, bool)
    _check_off_dataset(f"session_{n_scans}", truth, ds, mask)
    true_jaw = actor.jaw_parameters(acts)
    widest = max(m.extra["jaw"][0] for m in ds.shape_meta[:len(base_names)])
    return _finish(
        f"session_{n_scans}" + ("" if rig else "_norig"),
        f"The synthetic actor's random performance of {frames} frames (seed {seed}) against a dataset of the 47 "
        f"shapes plus {n_scans} captured poses (the true nonlinear face at frames of another 600-frame "
        f"performance, seed {scan_seed}), so no frame is a dataset shape (frames with no control active are the "
        "neutral).",
        ds, layout, synth.jaw_rig(actor) if rig else None, truth, mask, _synthetic_lip_line(actor.neutral),
        true_jaw[:, 0], widest,
        true_jaw, seed, {"scan_seed": scan_seed, "scan_frames": scan_frames, "activations": acts,
                         "controls": list(synth.CONTROLS), "at_rest": ~(acts > 0).any(1)},
    )


# ---------------------------------------------------------------------------------------------- ICT
def ict_dir_or_none() -> Path | None:
    """The ICT FaceKit folder (``$LGI_SHARED_DATA/ict-facekit``, else ``../shared/data/ict-facekit`` beside
    the repository, as the tests and ``lgi bench`` find it), or None when it is absent."""
    from lgi.paths import shared_data

    path = shared_data("ict-facekit")
    return path if (path / "generic_neutral_mesh.obj").is_file() else None


@functools.lru_cache(maxsize=2)
def _ict_cached(ict_dir: str) -> ShapeDataset:
    from lgi.dataset.importing import import_obj_folder

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
    from lgi.dataset.markers import read_layout
    from lgi.paths import shipped

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
    from lgi.solve.jaw import fit_rig

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
        ds, _ict_layout(ds.triangles), actor.rig, truth, mask, _ict_lip_line(ds.triangles, ds.n_vertices), theta[:, 0],
        float(actor.jaw_open_params[0]), theta, seed,
        {"shapes": names, "weights": weights, "jaw_open_params": actor.jaw_open_params},
    )


def _teeth_opening(neutral: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(N,) opening (degrees) of the lower teeth's rigid motion in each of ``positions`` (N, V, 3)."""
    from lgi.dataset.stabilise import rigid_fit
    from lgi.solve.jaw import _euler

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
    from lgi.augment.combinations import linear_combinations, pick_combinations
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
        opening, widest, None, seed,
        {"frame_names": frame_names, "teeth_opening_deg": opening, "held_out": list(ICT_HELD_OUT)},
    )


# ---------------------------------------------------------------------------------------------- combinations
PAIR_PREFIXES = ("mouth", "cheek", "nose")
N_PAIRS = 12
MAX_PAIRS_PER_SHAPE = 2
MIN_AGREEMENT = -0.2
CORRECTIVE_CM = (0.3, 0.5)  # magnitude at weights (1, 1)
CORRECTIVE_SIGMA_CM = 1.0
CORRECTIVE_SMOOTHING = 10


def overlapping_pairs(dataset: ShapeDataset, names: list[str], mask: np.ndarray, n: int = N_PAIRS,
                      max_per_shape: int = MAX_PAIRS_PER_SHAPE, min_agreement: float = MIN_AGREEMENT
                      ) -> list[tuple[str, str, float]]:
    """The ``n`` compatible shape pairs whose displacements overlap most over ``mask``.

    Overlap: the cosine between the two shapes' per-vertex displacement magnitudes over the masked
    vertices (1 when they move the same vertices in the same proportions). Left out: opposites
    (:func:`lgi.augment.combinations.compatible`) and antagonists, whose displacement fields have a cosine below
    ``min_agreement`` (ICT's mouthSmile with mouthFrown, -0.25, or cheekPuff with mouthSmile, -0.39: a
    capture session does not record them together). Pairs are taken best first, each shape in at most
    ``max_per_shape`` of them so the correctives spread over the face.

    Returns
    -------
    list of (a, b, overlap)
    """
    import itertools

    from lgi.augment.combinations import compatible

    d = np.stack([np.asarray(dataset.deltas[dataset.index(k)], np.float64)[mask] for k in names])
    mag = np.linalg.norm(d, axis=2)
    unit = mag / np.maximum(np.linalg.norm(mag, axis=1, keepdims=True), 1e-12)
    cos = unit @ unit.T
    flat = d.reshape(len(names), -1)
    flat = flat / np.maximum(np.linalg.norm(flat, axis=1, keepdims=True), 1e-12)
    agree = flat @ flat.T
    cands = sorted(((float(cos[i, j]), names[i], names[j]) for i, j in itertools.combinations(range(len(names)), 2)
                    if agree[i, j] >= min_agreement and compatible([names[i], names[j]], requires={})), reverse=True)
    used: dict[str, int] = {}
    out = []
    for c, a, b in cands:
        if used.get(a, 0) < max_per_shape and used.get(b, 0) < max_per_shape:
            out.append((a, b, c))
            used[a] = used.get(a, 0) + 1
            used[b] = used.get(b, 0) + 1
            if len(out) == n:
                break
    return out


def pair_corrective(neutral: np.ndarray, triangles: np.ndarray, delta_a: np.ndarray, delta_b: np.ndarray,
                    mask: np.ndarray, magnitude: float, sigma: float = CORRECTIVE_SIGMA_CM,
                    smoothing: int = CORRECTIVE_SMOOTHING) -> np.ndarray:
    """A pair's corrective at weights (1, 1): a smooth bump along the normal where both shapes move.

    ``c(v) = magnitude * g(v) / max_mask g * n(v)`` with ``g`` the geometric mean of the two shapes'
    displacement magnitudes, ``sqrt(|s_a(v)| |s_b(v)|)``, times a Gaussian (``sigma``, straight-line on
    the neutral) about the masked vertex where that mean peaks, smoothed by ``smoothing`` averaging passes
    over mesh neighbours; ``n`` are the neutral's unit vertex normals. At weights ``(w_a, w_b)`` the
    corrective is ``w_a w_b c``.

    Parameters
    ----------
    neutral : (V, 3) float, cm; triangles : (T, 3) int
    delta_a, delta_b : (V, 3) float, cm
    mask : (V,) bool
        Where the peak is looked for and the normalisation taken (the face area).
    magnitude : float
        Largest displacement over ``mask``, cm; negative pushes inward.

    Returns
    -------
    (V, 3) float64, cm
    """
    from lgi.dataset.mesh import vertex_normals

    x0 = np.asarray(neutral, np.float64)
    both = np.sqrt(np.linalg.norm(delta_a, axis=1) * np.linalg.norm(delta_b, axis=1))
    centre = x0[np.flatnonzero(mask)[int(np.argmax(both[mask]))]]
    g = both * np.exp(-np.sum((x0 - centre) ** 2, 1) / (2 * sigma**2))
    g = _smooth_over_mesh(g, triangles, smoothing)
    g /= max(float(g[mask].max()), 1e-12)
    return magnitude * g[:, None] * vertex_normals(x0, triangles)


@dataclass
class _CombinationActor:
    """The rotating-jaw ICT actor with pair correctives (:func:`ict_combination_set`'s truth model)."""

    jaw: _JawActor
    names: list[str]  # the performed shapes: columns of a performance's weights
    mask: np.ndarray  # (V,) bool, the face area
    pairs: list[tuple[str, str]]
    magnitudes: np.ndarray  # (P,) cm, signed: each corrective's largest displacement at weights (1, 1)
    correctives: np.ndarray  # (P, V, 3) float64 cm at weights (1, 1)
    pair_index: np.ndarray  # (P, 2) int, the pairs as columns of a performance's weights

    def frames(self, weights: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """(F, V, 3) float64 cm: the actor at ``weights`` (F, K) over :attr:`names` and jaw ``theta`` (F, 4)."""
        return jaw_actor_frames(self.jaw.dataset, self.jaw.rig, self.names, weights, theta, self.correctives,
                                self.pair_index)


def _combination_actor(ict_dir: str | os.PathLike[str], seed: int) -> tuple[_CombinationActor, np.random.Generator]:
    """The combination actor of :func:`ict_combination_set` for ``seed``, and the random generator after its
    correctives were drawn (the set's performance continues from it, so the set stays as it always was)."""
    actor = _jaw_actor(ict_dir)
    base = actor.dataset
    rng = np.random.default_rng([seed, 4])
    mask = _ict_face_mask(base.n_vertices)
    names = _performed(base.names)
    cand = [n for n in names if n.startswith(PAIR_PREFIXES)]
    pairs = [(a, b) for a, b, _ in overlapping_pairs(base, cand, mask)]
    signs = rng.choice([-1.0, 1.0], len(pairs))
    mags = rng.uniform(*CORRECTIVE_CM, len(pairs)) * signs
    corr = np.stack([pair_corrective(base.neutral, base.triangles, np.asarray(base.deltas[base.index(a)], np.float64),
                                     np.asarray(base.deltas[base.index(b)], np.float64), mask, m)
                     for (a, b), m in zip(pairs, mags, strict=True)])
    col = {n: k for k, n in enumerate(names)}
    pair_index = np.array([[col[a], col[b]] for a, b in pairs])
    return _CombinationActor(actor, names, mask, pairs, mags, corr, pair_index), rng


def _combination_performance(ca: _CombinationActor, frames: int, rng: np.random.Generator
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A performance of the combination actor: about 2/3 of the frames inside a pair event, a track of
    single expressions that never completes a pair, and the moving jaw (see :func:`ict_combination_set`).

    Returns
    -------
    weights : (F, K) float64 in [0, 1], over ``ca.names``
    theta : (F, 4) float64, jaw parameters
    pair_active : (F,) bool, frames where a pair's weights are both above 0
    """
    pairs, names = ca.pairs, ca.names
    t = np.arange(frames, dtype=np.float64)
    col = {n: k for k, n in enumerate(names)}
    weights = np.zeros((frames, len(names)))
    busy: list[tuple[tuple[float, float], list[str]]] = []
    # Gaps of 0.15-0.85 of an event's length (mean 0.5) leave about 2/3 of the frames inside one.
    windows = _chain(frames, rng, (30.0, 60.0), (1.15, 1.85), cover_start=True)
    prev = -1
    for s, d in windows:
        p = int(rng.choice([k for k in range(len(pairs)) if k != prev]))
        prev = p
        a, b = pairs[p]
        bump = _raised_cosine(t, s, d)
        # Different exponents keep the two weights from moving in proportion.
        weights[:, col[a]] += rng.uniform(0.5, 1.0) * bump ** rng.uniform(0.6, 1.0)
        weights[:, col[b]] += rng.uniform(0.5, 1.0) * bump ** rng.uniform(1.0, 1.8)
        busy.append(((s, d), [a, b]))
    pair_set = {frozenset(p) for p in pairs}
    weights += _expression_weights(frames, names, rng, busy=busy, forbid_together=pair_set, tracks=1)
    weights = np.clip(weights, 0.0, 1.0)
    idx = ca.pair_index
    pair_active = (weights[:, idx[:, 0]] * weights[:, idx[:, 1]] > 0).any(1)
    theta = _jaw_motion(frames, rng)
    return weights, theta, pair_active


def ict_combination_set(ict_dir: str | os.PathLike[str], frames: int = 120, seed: int = 0) -> BenchSet:
    """The rotating-jaw ICT actor of :func:`ict_jaw_set` with combination correctives, as captured.

    Twelve compatible pairs of mouth, cheek and nose shapes whose face-area displacements overlap most
    (:func:`overlapping_pairs`) each get a corrective (:func:`pair_corrective`: a smooth bump along the
    normal where both move, 3-5 mm at weights (1, 1), random sign) that grows with the product of their
    weights. The dataset is :func:`ict_jaw_set`'s plus each pair at (1, 1) and (0.5, 0.5) (the sum of
    the two shapes plus the corrective at that product: ``a+b`` and ``a*0.5+b*0.5``). Frames:
    ``x(t) = skin(x0 + sum_k w_k s_k + sum_p w_a w_b c_p, theta(t))`` with about 2/3 of them inside a
    pair event (one pair, both shapes active together for 30-60 frames with smoothly varying,
    non-proportional weights), plus a track of single expressions that never form a corrective pair
    with what is active, and the moving jaw of :func:`ict_jaw_set`.

    Returns
    -------
    BenchSet
        ``info`` has ``shapes`` (K), ``weights`` (F, K), ``pairs`` (P of (a, b)), ``pair_index`` (P, 2)
        columns of ``weights``, ``correctives`` (P, V, 3) float32 cm at (1, 1), ``pair_active`` (F,)
        bool and ``jaw_open_params``.
    """
    ca, rng = _combination_actor(ict_dir, seed)
    actor, base, pairs, corr, mags = ca.jaw, ca.jaw.dataset, ca.pairs, ca.correctives, ca.magnitudes
    extra, extra_names, extra_meta = [], [], []
    for (a, b), c in zip(pairs, corr, strict=True):
        s = np.asarray(base.deltas[base.index(a)], np.float64) + np.asarray(base.deltas[base.index(b)], np.float64)
        for w, label in ((1.0, f"{a}+{b}"), (0.5, f"{a}*0.5+{b}*0.5")):
            extra.append(w * s + w * w * c)
            extra_names.append(label)
            extra_meta.append(ShapeMeta(source="combination with corrective", tags=["combination", "corrective"],
                                        extra={"sources": {a: w, b: w}}))
    ds = base.take(range(base.n_shapes))
    ds.deltas = np.concatenate([np.asarray(base.deltas, np.float32), np.stack(extra).astype(np.float32)])
    ds.names = base.names + extra_names
    ds.shape_meta = base.shape_meta + extra_meta
    ds.info = {**base.info, "correctives": {"pairs": [list(p) for p in pairs], "magnitude_cm": mags.tolist()}}

    weights, theta, pair_active = _combination_performance(ca, frames, rng)
    truth = ca.frames(weights, theta)
    mask = ca.mask
    return _finish(
        "ict_combination",
        f"The rotating-jaw ICT actor, {frames} frames (seed {seed}), about 2/3 of them holding one of 12 "
        "overlapping mouth/cheek/nose shape pairs whose combination adds a corrective bump, with single "
        "expressions and a moving jaw.",
        ds, _ict_layout(ds.triangles), actor.rig, truth, mask, _ict_lip_line(ds.triangles, ds.n_vertices), theta[:, 0],
        float(actor.jaw_open_params[0]), theta, seed,
        {"shapes": ca.names, "weights": weights, "pairs": pairs, "pair_index": ca.pair_index,
         "correctives": corr.astype(np.float32), "pair_active": pair_active,
         "jaw_open_params": actor.jaw_open_params},
    )


def ict_session_set(ict_dir: str | os.PathLike[str], n_scans: int = 150, frames: int = 120, seed: int = 0,
                    scan_seed: int = 7) -> BenchSet:
    """The combination actor of :func:`ict_combination_set`, with a capture session's scans in the dataset
    instead of its combination shapes: truth nonlinear beyond what the base shapes span.

    Frames: exactly :func:`ict_combination_set`'s (``frames``, ``seed``; the same noisy bundles too).
    Dataset: the rotating-jaw actor's base dataset (:func:`ict_jaw_set`'s 57 shapes, without the 24
    combination shapes) plus ``n_scans`` captured frames of another performance of the same actor (the same
    pairs, corrective magnitudes and signs: the actor comes from ``seed``; only the motion differs, 600
    frames drawn from ``scan_seed``), spread evenly over that performance's frames not at rest
    (:func:`_spread`). A scan is captured as it is, its jaw rotation included (``lgi build --jaw-rig``
    fits each shape's jaw parameters); scans are named ``scan_NNNN`` (the frame number) and tagged
    ``scan``. Errors over the face area; wide open as :func:`ict_combination_set`.

    Parameters
    ----------
    ict_dir : path
        The ICT FaceKit folder (:func:`ict_dir_or_none`).
    n_scans : int
        Captured frames added to the dataset.
    frames : int
        Length of the test shot.
    seed : int
        The actor's correctives, the test shot's motion and the noise (as :func:`ict_combination_set`).
    scan_seed : int
        The motion of the performance the scans are taken from.

    Returns
    -------
    BenchSet
        ``info`` has ``scan_seed``, ``scan_frames`` (n_scans,) int, ``scan_weights`` (n_scans, K),
        ``scan_jaw`` (n_scans, 4), and :func:`ict_combination_set`'s ``shapes``, ``weights``, ``pairs``,
        ``pair_index``, ``correctives``, ``pair_active`` and ``jaw_open_params``.

    Raises
    ------
    InputError
        More scans than the scan performance has frames not at rest.
    """
    ca, rng = _combination_actor(ict_dir, seed)
    weights, theta, pair_active = _combination_performance(ca, frames, rng)
    truth = ca.frames(weights, theta)
    # Another stream than the correctives' ([seed, 4]): the scans' motion is independent of the shot's.
    s_weights, s_theta, _ = _combination_performance(ca, SCAN_PERFORMANCE_FRAMES,
                                                     np.random.default_rng([scan_seed, 5]))
    moving = np.flatnonzero((s_weights > 0).any(1) | (s_theta != 0).any(1))
    scan_frames = _spread(moving, n_scans)
    scans = ca.frames(s_weights[scan_frames], s_theta[scan_frames])
    base = ca.jaw.dataset
    ds = base.take(range(base.n_shapes))
    ds.deltas = np.concatenate([np.asarray(base.deltas, np.float32),
                                (scans - base.neutral).astype(np.float32)])
    ds.names = base.names + [f"scan_{f:04d}" for f in scan_frames]
    ds.shape_meta = base.shape_meta + [
        ShapeMeta(source=f"scan: frame {f} of the combination actor's performance (scan seed {scan_seed})",
                  tags=["scan"], extra={"frame": int(f), "jaw": th.round(9).tolist()})
        for f, th in zip(scan_frames, s_theta[scan_frames], strict=True)]
    ds.info = {**base.info, "correctives": {"pairs": [list(p) for p in ca.pairs],
                                            "magnitude_cm": ca.magnitudes.tolist()}}
    _check_off_dataset("ict_session", truth, ds, ca.mask)
    actor = ca.jaw
    return _finish(
        "ict_session",
        f"The frames of ict_combination ({frames} frames, seed {seed}) against the rotating-jaw ICT actor's 57 "
        f"shapes plus {n_scans} captured frames, jaw included, of another 600-frame performance of the same actor "
        f"with its pair correctives (scan seed {scan_seed}), so the truth is nonlinear beyond what the dataset "
        "spans and no frame is a dataset shape.",
        ds, _ict_layout(ds.triangles), actor.rig, truth, ca.mask, _ict_lip_line(ds.triangles, ds.n_vertices),
        theta[:, 0], float(actor.jaw_open_params[0]), theta, seed,
        {"scan_seed": scan_seed, "scan_frames": scan_frames, "scan_weights": s_weights[scan_frames],
         "scan_jaw": s_theta[scan_frames], "shapes": ca.names, "weights": weights, "pairs": ca.pairs,
         "pair_index": ca.pair_index, "correctives": ca.correctives.astype(np.float32), "pair_active": pair_active,
         "jaw_open_params": actor.jaw_open_params},
    )


# ---------------------------------------------------------------------------------------------- loading
def needs_ict(name: str) -> bool:
    """Whether set ``name`` is built from ICT FaceKit (the others are the built-in synthetic actor's)."""
    return name.startswith("ict")


def load_sets(names: Iterable[str] | None = None, ict_dir: str | os.PathLike[str] | None = None
              ) -> dict[str, BenchSet]:
    """Build test sets by name with their default sizes and seeds.

    Parameters
    ----------
    names : iterable of str, optional
        From :data:`SET_NAMES`; default all of them, the ICT ones only when the data is found.
    ict_dir : path, optional
        The ICT FaceKit folder; default :func:`ict_dir_or_none`.

    Returns
    -------
    dict name -> BenchSet, in the order asked.

    Raises
    ------
    InputError
        An unknown name, or an ICT set asked for by name without the ICT data.
    """
    folder = Path(ict_dir) if ict_dir is not None else ict_dir_or_none()
    asked: Sequence[str]
    if names is None:
        asked = [n for n in SET_NAMES if not needs_ict(n) or folder is not None]
    else:
        asked = list(names)
    unknown = [n for n in asked if n not in SET_NAMES]
    if unknown:
        raise InputError(f"unknown benchmark set(s) {unknown}; known: {list(SET_NAMES)}")
    builders = {"synthetic": lambda: synthetic_set(), "ict_jaw": lambda: ict_jaw_set(folder),
                "ict_heldout": lambda: ict_heldout_set(folder), "ict_combination": lambda: ict_combination_set(folder),
                "ict_session": lambda: ict_session_set(folder),
                **{f"session_{n}": functools.partial(session_set, n) for n in SESSION_SCANS},
                **{f"session_{n}_norig": functools.partial(session_set, n, rig=False) for n in SESSION_SCANS}}
    if folder is None and any(needs_ict(n) for n in asked):
        raise InputError("the ICT sets need the ICT FaceKit folder: pass ict_dir or set LGI_SHARED_DATA "
                         "(looked for ../shared/data/ict-facekit)")
    return {n: builders[n]() for n in asked}
