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

Sets of real motion (:data:`REAL_SET_NAMES`, built by name with :func:`load_sets` but not by default: they also
need the shared data's ``real-performances`` folder, :func:`real_performances_dir_or_none`):

* ``ict_livelink`` (:func:`ict_livelink_set`): ``ict_combination``'s actor against ``ict_jaw``'s shapes and rig (the
  correctives in no dataset shape, so no linear fit is exact), its frames a window of a
  real Live Link Face take (another performer's iPhone ARKit curves, default 300 frames of ``S07-001`` at its
  native 30 fps, speech and holds, the tracker's jitter kept): every ICT shape takes the curve of its name and
  the rotating jaw follows ``JawOpen`` and ``JawLeft``/``JawRight``, so the frames hold the many simultaneous,
  small and jittery weights of captured motion, with the pair correctives acting on most of them (takes
  from alexdjulin/LiveLinkFace-CSV-Retarget-For-Motionbuilder, Copyright (c) 2021 Alexandre Donciu-Julin, MIT).

Conventions shared by all sets:

* noisy bundles (:func:`tracking_noise`): Gaussian noise of 0.3 mm per coordinate, then markers lost
  for runs of 1-6 consecutive frames until 5 % of marker-frames are NaN rows;
* lips (:func:`lip_region`): the measured vertices within 1.5 cm (straight-line distance on the
  neutral) of the lip line, the inner lip contour from mouth corner to mouth corner;
* wide open (:func:`wide_open_threshold`): the jaw opened more than min(15 deg, 60 % of the dataset's
  widest opening).

The sets are built in :mod:`~lgi.evaluation.benchsets.synthetic`, :mod:`~lgi.evaluation.benchsets.ict` and
:mod:`~lgi.evaluation.benchsets.combinations` (real motion: :mod:`~lgi.evaluation.benchsets.livelink`), from the
construction they share (:mod:`~lgi.evaluation.benchsets.core`); this module names them and builds them by name
(:func:`load_sets`).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

from lgi.errors import InputError
from lgi.evaluation.benchsets.combinations import (
    CORRECTIVE_CM,
    CORRECTIVE_SIGMA_CM,
    CORRECTIVE_SMOOTHING,
    MAX_PAIRS_PER_SHAPE,
    MIN_AGREEMENT,
    N_PAIRS,
    PAIR_PREFIXES,
    ict_combination_set,
    ict_session_set,
    overlapping_pairs,
    pair_corrective,
)
from lgi.evaluation.benchsets.core import (
    ICT_JAW_MAX_DEG,
    ICT_JAW_MAX_YAW_DEG,
    LIP_RADIUS_CM,
    MAX_GAP_FRAMES,
    MISSING_FRACTION,
    NOISE_CM,
    OFF_DATASET_CM,
    SCAN_PERFORMANCE_FRAMES,
    SESSION_SCANS,
    WIDE_OPEN_DEG,
    WIDE_OPEN_FRACTION,
    BenchSet,
    lip_region,
    min_shape_distance,
    tracking_noise,
    wide_open_threshold,
)
from lgi.evaluation.benchsets.ict import (
    ICT_FACE_VERTICES,
    ICT_LOWER_TEETH,
    ICT_MOUTH_SOCKET,
    ICT_NOT_PERFORMED,
    ict_dir_or_none,
    ict_heldout_set,
    ict_jaw_set,
    jaw_actor_frames,
)
from lgi.evaluation.benchsets.livelink import (
    LIVELINK_FRAMES,
    LIVELINK_START,
    LIVELINK_TAKE,
    ict_livelink_set,
    livelink_jaw,
)
from lgi.evaluation.benchsets.synthetic import session_set, synthetic_set
from lgi.evaluation.realmotion import real_performances_dir_or_none

SET_NAMES = ("synthetic", "ict_jaw", "ict_heldout", "ict_combination", "session_0", "session_150", "session_400",
             "session_0_norig", "session_150_norig", "session_400_norig", "ict_session")
# Built by name only (not by load_sets' default): they need the real-performances data besides ICT.
REAL_SET_NAMES = ("ict_livelink",)

__all__ = ["BenchSet", "CORRECTIVE_CM", "CORRECTIVE_SIGMA_CM", "CORRECTIVE_SMOOTHING", "ICT_FACE_VERTICES",
           "ICT_JAW_MAX_DEG", "ICT_JAW_MAX_YAW_DEG", "ICT_LOWER_TEETH", "ICT_MOUTH_SOCKET", "ICT_NOT_PERFORMED",
           "LIP_RADIUS_CM", "LIVELINK_FRAMES", "LIVELINK_START", "LIVELINK_TAKE", "MAX_GAP_FRAMES",
           "MAX_PAIRS_PER_SHAPE", "MIN_AGREEMENT", "MISSING_FRACTION", "NOISE_CM", "N_PAIRS", "OFF_DATASET_CM",
           "PAIR_PREFIXES", "REAL_SET_NAMES", "SCAN_PERFORMANCE_FRAMES", "SESSION_SCANS", "SET_NAMES", "WIDE_OPEN_DEG",
           "WIDE_OPEN_FRACTION", "ict_combination_set", "ict_dir_or_none", "ict_heldout_set", "ict_jaw_set",
           "ict_livelink_set", "ict_session_set", "jaw_actor_frames", "lip_region", "livelink_jaw", "load_sets",
           "min_shape_distance", "needs_ict", "needs_real_performances", "overlapping_pairs", "pair_corrective",
           "real_performances_dir_or_none", "session_set", "synthetic_set", "tracking_noise", "wide_open_threshold"]


def needs_ict(name: str) -> bool:
    """Whether set ``name`` is built from ICT FaceKit (the others are the built-in synthetic actor's)."""
    return name.startswith("ict")


def needs_real_performances(name: str) -> bool:
    """Whether set ``name`` is built from the real performances (:data:`REAL_SET_NAMES`; they need ICT too)."""
    return name in REAL_SET_NAMES


def load_sets(names: Iterable[str] | None = None, ict_dir: str | os.PathLike[str] | None = None,
              real_dir: str | os.PathLike[str] | None = None) -> dict[str, BenchSet]:
    """Build test sets by name with their default sizes and seeds.

    Parameters
    ----------
    names : iterable of str, optional
        From :data:`SET_NAMES` or :data:`REAL_SET_NAMES`; default all of :data:`SET_NAMES`, the ICT ones only when
        the data is found (the real-motion sets only when asked for by name).
    ict_dir : path, optional
        The ICT FaceKit folder; default :func:`ict_dir_or_none`.
    real_dir : path, optional
        The real-performances folder; default :func:`real_performances_dir_or_none`.

    Returns
    -------
    dict name -> BenchSet, in the order asked.

    Raises
    ------
    InputError
        An unknown name, an ICT set asked for by name without the ICT data, or a real-motion set without the
        real performances.
    """
    folder = Path(ict_dir) if ict_dir is not None else ict_dir_or_none()
    asked: Sequence[str]
    if names is None:
        asked = [n for n in SET_NAMES if not needs_ict(n) or folder is not None]
    else:
        asked = list(names)
    known = SET_NAMES + REAL_SET_NAMES
    unknown = [n for n in asked if n not in known]
    if unknown:
        raise InputError(f"unknown benchmark set(s) {unknown}; known: {list(known)}")
    real = Path(real_dir) if real_dir is not None else real_performances_dir_or_none()
    builders = {"synthetic": lambda: synthetic_set(), "ict_jaw": lambda: ict_jaw_set(folder),
                "ict_heldout": lambda: ict_heldout_set(folder), "ict_combination": lambda: ict_combination_set(folder),
                "ict_session": lambda: ict_session_set(folder), "ict_livelink": lambda: ict_livelink_set(folder, real),
                **{f"session_{n}": functools.partial(session_set, n) for n in SESSION_SCANS},
                **{f"session_{n}_norig": functools.partial(session_set, n, rig=False) for n in SESSION_SCANS}}
    if folder is None and any(needs_ict(n) for n in asked):
        raise InputError("the ICT sets need the ICT FaceKit folder: pass ict_dir or set LGI_SHARED_DATA "
                         "(looked for ../shared/data/ict-facekit)")
    if real is None and any(needs_real_performances(n) for n in asked):
        raise InputError("the real-motion sets need the real performances: pass real_dir or set LGI_SHARED_DATA "
                         "(looked for ../shared/data/real-performances)")
    return {n: builders[n]() for n in asked}
