"""What every benchmark set is made of: :class:`BenchSet`, and the conventions and construction they share
(tracking noise, the lip region, the wide-open threshold, random motion built from shapes and the jaw, the
check that no test frame is a dataset shape)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lgi.augment.combinations import compatible
from lgi.dataset.markers import MarkerLayout
from lgi.dataset.shapes import ShapeDataset
from lgi.errors import InputError
from lgi.solve.jaw import JawRig

NOISE_CM = 0.03  # 0.3 mm per coordinate: a good head-mounted stereo rig's triangulation noise
MISSING_FRACTION = 0.05
MAX_GAP_FRAMES = 6
LIP_RADIUS_CM = 1.5
WIDE_OPEN_DEG = 15.0
WIDE_OPEN_FRACTION = 0.6
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
            truth: np.ndarray, mask: np.ndarray, lip_line: np.ndarray, opening: tuple[np.ndarray, float],
            true_jaw: np.ndarray | None, seed: int, info: dict[str, Any]) -> BenchSet:
    """Assemble a set: bundles, noisy bundles, lips and wide-open frames from the truth. ``opening``: each frame's
    jaw opening (F,) and the dataset's widest (degrees)."""
    opening_deg, widest_deg = opening
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
