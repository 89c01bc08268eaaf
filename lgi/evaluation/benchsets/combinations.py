"""The ICT sets with combination shapes: the rotating-jaw actor whose overlapping shape pairs get a corrective
when they act together (``ict_combination``), and a capture session of that actor (``ict_session``)."""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass

import numpy as np

from lgi.augment.combinations import compatible
from lgi.dataset.mesh import vertex_normals
from lgi.dataset.shapes import ShapeDataset, ShapeMeta
from lgi.evaluation.benchsets.core import (
    SCAN_PERFORMANCE_FRAMES,
    BenchSet,
    _chain,
    _check_off_dataset,
    _expression_weights,
    _finish,
    _jaw_motion,
    _raised_cosine,
    _smooth_over_mesh,
    _spread,
)
from lgi.evaluation.benchsets.ict import (
    _ict_face_mask,
    _ict_layout,
    _ict_lip_line,
    _jaw_actor,
    _JawActor,
    _performed,
    jaw_actor_frames,
)

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


def _combination_dataset(ca: _CombinationActor) -> ShapeDataset:
    """:func:`ict_combination_set`'s dataset: the rotating-jaw actor's shapes plus each corrective pair at (1, 1)
    and (0.5, 0.5) with its corrective at the weights' product."""
    base, pairs, corr, mags = ca.jaw.dataset, ca.pairs, ca.correctives, ca.magnitudes
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
    return ds


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
    actor, corr = ca.jaw, ca.correctives
    ds = _combination_dataset(ca)
    weights, theta, pair_active = _combination_performance(ca, frames, rng)
    truth = ca.frames(weights, theta)
    mask = ca.mask
    return _finish(
        "ict_combination",
        f"The rotating-jaw ICT actor, {frames} frames (seed {seed}), about 2/3 of them holding one of 12 "
        "overlapping mouth/cheek/nose shape pairs whose combination adds a corrective bump, with single "
        "expressions and a moving jaw.",
        ds, _ict_layout(ds.triangles), actor.rig, truth, mask, _ict_lip_line(ds.triangles, ds.n_vertices),
        (theta[:, 0], float(actor.jaw_open_params[0])), theta, seed,
        {"shapes": ca.names, "weights": weights, "pairs": ca.pairs, "pair_index": ca.pair_index,
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
        (theta[:, 0], float(actor.jaw_open_params[0])), theta, seed,
        {"scan_seed": scan_seed, "scan_frames": scan_frames, "scan_weights": s_weights[scan_frames],
         "scan_jaw": s_theta[scan_frames], "shapes": ca.names, "weights": weights, "pairs": ca.pairs,
         "pair_index": ca.pair_index, "correctives": ca.correctives.astype(np.float32), "pair_active": pair_active,
         "jaw_open_params": actor.jaw_open_params},
    )
