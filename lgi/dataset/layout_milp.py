"""Marker layouts designed by integer programming (after Zell and McDonnell, "Compact facial landmark layouts").

Zell et al. choose landmarks by a weighted set cover: every blendshape k must have at least one landmark among the
vertices whose displacement in k is at least a fraction ``epsilon`` of that shape's largest (their eq. 3, 5b), and the
objective prefers large relative displacement (eq. 1, 5a); the number of landmarks is whatever the cover needs.
LGI needs something else, so the formulation is adapted (see ``docs/layout_design.md``):

* **The count is given** (``sum x = N``) instead of minimised: a capture is planned for a number of dots.
* **Vertices, not shapes, are covered.** LGI reconstructs every vertex from the shape weights found at nearby
  bundles and pulls the surface through the bundles. If vertex ``v``'s displacement is a fixed linear function of
  candidate ``c``'s in every shape (``d_v^k = A d_c^k``), any weights that reproduce a bundle at ``c`` reproduce ``v``
  too, whichever they are. So candidate ``c`` covers target vertex ``v`` at level ``l`` when ``cost(v, c) <= tau_l``
  (and ``|p_v - p_c| <= radius``) with::

      cost(v, c)^2 = min_A mean_k ||d_v^k - A d_c^k||^2 (ridge toward A = I)  +  (beta * |p_v - p_c|)^2

  (:func:`motion_cost`; the small distance term keeps still regions covered). The objective is a graded
  (multi-level) maximum coverage: maximising ``sum_v sum_l (tau_{l+1}^2 - tau_l^2) y_vl`` with
  ``y_vl <= sum_{c covers v at l} x_c`` is a step-wise approximation of the p-median of squared costs
  ``sum_v min_c cost(v, c)^2`` (an RMS proxy) that stays a small, sparse MILP (no ``V x C`` assignment variables).
* **Zell's cover is kept as a constraint**: every shape whose motion can be seen on the allowed surface has at least
  one marker with relative displacement ``>= epsilon`` (eq. 3, 5b); shapes with no such candidate are reported.
  Zell's quality ``r`` (eq. 2) is a small tie-break in the objective. Global visibility (eq. 4) is not used: a
  head-mounted camera sees the allowed region (the exclusions say where it does not).
* **Symmetry** is one variable per mirror pair (a pair counts 2, a midline candidate 1), instead of Zell's
  pre-processing of the blendshapes followed by mirroring: the pair is chosen on the motion of both sides.
* **Minimum spacing**: ``x_a + x_b <= 1`` for candidates closer than the spacing (and, tighter for the LP
  relaxation, ``sum x <= 1`` over every ball of half the spacing around a candidate), which also replaces Zell's
  neighbourhood removal in their adaptive multi-cover.

Lengths are in the dataset's units (cm) unless said otherwise.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.optimize import Bounds, LinearConstraint, milp
from scipy.spatial import cKDTree

from lgi.errors import InputError


# ------------------------------------------------------------------------------------------ sampling
def voxel_subsample(points: np.ndarray, spacing: float, allowed: np.ndarray | None = None) -> np.ndarray:
    """One point per cube of side ``spacing``: the one nearest the cube's centre (deterministic).

    Parameters
    ----------
    points : (V, 3) float
    spacing : float
        Cube side, in point units.
    allowed : (V,) bool, optional
        Only these points are considered (default all).

    Returns
    -------
    (K,) int64
        Indices into ``points``, sorted.
    """
    idx = np.arange(len(points)) if allowed is None else np.flatnonzero(allowed)
    if idx.size == 0:
        return idx.astype(np.int64)
    p = np.asarray(points, np.float64)[idx]
    cell = np.floor(p / spacing).astype(np.int64)
    off = np.linalg.norm(p - (cell + 0.5) * spacing, axis=1)
    _, key = np.unique(cell, axis=0, return_inverse=True)
    key = key.ravel()
    order = np.lexsort((off, key))  # by cell, then nearest the centre first
    first = np.ones(order.size, bool)
    first[1:] = key[order[1:]] != key[order[:-1]]
    return np.sort(idx[order[first]]).astype(np.int64)


def symmetry_plane(points: np.ndarray, axis: int = 0, iterations: int = 5) -> float:
    """Position of the mirror plane ``x[axis] = c`` of a roughly symmetric point set.

    Starts from the mean and moves ``c`` by the median offset between each point's mirror image and its
    nearest point (a few iterations of a one-parameter ICP), so an off-centre mesh is handled.

    Parameters
    ----------
    points : (V, 3) float
    axis : int
        The left-right axis (0: x toward the actor's left, as lgi's meshes are).

    Returns
    -------
    float, in point units
    """
    p = np.asarray(points, np.float64)
    c = float(p[:, axis].mean())
    tree = cKDTree(p)
    sample = p[:: max(1, len(p) // 5000)]
    for _ in range(iterations):
        m = sample.copy()
        m[:, axis] = 2 * c - m[:, axis]
        _, j = tree.query(m)
        # The mirror of sample i should land on p[j]: c is off by half the residual along the axis.
        c += 0.5 * float(np.median(p[j, axis] - m[:, axis]))
    return c


def mirror_partners(points: np.ndarray, candidates: np.ndarray, plane: float, tol: float, axis: int = 0
                    ) -> np.ndarray:
    """Mirror partner of each candidate among ``points`` (-1 when none lies within ``tol``).

    Parameters
    ----------
    points : (V, 3) float
    candidates : (K,) int
        Indices into ``points``.
    plane : float
        The mirror plane ``x[axis] = plane``.
    tol : float
        Largest distance between a candidate's mirror image and its partner.

    Returns
    -------
    (K,) int64
        Index into ``points`` of the partner (the candidate itself on the midline), or -1.
    """
    p = np.asarray(points, np.float64)
    m = p[candidates].copy()
    m[:, axis] = 2 * plane - m[:, axis]
    d, j = cKDTree(p).query(m)
    return np.where(d <= tol, j, -1).astype(np.int64)


# ------------------------------------------------------------------------------------------ the program
@dataclass
class DesignProblem:
    """What :func:`design_layout_milp` optimises over.

    Attributes
    ----------
    neutral : (V, 3) float64
        Neutral positions (cm).
    deltas : (S, V, 3) float
        Displacements of the shapes the layout is designed for (cm).
    allowed : (V,) bool
        Vertices that may carry a marker (paint can go there).
    targets_mask : (V,) bool
        Vertices whose reconstruction matters (the covered region).
    """

    neutral: np.ndarray
    deltas: np.ndarray
    allowed: np.ndarray
    targets_mask: np.ndarray
    shape_names: list[str] = field(default_factory=list)


@dataclass
class DesignOptions:
    """Parameters of the program (lengths in cm).

    Attributes
    ----------
    count : int
        Number of markers N.
    min_spacing : float
        Smallest distance between two markers (0: none).
    symmetric : bool
        Select mirror pairs together (mirror across the plane ``x = c``, :func:`symmetry_plane`).
    candidate_spacing : float or None
        Cube side of the candidate subsample (None: from the allowed area and ``count``, about 4 candidates per
        marker's share of the area, at least 1/3 of ``min_spacing``).
    target_spacing : float or None
        Cube side of the subsample of covered vertices (None: 0.8 x the candidate spacing).
    radius : float or None
        A candidate covers vertices within this distance (None: 2.5 x the mean marker spacing).
    levels : int
        Number of coverage levels ``tau_l``, spaced geometrically between the ``low_percentile`` and the
        ``high_percentile`` of the cheapest cost each target reaches within the mean marker spacing.
    low_percentile, high_percentile : float
        See ``levels`` (50 and 99).
    beta : float
        Weight of the distance term of the cost: ``beta`` cm of cost per cm apart.
    model : "linear" or "difference"
        How a candidate's motion predicts a vertex's (:func:`motion_cost`).
    ridge : float
        Regularisation of the linear model, cm (:func:`motion_cost`).
    epsilon : float
        Zell's threshold on relative displacement (eq. 3) for the per-shape cover constraints; 0 disables them.
    quality_weight : float
        Weight of Zell's relative displacement as a tie-break, relative to one target's full coverage.
    time_limit : float
        Seconds HiGHS may spend; the best layout found is used (and the gap reported) when it runs out.
    mip_rel_gap : float
        Relative optimality gap at which HiGHS stops (1 %: the objective is only a proxy of the error; measured
        errors of layouts within a percent of each other's objective differ by up to ~25 % either way, so a
        tighter gap does not reliably help, and on ICT it costs minutes).
    """

    count: int
    min_spacing: float = 0.8
    symmetric: bool = False
    candidate_spacing: float | None = None
    target_spacing: float | None = None
    radius: float | None = None
    levels: int = 8
    low_percentile: float = 50.0
    high_percentile: float = 99.0
    beta: float = 0.02
    model: str = "linear"
    ridge: float = 0.01
    epsilon: float = 0.5
    quality_weight: float = 0.01
    time_limit: float = 60.0
    mip_rel_gap: float = 1e-2


@dataclass
class DesignResult:
    """A designed layout and how it was found.

    Attributes
    ----------
    vertices : (N,) int64
        Chosen vertices (markers sit on them).
    partner : (N,) int64
        Mirror partner of each chosen vertex among ``vertices`` (itself on the midline; -1 when not symmetric).
    info : dict
        Sizes of the program, solver status, objective, gap, timings, uncovered shapes.
    """

    vertices: np.ndarray
    partner: np.ndarray
    info: dict


def surface_area(neutral: np.ndarray, triangles: np.ndarray, mask: np.ndarray) -> float:
    """Area of the triangles whose corners are all in ``mask`` (units^2)."""
    t = np.asarray(triangles)
    t = t[np.asarray(mask)[t].all(1)]
    p = np.asarray(neutral, np.float64)
    return float(0.5 * np.linalg.norm(np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]), axis=1).sum())


def _pairs_within(a: np.ndarray, b: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All (i, j) with |a_i - b_j| <= r, and the distances."""
    m = cKDTree(a).sparse_distance_matrix(cKDTree(b), r, output_type="coo_matrix")
    # sparse_distance_matrix drops exact zeros (a point paired with itself): add them back.
    zi, zj = cKDTree(a).query(b, distance_upper_bound=1e-12)
    hit = np.isfinite(zi)
    i = np.concatenate([m.row, zj[hit]]).astype(np.int64)
    j = np.concatenate([m.col, np.flatnonzero(hit)]).astype(np.int64)
    d = np.concatenate([m.data, np.zeros(hit.sum())])
    key = np.unique(i * len(b) + j, return_index=True)[1]
    return i[key], j[key], d[key]


def motion_cost(deltas: np.ndarray, neutral: np.ndarray, v: np.ndarray, c: np.ndarray, beta: float,
                model: str = "linear", ridge: float = 0.01, chunk: int = 100_000) -> np.ndarray:
    """``cost(v_i, c_i)`` for vertex pairs: how badly ``c``'s motion predicts ``v``'s over the shapes, plus a
    distance term.

    ``model="linear"``: the RMS residual over shapes of the best linear map ``d_v^k ~ A d_c^k`` (one 3 x 3 ``A`` for
    all shapes, ridge-regularised toward the identity). This is what LGI needs: if ``v``'s displacement is a fixed
    linear function of ``c``'s in every shape, any shape weights that reproduce the bundle at ``c`` reproduce ``v``
    too, whichever they are. ``model="difference"``: ``A = I`` (``v`` moves as ``c`` does).

    Parameters
    ----------
    deltas : (S, V, 3) float, cm
    neutral : (V, 3) float, cm
    v, c : (P,) int
        Vertex pairs.
    beta : float
        cm of cost per cm of distance.
    model : "linear" or "difference"
    ridge : float, cm
        Regularisation of the linear map: a displacement of ``ridge`` cm over the shapes (RMS) is where the map is
        pulled halfway toward the identity (so a still candidate predicts nothing that moves).

    Returns
    -------
    (P,) float64, cm
    """
    s = deltas.shape[0]
    uv = np.unique(np.concatenate([v, c]))
    dd = np.ascontiguousarray(np.asarray(deltas[:, uv], np.float64).transpose(1, 0, 2))  # (U, S, 3)
    pos_v, pos_c = np.searchsorted(uv, v), np.searchsorted(uv, c)
    lam = s * ridge**2
    eye = np.eye(3)
    gram = np.einsum("usi,usj->uij", dd, dd) + lam * eye  # (U, 3, 3)
    out = np.empty(len(v))
    for lo in range(0, len(v), chunk):
        a, b = pos_v[lo:lo + chunk], pos_c[lo:lo + chunk]
        if model == "difference":
            sq = np.sum((dd[a] - dd[b]) ** 2, axis=(1, 2))
        else:
            # A^T = (G_c + lam I)^-1 (D_c^T D_v + lam I): least squares of D_v on D_c, ridge toward A = I.
            cross = np.einsum("psi,psj->pij", dd[b], dd[a])  # (P, 3, 3) D_c^T D_v
            at = np.linalg.solve(gram[b], cross + lam * eye)
            sq = np.sum((dd[a] - np.einsum("psi,pij->psj", dd[b], at)) ** 2, axis=(1, 2))
        dist = np.sum((neutral[v[lo:lo + chunk]] - neutral[c[lo:lo + chunk]]) ** 2, axis=1)
        out[lo:lo + chunk] = np.sqrt(sq / max(s, 1) + beta**2 * dist)
    return out


def relative_displacement(deltas: np.ndarray, where: np.ndarray, within: np.ndarray) -> np.ndarray:
    """Zell's ``r_n^k`` (eq. 2): each vertex's displacement over the shape's largest (over ``within``).

    Parameters
    ----------
    deltas : (S, V, 3) float
    where : (K,) int
        Vertices to evaluate.
    within : (V,) bool
        The region the maximum is taken over (the covered region: a shape's largest motion on the face).

    Returns
    -------
    (S, K) float64 in [0, 1] (0 for a shape that does not move there)
    """
    mag = np.linalg.norm(np.asarray(deltas[:, where], np.float64), axis=2)
    top = np.linalg.norm(np.asarray(deltas[:, np.flatnonzero(within)], np.float64), axis=2).max(1)
    return np.where(top[:, None] > 0, mag / np.where(top[:, None] > 0, top[:, None], 1.0), 0.0)


def greedy_packing(points: np.ndarray, weight: np.ndarray, spacing: float) -> int:
    """How many of ``points`` a greedy pass keeps at least ``spacing`` apart (a lower bound on the most that fit;
    used to say how far off an infeasible request is)."""
    tree = cKDTree(points)
    free = np.ones(len(points), bool)
    n = 0
    for i in np.argsort(-np.asarray(weight), kind="stable"):
        if free[i]:
            n += int(weight[i])
            free[tree.query_ball_point(points[i], spacing * (1 - 1e-9))] = False
    return n


def _candidates(x0: np.ndarray, allowed: np.ndarray, cs: float, o: DesignOptions):
    """The candidate marker positions: a subsample of the allowed vertices ``cand`` (spacing ``cs``, cm); with
    symmetry, chosen on one side and paired by mirroring (``mate``, a midline candidate its own). Returns
    ``(cand, mate, members, orbit_of, size, plane)``: every candidate vertex of either side, the orbit (pair) each
    belongs to, each orbit's size, and the symmetry plane's x (cm)."""
    plane = symmetry_plane(x0) if o.symmetric else 0.0
    if o.symmetric:
        folded = x0.copy()
        folded[:, 0] = np.abs(folded[:, 0] - plane)
        side = allowed & (x0[:, 0] >= plane - 0.5 * cs)
        cand = voxel_subsample(folded, cs, side)
        mate = mirror_partners(x0, cand, plane, tol=0.5 * cs)
        on_mid = np.abs(x0[cand, 0] - plane) < 0.25 * cs
        mate[on_mid] = cand[on_mid]
        ok = (mate >= 0) & allowed[np.maximum(mate, 0)]
        # A pair closer than the spacing cannot be taken together.
        ok &= on_mid | (np.linalg.norm(x0[cand] - x0[np.maximum(mate, 0)], axis=1) >= o.min_spacing)
        cand, mate = cand[ok], mate[ok]
        orbit_of = np.concatenate([np.arange(len(cand)), np.arange(len(cand))])
        members = np.concatenate([cand, mate])
        keep = np.ones(len(members), bool)
        keep[len(cand):] = mate != cand  # a midline candidate is its own partner: once
        members, orbit_of = members[keep], orbit_of[keep]
        size = np.where(mate == cand, 1, 2)
    else:
        cand = voxel_subsample(x0, cs, allowed)
        mate = np.full(len(cand), -1, np.int64)
        members, orbit_of = cand, np.arange(len(cand))
        size = np.ones(len(cand), np.int64)
    return cand, mate, members, orbit_of, size, plane


def _spacing_rows(x0: np.ndarray, cand: np.ndarray, members: np.ndarray, orbit_of: np.ndarray, n_var: int,
                  min_spacing: float, add: Callable[[sp.spmatrix, float, float], None]) -> int:
    """The spacing constraints, handed to ``add``: conflicting orbits (any members closer than ``min_spacing``,
    cm) exclude each other, and candidates within half the spacing of one candidate (pairwise conflicting) make a
    clique cut. Returns the number of conflicting pairs."""
    n_conf = 0
    if min_spacing > 0:
        pi, pj, _ = _pairs_within(x0[members], x0[members], min_spacing * (1 - 1e-9))
        oa, ob = orbit_of[pi], orbit_of[pj]
        keep = oa < ob
        pairs = np.unique(np.stack([oa[keep], ob[keep]], 1), axis=0)
        n_conf = len(pairs)
        if n_conf:
            k = np.arange(n_conf)
            add(sp.csr_matrix((np.ones(2 * n_conf), (np.concatenate([k, k]), pairs.T.ravel())),
                              shape=(n_conf, n_var)), -np.inf, 1.0)
        # Clique cuts: candidates within half the spacing of one candidate are pairwise conflicting.
        ci, cj, _ = _pairs_within(x0[cand], x0[cand], 0.5 * min_spacing * (1 - 1e-9))
        if len(ci):
            cl = sp.csr_matrix((np.ones(len(ci)), (ci, cj)), shape=(len(cand), n_var))
            big = np.asarray(cl.sum(1)).ravel() > 2
            if big.any():
                add(cl[big], -np.inf, 1.0)
    return n_conf


def _no_layout(res, cand_points: np.ndarray, size: np.ndarray, n: int, area: float, o: DesignOptions) -> None:
    """Raise why the integer program found no layout: infeasible (with how many a greedy packing fits), or out of
    time."""
    if res.status == 2 or "infeasible" in str(res.message).lower():
        most = greedy_packing(cand_points, size, o.min_spacing) if o.min_spacing > 0 else int(size.sum())
        extra = " with Zell's cover constraints (lower --epsilon)" if o.epsilon > 0 and most >= n else ""
        raise InputError(f"infeasible: {n} markers cannot be placed at least {o.min_spacing * 10:g} mm apart on "
                         f"the allowed surface{extra} (a greedy packing fits {most}; about {area:.0f} cm^2 "
                         "allowed): lower --count or --min-spacing, or allow more surface")
    raise InputError(f"the integer program found no layout within {o.time_limit:g} s ({res.message}): "
                     "raise the time limit or lower --count")


def design_layout_milp(problem: DesignProblem, triangles: np.ndarray, options: DesignOptions) -> DesignResult:
    """Choose ``options.count`` marker vertices by the integer program in the module docstring (HiGHS).

    Parameters
    ----------
    problem
        Neutral, shapes, allowed and covered vertices.
    triangles : (T, 3) int
        The neutral's triangles (for the allowed area, which sets the default spacings).
    options
        Count, spacing, symmetry and the program's parameters.

    Returns
    -------
    DesignResult

    Raises
    ------
    InputError
        When the request cannot be met (too few candidates, or the count does not fit at that spacing).
    """
    t0 = time.perf_counter()
    o = options
    x0 = np.asarray(problem.neutral, np.float64)
    deltas = problem.deltas
    n = int(o.count)
    allowed = np.asarray(problem.allowed, bool)
    if not allowed.any():
        raise InputError("no vertex is allowed to carry a marker: the exclusions cover the whole mesh")
    area = surface_area(x0, triangles, allowed)
    mean_gap = np.sqrt(max(area, 1e-12) / max(n, 1))  # side of each marker's share of the allowed area
    cs = o.candidate_spacing or max(mean_gap / 2.0, o.min_spacing / 3.0, 1e-6)
    ts = o.target_spacing or 0.8 * cs
    radius = o.radius or 2.5 * mean_gap

    cand, mate, members, orbit_of, size, plane = _candidates(x0, allowed, cs, o)
    n_orb = len(cand)
    if size.sum() < n:
        raise InputError(f"{n} markers asked for but only {int(size.sum())} candidate positions are allowed "
                         f"(candidate spacing {cs * 10:.1f} mm): lower --count or the exclusions")

    # Targets: the covered region, subsampled; each stands for its cube of surface.
    targets = voxel_subsample(x0, ts, np.asarray(problem.targets_mask, bool))
    ti, mi, dist = _pairs_within(x0[targets], x0[members], radius)
    cost = motion_cost(deltas, x0, targets[ti], members[mi], o.beta, o.model, o.ridge)
    # Levels: from the cost a marker within the mean spacing reaches for a typical target up to what the worst-off
    # targets reach within the radius.
    near = dist <= mean_gap
    best = np.full(len(targets), np.inf)
    np.minimum.at(best, ti[near], cost[near])
    fin = best[np.isfinite(best)]
    lo = max(float(np.percentile(fin, o.low_percentile)) if fin.size else 1e-3, 1e-4)
    hi = max(float(np.percentile(fin, o.high_percentile)) if fin.size else 1.0, 1.01 * lo)
    taus = np.geomspace(lo, hi, o.levels)
    # Covering a target at level l (cost <= tau_l) instead of l + 1 saves tau_{l+1}^2 - tau_l^2: the objective is
    # then a step-wise sum of squared costs (an RMS proxy, so the worst-off targets count most).
    top = np.append(taus[1:], 1.5 * hi)
    gain = top**2 - taus**2
    # Each target's orbit-level coverage sets, for every level (an orbit covers if one of its members does).
    rows, cols, lev = [], [], []
    orb = orbit_of[mi]
    for li, tau in enumerate(taus):
        sel = cost <= tau
        key = np.unique(ti[sel] * n_orb + orb[sel])
        rows.append(key // n_orb)
        cols.append(key % n_orb)
        lev.append(np.full(key.size, li))
    rows, cols, lev = np.concatenate(rows), np.concatenate(cols), np.concatenate(lev)
    # y variables only for (target, level) pairs some candidate can cover.
    tl = rows * o.levels + lev
    y_key, y_of = np.unique(tl, return_inverse=True)
    n_y = len(y_key)

    # Zell's relative displacement at the candidates (per orbit: the larger of the pair, as a pair is one choice).
    r = relative_displacement(deltas, members, np.asarray(problem.targets_mask, bool))  # (S, members)
    r_orb = np.zeros((r.shape[0], n_orb))
    np.maximum.at(r_orb.T, orbit_of, r.T)

    # Objective (minimise): -sum_v w_v y_vl - quality tie-break.
    gain_y = gain[y_key % o.levels] / gain.sum()
    c_obj = np.concatenate([-o.quality_weight * r_orb.mean(0) * size, -gain_y])
    n_var = n_orb + n_y
    a_rows, lbs, ubs = [], [], []

    def add(mat: sp.spmatrix, lb: np.ndarray | float, ub: np.ndarray | float) -> None:
        a_rows.append(sp.csr_matrix(mat))
        k = mat.shape[0]
        lbs.append(np.broadcast_to(lb, (k,)).astype(float))
        ubs.append(np.broadcast_to(ub, (k,)).astype(float))

    # Count.
    add(sp.csr_matrix((size.astype(float), (np.zeros(n_orb, int), np.arange(n_orb))), shape=(1, n_var)), n, n)
    # Coverage: y_k - sum_{orbits covering k} x_o <= 0.
    cov = sp.csr_matrix((np.concatenate([np.ones(n_y), -np.ones(len(rows))]),
                         (np.concatenate([np.arange(n_y), y_of]), np.concatenate([n_orb + np.arange(n_y), cols]))),
                        shape=(n_y, n_var))
    add(cov, -np.inf, 0.0)
    n_conf = _spacing_rows(x0, cand, members, orbit_of, n_var, o.min_spacing, add)
    # Zell's cover: every shape seen on the allowed surface gets a marker where it moves >= epsilon of its largest.
    uncovered = []
    if o.epsilon > 0:
        rep = r_orb >= o.epsilon
        moving = np.linalg.norm(np.asarray(deltas, np.float64).reshape(len(deltas), -1), axis=1) > 0
        has = rep.any(1) & moving
        names = problem.shape_names or [str(i) for i in range(len(deltas))]
        uncovered = [names[i] for i in np.flatnonzero(moving & ~has)]
        if has.any():
            sub = sp.csr_matrix(rep[has].astype(float))
            add(sp.hstack([sub, sp.csr_matrix((sub.shape[0], n_y))]), 1.0, np.inf)
    a = sp.vstack(a_rows, format="csr")
    integrality = np.concatenate([np.ones(n_orb), np.zeros(n_y)])
    t1 = time.perf_counter()
    res = milp(c_obj, integrality=integrality, bounds=Bounds(0, 1),
               constraints=LinearConstraint(a, np.concatenate(lbs), np.concatenate(ubs)),
               options={"time_limit": float(o.time_limit), "mip_rel_gap": float(o.mip_rel_gap), "disp": False})
    t2 = time.perf_counter()
    if res.x is None:
        _no_layout(res, x0[cand], size, n, area, o)
    pick = np.flatnonzero(np.round(res.x[:n_orb]) > 0.5)
    chosen = np.concatenate([cand[pick], mate[pick][mate[pick] != cand[pick]]]) if o.symmetric else cand[pick]
    partner = np.full(len(chosen), -1, np.int64)
    if o.symmetric:
        pos = {int(v): i for i, v in enumerate(chosen)}
        for c_, m_ in zip(cand[pick], mate[pick], strict=True):
            partner[pos[int(c_)]], partner[pos[int(m_)]] = pos[int(m_)], pos[int(c_)]
    covered = res.x[n_orb:] > 0.5
    w_levels = np.bincount(y_key[covered] % o.levels, minlength=o.levels) / max(len(targets), 1)
    info = {"candidates": int(size.sum()), "orbits": n_orb, "targets": len(targets), "levels": [float(t) for t in taus],
            "covered_share_per_level": w_levels.round(4).tolist(), "variables": n_var, "constraints": a.shape[0],
            "nonzeros": int(a.nnz), "conflicts": n_conf, "candidate_spacing": cs, "target_spacing": ts,
            "radius": radius, "plane": plane, "status": int(res.status), "message": str(res.message),
            "objective": float(-res.fun), "gap": float(getattr(res, "mip_gap", np.nan) or 0.0),
            "setup_s": t1 - t0, "solve_s": t2 - t1, "uncovered_shapes": uncovered}
    return DesignResult(chosen.astype(np.int64), partner, info)
