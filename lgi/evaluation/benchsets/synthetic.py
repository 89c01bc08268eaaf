"""The sets of the built-in synthetic actor: its random performance (``synthetic``) and a capture session of
it (``session_N``)."""

from __future__ import annotations

import numpy as np

from lgi.evaluation.benchsets.core import SCAN_PERFORMANCE_FRAMES, BenchSet, _check_off_dataset, _finish, _spread
from lgi.synthetic import actor as synth


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
        ds, layout, synth.jaw_rig(actor), truth, np.ones(actor.n_vertices, bool), lip_line,
        (true_jaw[:, 0], widest), true_jaw, seed, {"activations": acts, "controls": list(synth.CONTROLS),
                                 "at_rest": ~(acts > 0).any(1)},
    )


def _synthetic_lip_line(neutral: np.ndarray) -> np.ndarray:
    """The synthetic actor's mouth slit row, corner to corner (its lower-lip duplicates included)."""
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
        (true_jaw[:, 0], widest), true_jaw, seed,
        {"scan_seed": scan_seed, "scan_frames": scan_frames, "activations": acts, "controls": list(synth.CONTROLS),
         "at_rest": ~(acts > 0).any(1)},
    )
