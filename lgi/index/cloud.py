"""Per-bundle point clouds and their overlapping, non-manifold simplices.

For bundle ``i`` the cloud holds its position on every shape (the neutral included). Pruning keeps
what can matter:

* a shape that moves the bundle less than ``max(min_motion_rel * largest motion, min_motion_abs)`` is
  *dropped*: it becomes an alias of the neutral point (for this bundle it is the neutral);
* points closer than ``merge_tol`` are *merged*: one representative point, the others its aliases.

Aliases keep the map from points back to shapes: when a candidate simplex puts most of its weight on
an aliased point, the solver tries every shape of that point and keeps the one that fits the
neighbouring bundles best, so a dropped shape can still be chosen where it matters (between bundles).

Simplices live in the cloud's own affine subspace: a bundle moved by few shapes has a flat (2D),
linear (1D) or single-point cloud, and tetrahedra there would be slivers. Candidate generation (see
``docs/indexing.md``):

1. a Delaunay tessellation of all points: covers the convex hull, so a bundle inside the hull is
   always inside some simplex;
2. Delaunay tessellations of ``n_subsets`` random subsets (``subset_fraction`` of the points, the
   neutral always in): the same region covered again by other combinations of shapes, which is what
   makes the volume non-manifold;
3. k-nearest-neighbour fans: every point with each combination of ``d`` of its ``knn`` nearest
   neighbours: small local simplices, many overlapping;

then filtered (degenerate, slivers, oversized), de-duplicated, and capped at ``budget`` per bundle
(the full Delaunay first, then the rest by quality).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from lgi.errors import InputError


@dataclass
class CloudOptions:
    """Pruning and simplex-generation parameters (lengths in the dataset's units, cm)."""

    min_motion_rel: float = 0.005
    min_motion_abs: float = 1e-4
    merge_tol: float = 1e-4
    flat_tol: float = 1e-4
    n_subsets: int = 4
    subset_fraction: float = 0.6
    knn: int = 0
    min_quality: float = 0.02
    max_edge_rel: float = 0.6
    budget: int = 20000
    seed: int = 0

    def __post_init__(self) -> None:
        # (name, CLI flag, least, most, whole number)
        checks = (("min_motion_rel", "--min-motion-rel", 0.0, 1.0, False),
                  ("min_motion_abs", "--min-motion-abs", 0.0, None, False),
                  ("merge_tol", "--merge-tol", 0.0, None, False), ("flat_tol", "flat_tol", 0.0, None, False),
                  ("n_subsets", "--subsets", 0, None, True), ("subset_fraction", "--subset-fraction", 0.0, 1.0, False),
                  ("knn", "--knn", 0, None, True), ("min_quality", "--min-quality", 0.0, 1.0, False),
                  ("max_edge_rel", "--max-edge-rel", 0.0, None, False), ("budget", "--budget", 1, None, True),
                  ("seed", "--seed", 0, None, True))
        for name, flag, least, most, whole in checks:
            v = getattr(self, name)
            ok = (isinstance(v, (int, np.integer)) if whole else isinstance(v, (int, float, np.number)))
            ok = ok and not isinstance(v, bool) and bool(np.isfinite(v)) and v >= least and (most is None or v <= most)
            if not ok:
                rng = f">= {least}" if most is None else f"in [{least}, {most}]"
                raise InputError(f"{flag} must be {'a whole number' if whole else 'a number'} {rng}, not {v!r}")

    def to_json(self) -> dict:
        return dict(self.__dict__)


@dataclass
class BundleCloud:
    """One bundle's pruned cloud and simplices (local coordinates of its affine subspace).

    Attributes
    ----------
    origin : (3,) float64
        The neutral point (subspace origin).
    basis : (3, d) float64
        Orthonormal directions of the subspace.
    points : (P, d) float64
        Local coordinates of the representative points (point 0 is the neutral).
    point_shape : (P,) int64
        Representative shape of each point (extended index: 0 = neutral, k + 1 = dataset shape k).
    aliases : list of (A_p,) int64
        Every shape of each point, representative first.
    simplices : (N, d + 1) int64
        Point indices.
    kinds : (N,) int8
        0 full Delaunay, 1 subset Delaunay, 2 kNN fan.
    hull : (H, d) int64
        Boundary facets of the convex hull (for projection); for d = 0 one row with point 0.
    report : dict
        Counts: shapes, dropped, merged, points, simplices by kind, filtered.
    """

    origin: np.ndarray
    basis: np.ndarray
    points: np.ndarray
    point_shape: np.ndarray
    aliases: list[np.ndarray]
    simplices: np.ndarray
    kinds: np.ndarray
    hull: np.ndarray
    report: dict = field(default_factory=dict)

    @property
    def dim(self) -> int:
        return int(self.basis.shape[1])


def _subspace(x: np.ndarray, tol: float) -> np.ndarray:
    """Orthonormal basis (3, d) of the directions in which centred points ``x`` spread more than tol."""
    if len(x) < 2:
        return np.zeros((3, 0))
    _, s, vt = np.linalg.svd(x - x[0], full_matrices=False)
    # Spread along a direction: singular value / sqrt(n) is the RMS extent.
    d = int(np.sum(s / np.sqrt(len(x)) > tol))
    return vt[:d].T.copy()


def _quality(p: np.ndarray) -> np.ndarray:
    """Shape quality of simplices (N, d+1, d) in [0, 1]: volume over (RMS edge length)^d, normalised so a
    regular simplex scores 1 (1 for all 1-simplices of positive length)."""
    n, k, d = p.shape
    if d == 0:
        return np.ones(n)
    e = p[:, 1:] - p[:, :1]
    vol = np.abs(np.linalg.det(e)) if d > 1 else np.abs(e[:, 0, 0])
    pairs = list(itertools.combinations(range(k), 2))
    l2 = np.mean([np.sum((p[:, a] - p[:, b]) ** 2, axis=1) for a, b in pairs], axis=0)
    lrms = np.sqrt(l2)
    regular = {1: 1.0, 2: np.sqrt(3) / 2, 3: 1 / np.sqrt(2)}[d]  # det of a regular unit simplex
    return np.where(lrms > 0, vol / np.maximum(lrms, 1e-300) ** d / regular, 0.0)


def _delaunay(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Simplices and hull facets of a Delaunay tessellation in 1-3 dimensions."""
    from scipy.spatial import Delaunay

    d = points.shape[1]
    if d == 1:
        order = np.argsort(points[:, 0])
        simp = np.stack([order[:-1], order[1:]], axis=1)
        return simp, np.array([[order[0]], [order[-1]]])
    tri = Delaunay(points, qhull_options="Qbb Qc Qz Q12" if d == 3 else "Qbb Qc Qz")
    return tri.simplices.astype(np.int64), tri.convex_hull.astype(np.int64)


def build_cloud(positions: np.ndarray, opts: CloudOptions, rng: np.random.Generator) -> BundleCloud:
    """Prune one bundle's positions and generate its simplices.

    Parameters
    ----------
    positions : (S + 1, 3) float
        The bundle on the neutral (row 0) and on every dataset shape, cm.
    """
    from scipy.spatial import QhullError, cKDTree  # build time only: not imported by every command

    pos = np.asarray(positions, np.float64)
    n_shapes = len(pos) - 1
    motion = np.linalg.norm(pos - pos[0], axis=1)
    thresh = max(opts.min_motion_rel * float(motion.max()), opts.min_motion_abs)
    moving = np.flatnonzero(motion >= thresh)
    moving = moving[moving > 0]
    dropped = np.flatnonzero((motion < thresh) & (np.arange(len(pos)) > 0))

    # Merge near-duplicates greedily in shape order (the neutral is point 0 and absorbs the dropped).
    reps = [0]
    aliases: list[list[int]] = [[0, *dropped.tolist()]]
    merged = 0
    if moving.size:
        tree = cKDTree(pos[moving])
        taken = np.zeros(len(moving), bool)
        for a in range(len(moving)):
            if taken[a]:
                continue
            group = [b for b in tree.query_ball_point(pos[moving[a]], opts.merge_tol) if not taken[b]]
            group.sort()
            taken[group] = True
            reps.append(int(moving[group[0]]))
            aliases.append([int(moving[g]) for g in group])
            merged += len(group) - 1
    reps_arr = np.asarray(reps)
    origin = pos[0].copy()
    basis = _subspace(pos[reps_arr], opts.flat_tol)
    local = (pos[reps_arr] - origin) @ basis
    d = basis.shape[1]
    # Every dropped or merged shape lies within this distance of its point: the solver snaps to points
    # this close so that their aliases can be chosen.
    snap = 1.5 * max(thresh, opts.merge_tol)
    report = {"shapes": n_shapes, "dropped_static": int(dropped.size), "merged_duplicates": merged,
              "points": len(reps), "dim": d, "snap_radius": snap}

    if d == 0 or len(reps) <= d:
        simp = np.zeros((1, 1), np.int64) if d == 0 else np.arange(len(reps))[None]
        if d > 0:  # too few points for a full-dimensional simplex: keep the point alone
            basis, local, d = np.zeros((3, 0)), np.zeros((len(reps), 0)), 0
            simp = np.zeros((1, 1), np.int64)
        report.update(simplices=1, by_kind=[1, 0, 0], filtered=0)
        return BundleCloud(origin, basis, local, reps_arr, [np.asarray(a) for a in aliases], simp,
                           np.zeros(1, np.int8), np.zeros((1, 1), np.int64), report)

    base, hull = _delaunay(local)
    extent = float(np.ptp(local, axis=0).max())
    extra = []
    n = len(local)
    for _ in range(opts.n_subsets if n > d + 2 else 0):
        k = max(d + 1, int(round(opts.subset_fraction * n)))
        pick = np.r_[0, 1 + rng.choice(n - 1, size=min(k, n) - 1, replace=False)]
        try:
            s, _ = _delaunay(local[pick])
        except (QhullError, ValueError):
            continue
        extra.append((pick[s], 1))
    if opts.knn > d and n > d + 1:
        kk = min(opts.knn, n - 1)
        _, nbr = cKDTree(local).query(local, k=kk + 1)
        fans = [np.column_stack([np.arange(n), nbr[:, list(c)]]) for c in itertools.combinations(range(1, kk + 1), d)]
        extra.append((np.concatenate(fans), 2))

    # Base tessellation: drop only degenerate simplices (they cover nothing a neighbour does not).
    qb = _quality(local[base])
    keep_b = qb > 1e-9
    simp_list = [base[keep_b]]
    kind_list = [np.zeros(int(keep_b.sum()), np.int8)]
    filtered = int((~keep_b).sum())
    if extra:
        allc = np.concatenate([simp_list[0]] + [s for s, _ in extra])
        allk = np.concatenate([np.full(len(simp_list[0]), -1, np.int8)]
                              + [np.full(len(s), k, np.int8) for s, k in extra])
        key = np.sort(allc, axis=1)
        # First occurrence wins, so a simplex already in the base tessellation is not repeated.
        _, first = np.unique(key, axis=0, return_index=True)
        first = np.sort(first)
        distinct = np.all(np.diff(key[first], axis=1) > 0, axis=1)
        first = first[distinct & (allk[first] >= 0)]
        cs, ck = allc[first], allk[first]
    else:
        cs, ck = np.zeros((0, d + 1), np.int64), np.zeros(0, np.int8)
    if len(cs):
        q = _quality(local[cs])
        pts = local[cs]
        edges = np.max([np.linalg.norm(pts[:, a] - pts[:, b], axis=1)
                        for a, b in itertools.combinations(range(d + 1), 2)], axis=0)
        ok = (q >= opts.min_quality) & (edges <= opts.max_edge_rel * extent)
        filtered += int((~ok).sum())
        cs, ck, q = cs[ok], ck[ok], q[ok]
        room = max(opts.budget - len(simp_list[0]), 0)
        if len(cs) > room:
            best = np.sort(np.argsort(-q, kind="stable")[:room])
            filtered += len(cs) - room
            cs, ck = cs[best], ck[best]
        simp_list.append(cs)
        kind_list.append(ck)
    simplices = np.concatenate(simp_list)
    kinds = np.concatenate(kind_list)
    report.update(simplices=int(len(simplices)), by_kind=np.bincount(kinds, minlength=3).tolist(), filtered=filtered)
    return BundleCloud(origin, basis, local, reps_arr, [np.asarray(a) for a in aliases], simplices, kinds, hull,
                       report)


def barycentric_inverse(points: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """(N, d, d) inverses ``T^-1`` with ``lambda[1:] = T^-1 (y - p0)`` for each simplex."""
    p = points[simplices]
    t = np.transpose(p[:, 1:] - p[:, :1], (0, 2, 1))  # columns p_k - p_0
    return np.linalg.inv(t)
