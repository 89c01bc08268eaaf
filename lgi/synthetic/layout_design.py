"""Designing marker layouts: variable-density Poisson-disk sampling on the neutral surface.

Production dot patterns are roughly even over the face and denser where the skin moves in complex
ways (around the mouth and eyes). This samples candidate surface points in a seeded random order and
accepts a point when it is at least the mean of the two points' radii ``r(p) = r0 / sqrt(density(p))``
from every accepted one; ``r0``
is found by bisection so that the layout has the requested number of markers.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from lgi.dataset.markers import MarkerLayout, layout_from_points


def poisson_disk(points: np.ndarray, density: np.ndarray, r0: float, order: np.ndarray) -> np.ndarray:
    """Indices of ``points`` accepted by variable-radius dart throwing in the given ``order``.

    Parameters
    ----------
    points : (N, 3) float
        Candidate positions.
    density : (N,) float
        Relative marker density (> 0); spacing scales as ``1 / sqrt(density)``.
    r0 : float
        Spacing where the density is 1, in point units.
    order : (N,) int
        Order in which candidates are tried.
    """
    radius = r0 / np.sqrt(density)
    tree = cKDTree(points)
    blocked = np.zeros(len(points), bool)
    accepted = []
    for i in order:
        if blocked[i]:
            continue
        accepted.append(i)
        # Block every candidate closer than the mean of the two radii (symmetric, keeps the contrast).
        near = np.asarray(tree.query_ball_point(points[i], max(radius[i], radius.max())))
        if near.size:
            d = np.linalg.norm(points[near] - points[i], axis=1)
            blocked[near[d < 0.5 * (radius[near] + radius[i])]] = True
    return np.asarray(accepted, np.int64)


def design_layout(
    vertices: np.ndarray,
    triangles: np.ndarray,
    candidates: np.ndarray,
    density: np.ndarray,
    n_markers: int,
    seed: int = 0,
    namer: Callable[[np.ndarray], list[str]] | None = None,
) -> MarkerLayout:
    """A layout of about ``n_markers`` markers at candidate vertices.

    Parameters
    ----------
    vertices : (V, 3) float; triangles : (T, 3) int
        The neutral mesh.
    candidates : (N,) int
        Vertices allowed to carry a marker (face area minus eyes, inner lips, borders).
    density : (N,) float
        Relative density at each candidate.
    n_markers : int
        Target count (met within 2 %, or as closely as the spacing allows).
    namer
        Maps the chosen positions (M, 3) to names; default ``m000``, ``m001``, ... top to bottom.
    """
    rng = np.random.default_rng(seed)
    pts = np.asarray(vertices, np.float64)[candidates]
    order = rng.permutation(len(pts))
    lo, hi = 1e-3, float(np.ptp(pts, axis=0).max())
    best = None
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        acc = poisson_disk(pts, density, mid, order)
        if best is None or abs(len(acc) - n_markers) < abs(len(best) - n_markers):
            best = acc
        if abs(len(acc) - n_markers) <= max(1, n_markers // 50):
            break
        if len(acc) > n_markers:
            lo = mid
        else:
            hi = mid
    chosen = pts[best]
    # Reading order: rows from top (forehead) to bottom, then left to right in the image.
    key = np.lexsort((-chosen[:, 0], -np.round(chosen[:, 1] / 0.5)))
    chosen = chosen[key]
    names = namer(chosen) if namer else [f"m{i:03d}" for i in range(len(chosen))]
    layout, _ = layout_from_points(names, chosen, vertices, triangles)
    return layout


def region_namer(anchors: dict[str, np.ndarray], mid_x: float = 0.0, center_band: float = 0.4) -> Callable:
    """Namer labelling each marker by its nearest anchor region and side: ``mouth_L_03``.

    Parameters
    ----------
    anchors : dict name -> (3,) or (K, 3)
        Representative points of each region.
    mid_x : float
        x of the face's midline; ``_L`` is +x (the actor's left), ``_C`` within ``center_band``.
    """
    names = list(anchors)
    pts = [np.atleast_2d(anchors[n]) for n in names]

    def name(chosen: np.ndarray) -> list[str]:
        out, count = [], {}
        for p in chosen:
            d = [np.linalg.norm(a - p, axis=1).min() for a in pts]
            region = names[int(np.argmin(d))]
            side = "C" if abs(p[0] - mid_x) < center_band else ("L" if p[0] > mid_x else "R")
            key = f"{region}_{side}"
            count[key] = count.get(key, 0) + 1
            out.append(f"{key}_{count[key]:02d}")
        return out

    return name
