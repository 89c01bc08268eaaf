"""What the solver returns: one frame's choice and surface (:class:`FrameResult`), a sequence's meshes and
diagnostics (:class:`SequenceResult`), and the status codes the diagnostics name."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from lgi.solve._select_kernels import (
    BORROWED,
    CONTAINED,
    MISSING,
    PROJECTED,
)
from lgi.solve.globalfit import GlobalFitResult

# FITTED: a bundle given the global weights without a simplex search: a noisy one (its cloud would be matched
# to the noise), or an exact one that the global fit already meets with its natural neighbours (within
# LOCAL_MIN_MISFIT of :mod:`lgi.solve.selection`). The search is the costliest step of a frame.
FITTED = 4
STATUS = {CONTAINED: "contained", PROJECTED: "projected", MISSING: "missing", BORROWED: "neighbour",
          FITTED: "fitted"}


@dataclass(kw_only=True)
class FrameResult:
    """One reconstructed frame (made by name: seventeen fields).

    Attributes
    ----------
    vertices : (V, 3) float32, cm
    shapes : (M, 4) int64
        Chosen shapes per bundle (extended index: 0 neutral, k + 1 dataset shape k).
    weights : (M, 4) float64
        Their convex barycentric weights.
    n_containing : (M,) int64
        Simplices that contained the bundle (-1: not searched, the global weights already fit it).
    status : (M,) int64
        0 contained, 1 projected, 2 missing, 3 neighbour (took a natural neighbour's mixture), 4 fitted
        (the global fit's weights already fit the bundle's neighbourhood, no simplex searched; ``projection`` NaN).
    projection : (M,) float64, cm
        Distance from the bundle to where its chosen blend puts it before correction: to its cloud's
        volume when projected, to the neighbour's mixture when borrowed, 0 (or the snap offset) when
        contained.
    score : (M,) float64, cm
        RMS neighbour misfit of the chosen candidate.
    residual : (M,) float64, cm
        Distance from each seen bundle to the reconstructed surface point (NaN if missing).
    fallback : list of str
        For missing bundles: where their choice came from.
    jaw : (4,) float64 or None
        Jaw parameters of the frame (open, yaw, roll in degrees; forward in cm) when the index has a rig.
    bundles : (M, 3) float64 or None
        The bundle positions the frame was solved for.
    residual_before : (M,) float64 or None, cm
        Distance from each bundle to the blended (and, with a rig, skinned) surface before the smooth
        correction: what temporal smoothing or a projection left to correct.
    source : (M,) object or None
        Where each bundle's weights came from: "local fit" or "simplex".
    fit : GlobalFitResult or None
        The frame's global fit (jaw and weights of all shapes) the local fits started from.
    simplex_shapes, simplex_weights : (M, 4) int64 and float64, or None
        The simplex choice of every bundle (carried to the next frame's temporal preference).
    far_share : (M,) float64 or None
        How far each bundle's weights are trusted away from the bundles, as a share given to the global
        fit in the far field (0: the bundle's own geometry extrapolates as well as the global fit, 1: far
        worse; :meth:`LGISolver.far_shares`). None: 1 for every bundle.
    """

    vertices: np.ndarray
    shapes: np.ndarray
    weights: np.ndarray
    n_containing: np.ndarray
    status: np.ndarray
    projection: np.ndarray
    score: np.ndarray
    residual: np.ndarray
    fallback: list[str]
    jaw: np.ndarray | None = None
    bundles: np.ndarray | None = None
    residual_before: np.ndarray | None = None
    source: np.ndarray | None = None
    fit: GlobalFitResult | None = None
    simplex_shapes: np.ndarray | None = None
    simplex_weights: np.ndarray | None = None
    far_share: np.ndarray | None = None


@dataclass
class SequenceResult:
    """A reconstructed sequence: vertices (F, V, 3) float32 cm, frame numbers, per-bundle diagnostics,
    the jaw parameters used (F, 4) when the index has a rig, and each bundle's distance (F, M) cm to the
    blend before the correction (``before``) and to the final surface (``after``; NaN where missing)."""

    frames: np.ndarray
    vertices: np.ndarray
    diagnostics: pd.DataFrame
    jaw: np.ndarray | None = None
    noise: float = 0.0
    smooth: int = 1
    before: np.ndarray | None = None
    after: np.ndarray | None = None


def join_results(parts: list[SequenceResult]) -> SequenceResult:
    """Consecutive blocks of a sequence (:meth:`LGISolver.stream_prepared`) as one result."""
    def cat(get):
        got = [get(p) for p in parts]
        return None if got[0] is None else np.concatenate(got)

    return SequenceResult(cat(lambda p: p.frames), cat(lambda p: p.vertices),
                          pd.concat([p.diagnostics for p in parts], ignore_index=True), cat(lambda p: p.jaw),
                          parts[0].noise, parts[0].smooth, cat(lambda p: p.before), cat(lambda p: p.after))
