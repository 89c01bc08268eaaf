"""Compiled loops of the per-bundle choice (numba): the simplex search and candidate scoring of one frame
(:func:`solve_bundles`), the neighbours' agreement for the second pass, and the local refits
(:func:`local_fits`). Called by :mod:`lgi.solve.selection`.

Arrays are the flattened index (see :mod:`lgi.index.build`): per-bundle blocks of points, simplices, hull
facets and grid cells addressed through offset arrays. Local coordinates are padded to 3 components and
simplices to 4 corners (-1 where unused); a bundle's dimension ``d`` says how many are real.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from lgi.index._grid_kernels import _bary, _cell, _closest_on_segment, _closest_on_triangle
from lgi.solve.qp import box_qp

# Status codes written to the diagnostics.
CONTAINED, PROJECTED, MISSING, BORROWED = 0, 1, 2, 3
# A candidate's own distance to the bundle counts as much as this many natural neighbours' misfits
# (measured on held-out ICT and synthetic frames, see docs/indexing.md).
OWN_WEIGHT = 4.0


class IndexArrays(NamedTuple):
    """The flattened index the search reads (:mod:`lgi.index.build`), gathered once per solver: M bundles,
    P cloud points, T simplices (``sx`` (T, 4) corners, ``tinv`` (T, 3, 3) their inverse maps), hull facets and
    grid cells, each bundle's block addressed by an offset array (M+1,)."""

    dim: np.ndarray  # (M,) int64: each cloud's dimension d (0-3)
    origin: np.ndarray  # (M, 3) cm: the cloud's local frame, origin
    basis: np.ndarray  # (M, 3, 3): and axes (the first d real)
    pts: np.ndarray  # (P, 3): the clouds' points in local coordinates (padded to 3)
    pt_off: np.ndarray  # (M+1,)
    pt_shape: np.ndarray  # (P,): each point's representative shape
    alias_off: np.ndarray  # (P+1,): each point's alias classes
    class_off: np.ndarray  # each class's shapes in alias_shape
    alias_shape: np.ndarray
    sx: np.ndarray
    tinv: np.ndarray
    hull: np.ndarray  # (H, 3): hull facets' corners (points)
    hull_off: np.ndarray  # (M+1,)
    lo: np.ndarray  # (M, 3): each bundle's grid, lower corner
    h: np.ndarray  # (M,): cell size
    dims: np.ndarray  # (M, 3): cells per axis
    cell_off: np.ndarray  # (M+1,): each bundle's first cell
    cell_start: np.ndarray  # (C+1,): each cell's simplices in items
    items: np.ndarray
    ptab: np.ndarray  # (S+1, M, 3) cm: every extended shape at every bundle
    nb_off: np.ndarray  # (M+1,): natural neighbours
    nb_idx: np.ndarray
    snap_r: np.ndarray  # (M,): snap radius of the dataset points


class SearchSettings(NamedTuple):
    """The solver's settings of the search (:class:`lgi.solve.solver.LGISolver`)."""

    alias_min_w: float  # a corner tries its point's merged shapes from this weight
    tol: float  # barycentric tolerance of containment
    dist_tol: float  # cm: off a flat cloud's plane by less is still inside it
    n_project: int  # hull facets tried when nothing contains a bundle
    top_k: int  # candidates kept per bundle for the second pass


class FramePass(NamedTuple):
    """One pass of the search over a frame's bundles."""

    p: np.ndarray  # (M, 3) float64, cm: the bundles (zeros where missing)
    seen: np.ndarray  # (M,) bool
    prev: np.ndarray  # (M, 4) int64: the previous frame's shapes (-1: none)
    mu: float  # temporal weight, cm (0: none)
    agree: np.ndarray  # (M, S+1): the shapes' support (:func:`agreement`; unused when nu is 0)
    nu: float  # agreement weight, cm (0: the first pass)
    first_shapes: np.ndarray  # (M, 4) int64: the first pass's shapes (second pass)
    first_lam: np.ndarray  # (M, 4): and weights
    cand: np.ndarray  # (M, top_k) int64: the first pass's candidates (rows of -2: scan the grid)
    cand_score: np.ndarray  # (M, top_k): their scores
    first_score: np.ndarray  # (M,): each bundle's first-pass best
    active: np.ndarray  # (M,) bool: the bundles searched


class Choice(NamedTuple):
    """:func:`solve_bundles`' result for M bundles."""

    shapes: np.ndarray  # (M, 4) int64: extended shape indices
    lam: np.ndarray  # (M, 4): their weights
    points: np.ndarray  # (M, 4) int64: the corners' cloud points (-1 unused)
    n_contain: np.ndarray  # (M,) int64
    status: np.ndarray  # (M,) int64
    proj: np.ndarray  # (M,) cm
    score: np.ndarray  # (M,) cm
    cand: np.ndarray  # (M, top_k) int64: the distinct best containing simplices (-1 padded)
    cand_score: np.ndarray  # (M, top_k): their scores

@nb.njit(cache=True, inline="always")
def _misfit(i, ix, fr, shapes, lam, nz, own2):  # pragma: no cover - compiled
    """RMS distance (cm) of the natural neighbours, and of the bundle itself (``own2``, squared, weighted
    OWN_WEIGHT), to where the candidate's blend of shapes puts them."""
    tot = OWN_WEIGHT * own2
    cnt = OWN_WEIGHT
    for e in range(ix.nb_off[i], ix.nb_off[i + 1]):
        j = ix.nb_idx[e]
        if not fr.seen[j]:
            continue
        for k in range(3):
            acc = -fr.p[j, k]
            for c in range(nz):
                acc += lam[c] * ix.ptab[shapes[c], j, k]
            tot += acc * acc
        cnt += 1
    return np.sqrt(tot / cnt)


@nb.njit(cache=True, inline="always")
def _penalty(i, fr, shapes, lam, nz):  # pragma: no cover - compiled
    """Temporal (shapes not shared with the previous frame) and agreement (shapes the frame's evidence
    does not support) terms of the score, cm."""
    prev, mu, agree, nu = fr.prev, fr.mu, fr.agree, fr.nu
    out = 0.0
    if mu > 0 and prev[i, 0] >= 0:
        shared = 0
        for c in range(nz):
            for q in range(4):
                if prev[i, q] == shapes[c]:
                    shared += 1
                    break
        out += mu * (1.0 - shared / nz)
    if nu > 0:
        ag = 0.0
        for c in range(nz):
            ag += lam[c] * agree[i, shapes[c]]
        out += nu * (1.0 - ag)
    return out


@nb.njit(cache=True)
def _consider(i, ix, cfg, fr, shapes, lam, nz, own2, alias_pt, kept):  # pragma: no cover - compiled
    """Score one candidate and keep it in ``kept`` (best shapes, weights, points, score; the last score) if it
    is the best so far; returns True if it is. ``shapes`` is changed in place (each corner left at its best
    alias): the callers fill a candidate afresh each time.

    Every corner with weight >= alias_min_w (heaviest first) tries the shapes merged into its cloud
    point, one alias class at a time (a class: shapes that also coincide at all natural neighbours, so
    they share one misfit); within a class the temporal and agreement terms pick the member.
    """
    alias_off, class_off, alias_shape = ix.alias_off, ix.class_off, ix.alias_shape
    prev, mu, agree, nu = fr.prev, fr.mu, fr.agree, fr.nu
    best_shapes, best_lam, best_pts, best, last = kept
    done = 0  # a bit per corner
    for _ in range(nz):
        c = -1
        for q in range(nz):
            if not done & (1 << q) and (c < 0 or lam[q] > lam[c]):
                c = q
        done |= 1 << c
        pt = alias_pt[c]
        if pt < 0 or lam[c] < cfg.alias_min_w or alias_off[pt + 1] - alias_off[pt] <= 1 and \
                class_off[alias_off[pt] + 1] - class_off[alias_off[pt]] <= 1:
            continue
        keep = shapes[c]
        keep_sc = 1e300
        for cls in range(alias_off[pt], alias_off[pt + 1]):
            shapes[c] = alias_shape[class_off[cls]]
            fit = _misfit(i, ix, fr, shapes, lam, nz, own2)
            if fit >= keep_sc:
                continue
            member = shapes[c]
            if (mu > 0 and prev[i, 0] >= 0) or nu > 0:
                # Members differ only in this corner's temporal and agreement terms: take the best.
                best_gain = -1.0
                for o in range(class_off[cls], class_off[cls + 1]):
                    m_ = alias_shape[o]
                    gain = 0.0
                    if nu > 0:
                        gain += nu * lam[c] * agree[i, m_]
                    if mu > 0 and prev[i, 0] >= 0:
                        for q in range(4):
                            if prev[i, q] == m_:
                                gain += mu / nz
                                break
                    if gain > best_gain:
                        best_gain = gain
                        member = m_
                shapes[c] = member
            pen = _penalty(i, fr, shapes, lam, nz)
            if fit + pen < keep_sc:
                keep_sc = fit + pen
                keep = member
        shapes[c] = keep
    sc = _misfit(i, ix, fr, shapes, lam, nz, own2) + _penalty(i, fr, shapes, lam, nz)
    last[0] = sc
    if sc < best[0]:
        best[0] = sc
        for c in range(4):
            best_shapes[c] = shapes[c] if c < nz else 0
            best_lam[c] = lam[c] if c < nz else 0.0
            best_pts[c] = alias_pt[c] if c < nz else -1
        return True
    return False


@nb.njit(cache=True)
def _take_simplex(s, lam, sx, pt_shape, d, shapes, apt):  # pragma: no cover - compiled
    """Clamp tiny negative weights, renormalise, and fill the candidate's shapes and cloud points."""
    tot = 0.0
    for c in range(d + 1):
        lam[c] = max(lam[c], 0.0)
        tot += lam[c]
    for c in range(d + 1):
        lam[c] /= tot
        apt[c] = sx[s, c]
        shapes[c] = pt_shape[sx[s, c]]


@nb.njit(cache=True, inline="always")
def _local_coordinates(i, ix, p, y):  # pragma: no cover - compiled
    """Bundle i in its cloud's local frame (``y`` (3,), the first d real); returns its squared distance off
    the cloud's span, cm^2."""
    d = ix.dim[i]
    off2 = 0.0
    for k in range(d):
        acc = 0.0
        for r in range(3):
            acc += ix.basis[i, r, k] * (p[i, r] - ix.origin[i, r])
        y[k] = acc
    for r in range(3):
        acc = p[i, r] - ix.origin[i, r]
        for k in range(d):
            acc -= ix.basis[i, r, k] * y[k]
        off2 += acc * acc
    return off2


@nb.njit(cache=True, inline="always")
def _rescore(i, ix, cfg, fr, y, off2, kept, work):  # pragma: no cover - compiled
    """The second pass: the first pass's distinct best containing simplices, no grid scan. The agreement term
    adds at most nu and the sweep only raises a first-pass score, so a candidate more than nu behind the
    first-pass winner cannot win: skipped. Returns the number of candidates."""
    d = ix.dim[i]
    lam, shapes, apt = work[0], work[1], work[2]
    found = 0
    for r in range(cfg.top_k):
        s = fr.cand[i, r]
        if s < 0:
            break
        found += 1
        if fr.cand_score[i, r] > fr.first_score[i] + fr.nu + 1e-15:
            continue
        _bary(y, s, ix.sx, ix.tinv, ix.pts, d, lam)
        _take_simplex(s, lam, ix.sx, ix.pt_shape, d, shapes, apt)
        _consider(i, ix, cfg, fr, shapes, lam, d + 1, off2, apt, kept)
    return found


@nb.njit(cache=True, inline="always")
def _scan_grid(i, ix, cfg, fr, y, off2, kept, work, out):  # pragma: no cover - compiled
    """The first pass: every simplex of the bundle's grid cell containing it, pre-screened by misfit; the best
    ``top_k`` distinct blends scored in full and kept in ``out`` for the second pass. Returns the number of
    containing simplices."""
    d = ix.dim[i]
    lam, shapes, apt = work[0], work[1], work[2]
    last = kept[4]
    cell = _cell(y, i, ix.lo, ix.h, ix.dims, ix.cell_off, d)
    if cell < 0:
        return 0
    found = 0
    n_items = ix.cell_start[cell + 1] - ix.cell_start[cell]
    cand = np.empty(n_items, np.int64)
    pre = np.empty(n_items)
    for e in range(ix.cell_start[cell], ix.cell_start[cell + 1]):
        s = ix.items[e]
        _bary(y, s, ix.sx, ix.tinv, ix.pts, d, lam)
        inside = True
        for c in range(d + 1):
            if lam[c] < -cfg.tol:
                inside = False
        if not inside:
            continue
        _take_simplex(s, lam, ix.sx, ix.pt_shape, d, shapes, apt)
        cand[found] = s
        # Pre-screen with the points' representative shapes; only the best go on to the full score (alias
        # sweep, temporal and agreement terms).
        pre[found] = _misfit(i, ix, fr, shapes, lam, d + 1, off2)
        found += 1
    order = np.argsort(pre[:found])
    kept_lam = np.zeros((cfg.top_k, 4))
    kept_shapes = np.zeros((cfg.top_k, 4), np.int64)
    n_kept = 0
    for r in range(found):
        if n_kept >= cfg.top_k:
            break
        s = cand[order[r]]
        _bary(y, s, ix.sx, ix.tinv, ix.pts, d, lam)
        _take_simplex(s, lam, ix.sx, ix.pt_shape, d, shapes, apt)
        dup = False
        for u in range(n_kept):  # the same blend reached through another simplex
            same = True
            for c in range(d + 1):
                hit = False
                for c2 in range(d + 1):
                    if kept_shapes[u, c2] == shapes[c] and abs(kept_lam[u, c2] - lam[c]) < 1e-12:
                        hit = True
                if lam[c] > 0 and not hit:
                    same = False
            if same:
                dup = True
                break
        if dup:
            continue
        for c in range(d + 1):
            kept_shapes[n_kept, c] = shapes[c]
            kept_lam[n_kept, c] = lam[c]
        _consider(i, ix, cfg, fr, shapes, lam, d + 1, off2, apt, kept)
        out.cand[i, n_kept] = s
        out.cand_score[i, n_kept] = last[0]
        n_kept += 1
    return found


@nb.njit(cache=True, inline="always")
def _snap(i, ix, cfg, fr, y, off2, kept, work):  # pragma: no cover - compiled
    """Points within the snap radius: their dropped and merged shapes lie there, so each point is tried alone
    (with its aliases), the bundle's own distance counted in the score. Returns the squared distance to the
    point that won (-1: none)."""
    d = ix.dim[i]
    lam, shapes, apt = work[0], work[1], work[2]
    snapped = -1.0
    for a in range(ix.pt_off[i], ix.pt_off[i + 1]):
        dd = off2
        for k in range(d):
            dd += (y[k] - ix.pts[a, k]) ** 2
        if dd <= ix.snap_r[i] * ix.snap_r[i]:
            shapes[0] = ix.pt_shape[a]
            apt[0] = a
            lam[0] = 1.0
            if _consider(i, ix, cfg, fr, shapes, lam, np.int64(1), dd, apt, kept):
                snapped = dd
    return snapped


@nb.njit(cache=True, inline="always")
def _project(i, ix, cfg, fr, y, off2, kept, work):  # pragma: no cover - compiled
    """No simplex contains the bundle: onto the hull, the ``n_project`` nearest facets, then the simplices
    containing each projected point, scored with the bundle's own distance included. Returns the squared
    projection distance within the cloud's span, cm^2."""
    d = ix.dim[i]
    pts, hull = ix.pts, ix.hull
    lam, shapes, apt, q, tmp = work
    best = kept[3]
    nh = ix.hull_off[i + 1] - ix.hull_off[i]
    dists = np.empty(nh)
    for f in range(nh):
        hf = ix.hull_off[i] + f
        if d == 3:
            dists[f] = _closest_on_triangle(y, pts[hull[hf, 0]], pts[hull[hf, 1]], pts[hull[hf, 2]], tmp)
        elif d == 2:
            dists[f] = _closest_on_segment(y, pts[hull[hf, 0]], pts[hull[hf, 1]], d, tmp)
        else:
            dists[f] = (y[0] - pts[hull[hf, 0], 0]) ** 2
    order = np.argsort(dists)
    best_proj = 1e300
    for rank in range(min(cfg.n_project, nh)):
        hf = ix.hull_off[i] + order[rank]
        if d == 3:
            d2 = _closest_on_triangle(y, pts[hull[hf, 0]], pts[hull[hf, 1]], pts[hull[hf, 2]], q)
        elif d == 2:
            d2 = _closest_on_segment(y, pts[hull[hf, 0]], pts[hull[hf, 1]], d, q)
        else:
            q[0] = pts[hull[hf, 0], 0]
            d2 = (y[0] - q[0]) ** 2
        cell = _cell(q, i, ix.lo, ix.h, ix.dims, ix.cell_off, d)
        if cell < 0:
            continue
        tried = 0
        for e in range(ix.cell_start[cell], ix.cell_start[cell + 1]):
            if tried >= cfg.top_k:
                break
            s = ix.items[e]
            _bary(q, s, ix.sx, ix.tinv, pts, d, lam)
            inside = True
            for c in range(d + 1):
                if lam[c] < -1e-6:
                    inside = False
            if not inside:
                continue
            tried += 1
            _take_simplex(s, lam, ix.sx, ix.pt_shape, d, shapes, apt)
            if _consider(i, ix, cfg, fr, shapes, lam, d + 1, off2 + d2 + 1e-300, apt, kept):
                best_proj = d2
    if best[0] >= 1e299:
        # Numerically no simplex contains the hull point: fall back to the nearest point.
        bestp = ix.pt_off[i]
        bd = 1e300
        for a in range(ix.pt_off[i], ix.pt_off[i + 1]):
            dd = 0.0
            for k in range(d):
                dd += (y[k] - pts[a, k]) ** 2
            if dd < bd:
                bd = dd
                bestp = a
        shapes[0] = ix.pt_shape[bestp]
        apt[0] = bestp
        lam[0] = 1.0
        _consider(i, ix, cfg, fr, shapes, lam, np.int64(1), off2 + bd + 1e-300, apt, kept)
        best_proj = bd
    return best_proj


@nb.njit(cache=True, inline="always")
def _borrow(i, ix, cfg, fr, kept, work):  # pragma: no cover - compiled
    """Second pass: each seen natural neighbour's first-pass mixture, scored with this bundle's own distance.
    A bundle that barely moves, or sits where its cloud has no combination of the shapes its neighbours show,
    cannot tell those shapes apart; its neighbours can. Returns the squared distance of the mixture that won
    (-1: none)."""
    lam, shapes, apt = work[0], work[1], work[2]
    borrowed = -1.0
    for e in range(ix.nb_off[i], ix.nb_off[i + 1]):
        j = ix.nb_idx[e]
        if not fr.seen[j]:
            continue
        dd = 0.0
        for k in range(3):
            acc = -fr.p[i, k]
            for c in range(4):
                acc += fr.first_lam[j, c] * ix.ptab[fr.first_shapes[j, c], i, k]
            dd += acc * acc
        nzj = 0
        for c in range(4):
            if fr.first_lam[j, c] > 0:
                shapes[nzj] = fr.first_shapes[j, c]
                lam[nzj] = fr.first_lam[j, c]
                apt[nzj] = -1
                nzj += 1
        if _consider(i, ix, cfg, fr, shapes, lam, nzj, dd, apt, kept):
            borrowed = dd
    return borrowed


@nb.njit(cache=True)
def _solve_one(i, ix, cfg, fr, out):  # pragma: no cover - compiled
    """Bundle i's row of :func:`solve_bundles` written into ``out`` (a :class:`Choice`)."""
    d = ix.dim[i]
    y = np.zeros(3)
    kept = (np.zeros(4, np.int64), np.zeros(4), np.full(4, -1, np.int64), np.full(1, 1e300), np.zeros(1))
    bshapes, blam, bpts, best, _ = kept
    # The candidate being scored (weights, shapes, cloud points) and a projection's points, filled by each step.
    work = (np.zeros(4), np.zeros(4, np.int64), np.full(4, -1, np.int64), np.zeros(3), np.zeros(3))
    off2 = _local_coordinates(i, ix, fr.p, y)
    found = 0
    if d == 0:
        lam, shapes, apt = work[0], work[1], work[2]
        lam[0] = 1.0
        shapes[0] = ix.pt_shape[ix.pt_off[i]]
        apt[0] = ix.pt_off[i]
        # np.int64(1), not 1: a literal argument is a type of its own, compiled again (first run after an install).
        _consider(i, ix, cfg, fr, shapes, lam, np.int64(1), off2, apt, kept)
        found = 1
    elif fr.cand[i, 0] >= -1:
        found = _rescore(i, ix, cfg, fr, y, off2, kept, work)
    else:
        found = _scan_grid(i, ix, cfg, fr, y, off2, kept, work, out)
    snapped = _snap(i, ix, cfg, fr, y, off2, kept, work)
    out.n_contain[i] = found
    if snapped >= 0:
        # On a dataset point (a pruned shape's position): inside the data, not a projection.
        out.status[i] = CONTAINED
        out.proj[i] = np.sqrt(snapped)
    elif found > 0:
        out.status[i] = CONTAINED if off2 <= cfg.dist_tol * cfg.dist_tol else PROJECTED
        out.proj[i] = np.sqrt(off2)
    else:
        best_proj = _project(i, ix, cfg, fr, y, off2, kept, work)
        out.status[i] = PROJECTED
        out.proj[i] = np.sqrt(off2 + best_proj)
    if fr.nu > 0:
        borrowed = _borrow(i, ix, cfg, fr, kept, work)
        if borrowed >= 0:
            out.status[i] = BORROWED
            out.proj[i] = np.sqrt(borrowed)
    out.score[i] = best[0]
    for c in range(4):
        out.shapes[i, c] = bshapes[c]
        out.lam[i, c] = blam[c]
        out.points[i, c] = bpts[c]


def new_choice(m: int, top_k: int) -> Choice:
    """:func:`solve_bundles`' outputs for m bundles, at their fill values (no shapes, status MISSING)."""
    return Choice(np.zeros((m, 4), np.int64), np.zeros((m, 4)), np.full((m, 4), -1, np.int64), np.zeros(m, np.int64),
                  np.full(m, MISSING, np.int64), np.zeros(m), np.full(m, np.nan), np.full((m, top_k), -1, np.int64),
                  np.full((m, top_k), np.inf))


@nb.njit(parallel=True, cache=True, nogil=True)
def solve_bundles(ix, cfg, fr, out):  # pragma: no cover - compiled
    """Choose every bundle's simplex and barycentric weights for one frame (bundles in parallel).

    Parameters
    ----------
    ix : IndexArrays
    cfg : SearchSettings
    fr : FramePass
        The pass's bundles and inputs. Only the seen bundles with ``fr.active`` are searched; the others keep
        the outputs' fill values (status MISSING, no shapes).
    out : Choice
        Written: :func:`new_choice` (made outside, since parallel loops cannot make a named tuple).
    """
    for i in nb.prange(fr.p.shape[0]):  # solve_bundles_serial: the same loop on one thread
        if fr.seen[i] and fr.active[i]:
            _solve_one(i, ix, cfg, fr, out)


@nb.njit(cache=True, nogil=True)
def solve_bundles_serial(ix, cfg, fr, out):  # pragma: no cover - compiled
    """:func:`solve_bundles` on the calling thread alone (a shot's frames chosen on one thread while another
    blends: no parallel region is launched from two threads)."""
    for i in range(fr.p.shape[0]):
        if fr.seen[i] and fr.active[i]:
            _solve_one(i, ix, cfg, fr, out)


@nb.njit(cache=True, nogil=True)
def agreement(ix, points, lam, seen, n_shapes):  # pragma: no cover - compiled
    """(M, S+1) evidence for each shape from the first-pass choices: every corner's weight is split
    over all shapes merged into its cloud point (they are indistinguishable at that bundle), so only a
    shape consistent with many bundles collects much; half from the bundle's natural neighbours, half
    from the whole frame, each relative to its best-supported shape."""
    alias_off, class_off, alias_shape, nb_off, nb_idx = ix.alias_off, ix.class_off, ix.alias_shape, ix.nb_off, ix.nb_idx
    m = points.shape[0]
    vote = np.zeros((m, n_shapes))
    glob = np.zeros(n_shapes)
    for j in range(m):
        if not seen[j]:
            continue
        for c in range(4):
            a = points[j, c]
            if a < 0 or lam[j, c] <= 0:
                continue
            first = class_off[alias_off[a]]
            last = class_off[alias_off[a + 1]]
            for o in range(first, last):
                vote[j, alias_shape[o]] += lam[j, c] / (last - first)
        for s in range(n_shapes):
            glob[s] += vote[j, s]
    gmax = max(glob.max(), 1e-300)
    out = np.zeros((m, n_shapes))
    local = np.zeros(n_shapes)
    for i in range(m):
        local[:] = 0.0
        for e in range(nb_off[i], nb_off[i + 1]):
            j = nb_idx[e]
            if seen[j]:
                for s in range(n_shapes):
                    local[s] += vote[j, s]
        lmax = max(local.max(), 1e-300)
        for s in range(n_shapes):
            # Relative to the best-supported shape, so that the leader scores 1.
            out[i, s] = 0.5 * (local[s] / lmax + glob[s] / gmax)
    return out


@nb.njit(cache=True, nogil=True)
def _local_fit_one(i, resid, seen, basis, nb_off, nb_idx, col_off, cols, w_global, beta, own_weight,
                   out):  # pragma: no cover - compiled
    """Bundle i's row of :func:`local_fits`."""
    a0, a1 = col_off[i], col_off[i + 1]
    n = a1 - a0
    for k in range(w_global.shape[0]):
        out[i, k] = w_global[k]
    if n == 0:
        return
    h = np.zeros((n, n))
    g = np.zeros(n)
    for a in range(n):
        h[a, a] = beta[i]
    n_rows = 0
    for e in range(nb_off[i] - 1, nb_off[i + 1]):
        # The bundle itself first (e = nb_off[i] - 1), then its natural neighbours.
        own = e < nb_off[i]
        j = np.int64(i) if own else nb_idx[e]
        if not seen[j]:
            continue
        n_rows += 1
        cw = own_weight if own else 1.0
        for a in range(n):
            ka = cols[a0 + a]
            acc = 0.0
            for d in range(3):
                acc += basis[ka, j, d] * resid[j, d]
            g[a] += cw * acc
            for b in range(a + 1):
                kb = cols[a0 + b]
                acc = 0.0
                for d in range(3):
                    acc += basis[ka, j, d] * basis[kb, j, d]
                h[a, b] += cw * acc
    if n_rows == 0:
        return
    for a in range(n):
        for b in range(a):
            h[b, a] = h[a, b]
    lo = np.empty(n)
    hi = np.empty(n)
    x = np.zeros(n)
    for a in range(n):
        wk = w_global[cols[a0 + a]]
        lo[a] = -wk
        hi[a] = 1.0 - wk
    box_qp(h, g, lo, hi, x, np.int64(0), 1e-13, 0.0)
    for a in range(n):
        out[i, cols[a0 + a]] = w_global[cols[a0 + a]] + x[a]


@nb.njit(parallel=True, cache=True, nogil=True)
def local_fits(resid, seen, basis, nb_off, nb_idx, col_off, cols, w_global, beta, own_weight,
               out):  # pragma: no cover - compiled
    """Each bundle's local shape weights: the global weights changed, on the bundle's candidate shapes,
    to fit the bundle and its seen natural neighbours.

    For bundle i with rows J = {i} (weight ``own_weight``) and its seen natural neighbours (weight 1),
    the change d on shapes ``cols[col_off[i]:col_off[i+1]]`` minimises
    ``sum_j c_j |resid_j - sum_k d_k basis[k, j]|^2 + beta[i] |d|^2`` with ``0 <= w_global + d <= 1``.

    Parameters
    ----------
    resid : (M, 3) float64, cm
        Bundles minus the global fit's model (unskinned space); rows of missing bundles unused.
    basis : (S, M, 3) float64, cm
        Every shape's displacement of every bundle.
    w_global : (S,) float64
    beta : (M,) float64, cm^2
        Ridge toward the global weights per bundle.
    out : (M, S) float64
        Filled with each bundle's weights.
    """
    for i in nb.prange(resid.shape[0]):
        _local_fit_one(i, resid, seen, basis, nb_off, nb_idx, col_off, cols, w_global, beta, own_weight, out)


@nb.njit(cache=True, nogil=True)
def local_fits_serial(resid, seen, basis, nb_off, nb_idx, col_off, cols, w_global, beta, own_weight,
                      out):  # pragma: no cover - compiled
    """:func:`local_fits` on the calling thread alone (see :func:`solve_bundles_serial`)."""
    for i in range(resid.shape[0]):
        _local_fit_one(i, resid, seen, basis, nb_off, nb_idx, col_off, cols, w_global, beta, own_weight, out)


@nb.njit(cache=True, nogil=True)
def weight_misfits(rest, basis, q, seen, nb_off, nb_idx, w, rows, own_weight, out):  # pragma: no cover - compiled
    """Each bundle's RMS misfit (cm) under its own weights: its seen natural neighbours (weight 1) and itself
    (``own_weight``) against where ``rest + w[i] @ basis`` puts them. ``rows`` (M,) bool: the bundles scored
    (NaN in ``out`` elsewhere). Each row's few nonzero weights are gathered first (tens of hundreds of shapes).

    Parameters
    ----------
    rest : (M, 3) float64, cm
    basis : (S, M, 3) float64, cm
    q : (M, 3) float64, cm
        The bundles (rows of missing ones unused).
    w : (M, S) float64
    out : (M,) float64
    """
    n_s = basis.shape[0]
    nz = np.empty(n_s, np.int64)
    for i in range(q.shape[0]):
        if not rows[i]:
            out[i] = np.nan
            continue
        n = 0
        for k in range(n_s):
            if w[i, k] != 0.0:
                nz[n] = k
                n += 1
        tot = 0.0
        cnt = 0.0
        for e in range(nb_off[i] - 1, nb_off[i + 1]):
            j = i if e < nb_off[i] else nb_idx[e]
            if not seen[j]:
                continue
            d2 = 0.0
            for c in range(3):
                acc = rest[j, c] - q[j, c]
                for t in range(n):
                    acc += w[i, nz[t]] * basis[nz[t], j, c]
                d2 += acc * acc
            cw = own_weight if e < nb_off[i] else 1.0
            tot += cw * d2
            cnt += cw
        out[i] = np.sqrt(tot / max(cnt, 1e-300))
