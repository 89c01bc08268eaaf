"""Compiled inner loops of the indexing solver (numba).

Arrays are the flattened index (see :mod:`lgi.index.build`): per-bundle blocks of points, simplices, hull
facets and grid cells addressed through offset arrays. Local coordinates are padded to 3 components and
simplices to 4 corners (-1 where unused); a bundle's dimension ``d`` says how many are real.
"""

from __future__ import annotations

import numba as nb
import numpy as np

# Status codes written to the diagnostics.
CONTAINED, PROJECTED, MISSING, BORROWED = 0, 1, 2, 3
# A candidate's own distance to the bundle counts as much as this many natural neighbours' misfits
# (measured on held-out ICT and synthetic frames, see docs/indexing.md).
OWN_WEIGHT = 4.0


@nb.njit(cache=True)
def build_grids(pts, pt_off, sx, sx_off, dim, target_per_cell, max_dim):  # pragma: no cover - compiled
    """Uniform grid per bundle over its local bounding box; every simplex is listed in the cells its
    bounding box overlaps. Returns lo (M,3), h (M,), dims (M,3), cell_off (M+1), cell_start, items."""
    m = dim.shape[0]
    lo = np.zeros((m, 3))
    h = np.ones(m)
    dims = np.ones((m, 3), np.int64)
    cell_off = np.zeros(m + 1, np.int64)
    for i in range(m):
        d = dim[i]
        a, b = pt_off[i], pt_off[i + 1]
        n_sx = sx_off[i + 1] - sx_off[i]
        ext = 0.0
        for k in range(d):
            lo[i, k] = pts[a:b, k].min()
            e = pts[a:b, k].max() - lo[i, k]
            ext = max(ext, e)
        if d == 0 or ext <= 0:
            cell_off[i + 1] = cell_off[i] + 1
            continue
        vol = 1.0
        for k in range(d):
            vol *= max(pts[a:b, k].max() - lo[i, k], ext * 1e-3)
        cells = max(1.0, n_sx / target_per_cell)
        hh = (vol / cells) ** (1.0 / d)
        h[i] = max(hh, ext / max_dim)
        n_c = 1
        for k in range(d):
            dims[i, k] = min(max_dim, int(np.floor((pts[a:b, k].max() - lo[i, k]) / h[i])) + 1)
            n_c *= dims[i, k]
        cell_off[i + 1] = cell_off[i] + n_c
    counts = np.zeros(cell_off[m] + 1, np.int64)
    for pass_ in range(2):
        if pass_ == 1:
            start = np.zeros(cell_off[m] + 1, np.int64)
            for c in range(cell_off[m]):
                start[c + 1] = start[c] + counts[c]
            items = np.zeros(start[cell_off[m]], np.int64)
            fill = start[:-1].copy()
        for i in range(m):
            d = dim[i]
            for s in range(sx_off[i], sx_off[i + 1]):
                c0 = np.zeros(3, np.int64)
                c1 = np.zeros(3, np.int64)
                for k in range(d):
                    mn = 1e300
                    mx = -1e300
                    for c in range(d + 1):
                        v = pts[sx[s, c], k]
                        mn = min(mn, v)
                        mx = max(mx, v)
                    c0[k] = min(dims[i, k] - 1, max(0, int(np.floor((mn - lo[i, k]) / h[i]))))
                    c1[k] = min(dims[i, k] - 1, max(0, int(np.floor((mx - lo[i, k]) / h[i]))))
                for x in range(c0[0], c1[0] + 1):
                    for y in range(c0[1], c1[1] + 1):
                        for z in range(c0[2], c1[2] + 1):
                            cell = cell_off[i] + (x * dims[i, 1] + y) * dims[i, 2] + z
                            if pass_ == 0:
                                counts[cell] += 1
                            else:
                                items[fill[cell]] = s
                                fill[cell] += 1
    return lo, h, dims, cell_off, start, items


@nb.njit(cache=True)
def _cell(y, i, lo, h, dims, cell_off, d):  # pragma: no cover - compiled
    idx = np.zeros(3, np.int64)
    for k in range(d):
        c = int(np.floor((y[k] - lo[i, k]) / h[i]))
        if c < 0 or c >= dims[i, k]:
            return -1
        idx[k] = c
    return cell_off[i] + (idx[0] * dims[i, 1] + idx[1]) * dims[i, 2] + idx[2]


@nb.njit(cache=True)
def _bary(y, s, sx, tinv, pts, d, lam):  # pragma: no cover - compiled
    p0 = sx[s, 0]
    tot = 0.0
    for r in range(d):
        acc = 0.0
        for k in range(d):
            acc += tinv[s, r, k] * (y[k] - pts[p0, k])
        lam[r + 1] = acc
        tot += acc
    lam[0] = 1.0 - tot
    for r in range(d + 1, 4):
        lam[r] = 0.0


@nb.njit(cache=True)
def _closest_on_segment(y, a, b, d, out):  # pragma: no cover - compiled
    num = 0.0
    den = 0.0
    for k in range(d):
        num += (y[k] - a[k]) * (b[k] - a[k])
        den += (b[k] - a[k]) ** 2
    t = 0.0 if den <= 0 else min(1.0, max(0.0, num / den))
    dist = 0.0
    for k in range(d):
        out[k] = a[k] + t * (b[k] - a[k])
        dist += (y[k] - out[k]) ** 2
    return dist


@nb.njit(cache=True)
def _closest_on_triangle(p, a, b, c, out):  # pragma: no cover - compiled
    """Closest point of triangle abc to p (3D), Ericson's region tests; returns squared distance."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = ab @ ap
    d2 = ac @ ap
    if d1 <= 0 and d2 <= 0:
        out[:] = a
    else:
        bp = p - b
        d3 = ab @ bp
        d4 = ac @ bp
        if d3 >= 0 and d4 <= d3:
            out[:] = b
        else:
            vc = d1 * d4 - d3 * d2
            if vc <= 0 and d1 >= 0 and d3 <= 0:
                out[:] = a + d1 / (d1 - d3) * ab
            else:
                cp = p - c
                d5 = ab @ cp
                d6 = ac @ cp
                if d6 >= 0 and d5 <= d6:
                    out[:] = c
                else:
                    vb = d5 * d2 - d1 * d6
                    if vb <= 0 and d2 >= 0 and d6 <= 0:
                        out[:] = a + d2 / (d2 - d6) * ac
                    else:
                        va = d3 * d6 - d5 * d4
                        if va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:
                            out[:] = b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b)
                        else:
                            den = 1.0 / (va + vb + vc)
                            out[:] = a + ab * (vb * den) + ac * (vc * den)
    diff = p - out
    return diff @ diff


@nb.njit(cache=True)
def _misfit(i, shapes, lam, nz, p, seen, ptab, nb_off, nb_idx, own2):  # pragma: no cover - compiled
    """RMS distance (cm) of the natural neighbours, and of the bundle itself (``own2``, squared, weighted
    OWN_WEIGHT), to where the candidate's blend of shapes puts them."""
    tot = OWN_WEIGHT * own2
    cnt = OWN_WEIGHT
    for e in range(nb_off[i], nb_off[i + 1]):
        j = nb_idx[e]
        if not seen[j]:
            continue
        for k in range(3):
            acc = -p[j, k]
            for c in range(nz):
                acc += lam[c] * ptab[shapes[c], j, k]
            tot += acc * acc
        cnt += 1
    return np.sqrt(tot / cnt)


@nb.njit(cache=True)
def _penalty(i, shapes, lam, nz, prev, mu, agree, nu):  # pragma: no cover - compiled
    """Temporal (shapes not shared with the previous frame) and agreement (shapes the frame's evidence
    does not support) terms of the score, cm."""
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
def _consider(i, shapes_in, lam_in, nz, p, seen, ptab, nb_off, nb_idx, own2, alias_pt, alias_off, class_off,
              alias_shape, alias_min_w, prev, mu, agree, nu, best_shapes, best_lam, best_pts, best,
              last):  # pragma: no cover
    """Score one candidate and keep it if it is the best so far; returns True if it is.

    Every corner with weight >= alias_min_w (heaviest first) tries the shapes merged into its cloud
    point, one alias class at a time (a class: shapes that also coincide at all natural neighbours, so
    they share one misfit); within a class the temporal and agreement terms pick the member.
    """
    shapes = shapes_in.copy()
    lam = lam_in.copy()
    done = np.zeros(4, np.bool_)
    for _ in range(nz):
        c = -1
        for q in range(nz):
            if not done[q] and (c < 0 or lam[q] > lam[c]):
                c = q
        done[c] = True
        pt = alias_pt[c]
        if pt < 0 or lam[c] < alias_min_w or alias_off[pt + 1] - alias_off[pt] <= 1 and \
                class_off[alias_off[pt] + 1] - class_off[alias_off[pt]] <= 1:
            continue
        keep = shapes[c]
        keep_sc = 1e300
        for cls in range(alias_off[pt], alias_off[pt + 1]):
            shapes[c] = alias_shape[class_off[cls]]
            fit = _misfit(i, shapes, lam, nz, p, seen, ptab, nb_off, nb_idx, own2)
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
            pen = _penalty(i, shapes, lam, nz, prev, mu, agree, nu)
            if fit + pen < keep_sc:
                keep_sc = fit + pen
                keep = member
        shapes[c] = keep
    sc = _misfit(i, shapes, lam, nz, p, seen, ptab, nb_off, nb_idx, own2) + _penalty(i, shapes, lam, nz, prev, mu,
                                                                                      agree, nu)
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


@nb.njit(cache=True)
def _solve_one(i, p, seen, dim, origin, basis, pts, pt_off, pt_shape, alias_off, class_off, alias_shape, sx, tinv,
               hull, hull_off, lo, h, dims, cell_off, cell_start, items, ptab, nb_off, nb_idx, snap_r, prev, mu,
               agree, nu, first_shapes, first_lam, alias_min_w, tol, dist_tol, n_project, top_k, cand_in,
               cand_score_in, first_score, out_shapes, out_lam, out_pts, n_contain, status, proj, score, cand_out,
               cand_score_out):  # pragma: no cover
    d = dim[i]
    y = np.zeros(3)
    q = np.zeros(3)
    tmp = np.zeros(3)
    lam = np.zeros(4)
    shapes = np.zeros(4, np.int64)
    apt = np.full(4, -1, np.int64)
    best = np.full(1, 1e300)
    bshapes = np.zeros(4, np.int64)
    blam = np.zeros(4)
    bpts = np.full(4, -1, np.int64)
    last = np.zeros(1)
    off2 = 0.0
    for k in range(d):
        acc = 0.0
        for r in range(3):
            acc += basis[i, r, k] * (p[i, r] - origin[i, r])
        y[k] = acc
    for r in range(3):
        acc = p[i, r] - origin[i, r]
        for k in range(d):
            acc -= basis[i, r, k] * y[k]
        off2 += acc * acc

    found = 0
    if d == 0:
        shapes[0] = pt_shape[pt_off[i]]
        apt[0] = pt_off[i]
        lam[0] = 1.0
        # np.int64(1), not 1: a literal argument is a type of its own, compiled again (first run after an install).
        _consider(i, shapes, lam, np.int64(1), p, seen, ptab, nb_off, nb_idx, off2, apt, alias_off, class_off,
                  alias_shape, alias_min_w, prev, mu, agree, nu, bshapes, blam, bpts, best, last)
        found = 1
    else:
        if cand_in[i, 0] >= -1:
            # Second pass: the first pass's distinct best containing simplices, no grid scan. The
            # agreement term adds at most nu and the sweep only raises a first-pass score, so a
            # candidate more than nu behind the first-pass winner cannot win: skip it.
            for r in range(top_k):
                s = cand_in[i, r]
                if s < 0:
                    break
                found += 1
                if cand_score_in[i, r] > first_score[i] + nu + 1e-15:
                    continue
                _bary(y, s, sx, tinv, pts, d, lam)
                _take_simplex(s, lam, sx, pt_shape, d, shapes, apt)
                _consider(i, shapes, lam, d + 1, p, seen, ptab, nb_off, nb_idx, off2, apt, alias_off, class_off,
                          alias_shape, alias_min_w, prev, mu, agree, nu, bshapes, blam, bpts, best, last)
        else:
            cell = _cell(y, i, lo, h, dims, cell_off, d)
            if cell >= 0:
                n_items = cell_start[cell + 1] - cell_start[cell]
                cand = np.empty(n_items, np.int64)
                pre = np.empty(n_items)
                for e in range(cell_start[cell], cell_start[cell + 1]):
                    s = items[e]
                    _bary(y, s, sx, tinv, pts, d, lam)
                    inside = True
                    for c in range(d + 1):
                        if lam[c] < -tol:
                            inside = False
                    if not inside:
                        continue
                    _take_simplex(s, lam, sx, pt_shape, d, shapes, apt)
                    cand[found] = s
                    # Pre-screen with the points' representative shapes; only the best go on to the
                    # full score (alias sweep, temporal and agreement terms).
                    pre[found] = _misfit(i, shapes, lam, d + 1, p, seen, ptab, nb_off, nb_idx, off2)
                    found += 1
                order = np.argsort(pre[:found])
                kept_lam = np.zeros((top_k, 4))
                kept_shapes = np.zeros((top_k, 4), np.int64)
                n_kept = 0
                for r in range(found):
                    if n_kept >= top_k:
                        break
                    s = cand[order[r]]
                    _bary(y, s, sx, tinv, pts, d, lam)
                    _take_simplex(s, lam, sx, pt_shape, d, shapes, apt)
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
                    _consider(i, shapes, lam, d + 1, p, seen, ptab, nb_off, nb_idx, off2, apt, alias_off,
                              class_off, alias_shape, alias_min_w, prev, mu, agree, nu, bshapes, blam, bpts, best, last)
                    cand_out[i, n_kept] = s
                    cand_score_out[i, n_kept] = last[0]
                    n_kept += 1

    # Points within the snap radius: their dropped and merged shapes lie there, so try each point
    # alone (with its aliases), the bundle's own distance counted in the score.
    snapped = -1.0
    for a in range(pt_off[i], pt_off[i + 1]):
        dd = off2
        for k in range(d):
            dd += (y[k] - pts[a, k]) ** 2
        if dd <= snap_r[i] * snap_r[i]:
            shapes[0] = pt_shape[a]
            apt[0] = a
            lam[0] = 1.0
            if _consider(i, shapes, lam, np.int64(1), p, seen, ptab, nb_off, nb_idx, dd, apt, alias_off, class_off,
                         alias_shape, alias_min_w, prev, mu, agree, nu, bshapes, blam, bpts, best, last):
                snapped = dd
    n_contain[i] = found
    if snapped >= 0:
        # On a dataset point (a pruned shape's position): inside the data, not a projection.
        status[i] = CONTAINED
        proj[i] = np.sqrt(snapped)
    elif found > 0:
        status[i] = CONTAINED if off2 <= dist_tol * dist_tol else PROJECTED
        proj[i] = np.sqrt(off2)
    else:
        # Project onto the hull: the n_project nearest facets, then the simplices containing each
        # projected point; scored with the bundle's own distance included.
        nh = hull_off[i + 1] - hull_off[i]
        dists = np.empty(nh)
        for f in range(nh):
            hf = hull_off[i] + f
            if d == 3:
                dists[f] = _closest_on_triangle(y, pts[hull[hf, 0]], pts[hull[hf, 1]], pts[hull[hf, 2]], tmp)
            elif d == 2:
                dists[f] = _closest_on_segment(y, pts[hull[hf, 0]], pts[hull[hf, 1]], d, tmp)
            else:
                dists[f] = (y[0] - pts[hull[hf, 0], 0]) ** 2
        order = np.argsort(dists)
        best_proj = 1e300
        for rank in range(min(n_project, nh)):
            hf = hull_off[i] + order[rank]
            if d == 3:
                d2 = _closest_on_triangle(y, pts[hull[hf, 0]], pts[hull[hf, 1]], pts[hull[hf, 2]], q)
            elif d == 2:
                d2 = _closest_on_segment(y, pts[hull[hf, 0]], pts[hull[hf, 1]], d, q)
            else:
                q[0] = pts[hull[hf, 0], 0]
                d2 = (y[0] - q[0]) ** 2
            cell = _cell(q, i, lo, h, dims, cell_off, d)
            if cell < 0:
                continue
            tried = 0
            for e in range(cell_start[cell], cell_start[cell + 1]):
                if tried >= top_k:
                    break
                s = items[e]
                _bary(q, s, sx, tinv, pts, d, lam)
                inside = True
                for c in range(d + 1):
                    if lam[c] < -1e-6:
                        inside = False
                if not inside:
                    continue
                tried += 1
                _take_simplex(s, lam, sx, pt_shape, d, shapes, apt)
                if _consider(i, shapes, lam, d + 1, p, seen, ptab, nb_off, nb_idx, off2 + d2 + 1e-300, apt,
                             alias_off, class_off, alias_shape, alias_min_w, prev, mu, agree, nu, bshapes, blam, bpts,
                             best, last):
                    best_proj = d2
        if best[0] >= 1e299:
            # Numerically no simplex contains the hull point: fall back to the nearest point.
            bestp = pt_off[i]
            bd = 1e300
            for a in range(pt_off[i], pt_off[i + 1]):
                dd = 0.0
                for k in range(d):
                    dd += (y[k] - pts[a, k]) ** 2
                if dd < bd:
                    bd = dd
                    bestp = a
            shapes[0] = pt_shape[bestp]
            apt[0] = bestp
            lam[0] = 1.0
            _consider(i, shapes, lam, np.int64(1), p, seen, ptab, nb_off, nb_idx, off2 + bd + 1e-300, apt, alias_off,
                      class_off, alias_shape, alias_min_w, prev, mu, agree, nu, bshapes, blam, bpts, best, last)
            best_proj = bd
        status[i] = PROJECTED
        proj[i] = np.sqrt(off2 + best_proj)

    # Second pass: a natural neighbour's first-pass mixture, scored with this bundle's own distance.
    # A bundle that barely moves, or sits where its cloud has no combination of the shapes its
    # neighbours show, cannot tell those shapes apart; its neighbours can.
    if nu > 0:
        for e in range(nb_off[i], nb_off[i + 1]):
            j = nb_idx[e]
            if not seen[j]:
                continue
            dd = 0.0
            for k in range(3):
                acc = -p[i, k]
                for c in range(4):
                    acc += first_lam[j, c] * ptab[first_shapes[j, c], i, k]
                dd += acc * acc
            nzj = 0
            for c in range(4):
                if first_lam[j, c] > 0:
                    shapes[nzj] = first_shapes[j, c]
                    lam[nzj] = first_lam[j, c]
                    apt[nzj] = -1
                    nzj += 1
            if _consider(i, shapes, lam, nzj, p, seen, ptab, nb_off, nb_idx, dd, apt, alias_off, class_off,
                         alias_shape, alias_min_w, prev, mu, agree, nu, bshapes, blam, bpts, best, last):
                status[i] = BORROWED
                proj[i] = np.sqrt(dd)
    score[i] = best[0]
    for c in range(4):
        out_shapes[i, c] = bshapes[c]
        out_lam[i, c] = blam[c]
        out_pts[i, c] = bpts[c]


@nb.njit(cache=True, nogil=True)
def _solve_outputs(m, top_k):  # pragma: no cover - compiled
    """:func:`solve_bundles`' outputs for m bundles, at their fill values (no shapes, status MISSING)."""
    return (np.zeros((m, 4), np.int64), np.zeros((m, 4)), np.full((m, 4), -1, np.int64), np.zeros(m, np.int64),
            np.full(m, MISSING, np.int64), np.zeros(m), np.full(m, np.nan), np.full((m, top_k), -1, np.int64),
            np.full((m, top_k), np.inf))


@nb.njit(parallel=True, cache=True, nogil=True)
def solve_bundles(p, seen, dim, origin, basis, pts, pt_off, pt_shape, alias_off, class_off, alias_shape, sx, tinv,
                  hull, hull_off, lo, h, dims, cell_off, cell_start, items, ptab, nb_off, nb_idx, snap_r, prev, mu,
                  agree, nu, first_shapes, first_lam, alias_min_w, tol, dist_tol, n_project, top_k,
                  cand_in, cand_score_in, first_score, active):  # pragma: no cover - compiled
    """Choose every bundle's simplex and barycentric weights for one frame (bundles in parallel).

    Only the seen bundles with ``active`` (M,) bool are searched; the others keep the outputs' fill values
    (status MISSING, no shapes).

    ``cand_in`` (M, top_k): a first pass's candidates to reuse (rows of -2 mean scan the grid), with
    their first-pass scores ``cand_score_in`` and each bundle's first-pass best ``first_score``.

    Returns shapes (M,4) int64 (extended shape indices), lam (M,4), points (M,4) (cloud points of the
    corners, -1 unused), n_contain (M,), status (M,), proj_dist (M,) cm, score (M,) cm, and the
    distinct best containing simplices (M, top_k) (-1 padded) with their scores, for a second pass.
    """
    m = p.shape[0]
    out_shapes, out_lam, out_pts, n_contain, status, proj, score, cand_out, cand_score_out = _solve_outputs(m, top_k)
    for i in nb.prange(m):  # solve_bundles_serial: the same loop on one thread
        if seen[i] and active[i]:
            _solve_one(i, p, seen, dim, origin, basis, pts, pt_off, pt_shape, alias_off, class_off, alias_shape, sx,
                       tinv, hull, hull_off, lo, h, dims, cell_off, cell_start, items, ptab, nb_off, nb_idx, snap_r,
                       prev, mu, agree, nu, first_shapes, first_lam, alias_min_w, tol, dist_tol, n_project, top_k,
                       cand_in, cand_score_in, first_score, out_shapes, out_lam, out_pts, n_contain, status, proj,
                       score, cand_out, cand_score_out)
    return out_shapes, out_lam, out_pts, n_contain, status, proj, score, cand_out, cand_score_out


@nb.njit(cache=True, nogil=True)
def solve_bundles_serial(p, seen, dim, origin, basis, pts, pt_off, pt_shape, alias_off, class_off, alias_shape, sx,
                         tinv, hull, hull_off, lo, h, dims, cell_off, cell_start, items, ptab, nb_off, nb_idx, snap_r,
                         prev, mu, agree, nu, first_shapes, first_lam, alias_min_w, tol, dist_tol, n_project, top_k,
                         cand_in, cand_score_in, first_score, active):  # pragma: no cover - compiled
    """:func:`solve_bundles` on the calling thread alone (a shot's frames chosen on one thread while another
    blends: no parallel region is launched from two threads)."""
    m = p.shape[0]
    out_shapes, out_lam, out_pts, n_contain, status, proj, score, cand_out, cand_score_out = _solve_outputs(m, top_k)
    for i in range(m):
        if seen[i] and active[i]:
            _solve_one(i, p, seen, dim, origin, basis, pts, pt_off, pt_shape, alias_off, class_off, alias_shape, sx,
                       tinv, hull, hull_off, lo, h, dims, cell_off, cell_start, items, ptab, nb_off, nb_idx, snap_r,
                       prev, mu, agree, nu, first_shapes, first_lam, alias_min_w, tol, dist_tol, n_project, top_k,
                       cand_in, cand_score_in, first_score, out_shapes, out_lam, out_pts, n_contain, status, proj,
                       score, cand_out, cand_score_out)
    return out_shapes, out_lam, out_pts, n_contain, status, proj, score, cand_out, cand_score_out


@nb.njit(parallel=True, cache=True, nogil=True)
def blend(x0, deltas, w_indptr, w_indices, w_data, shapes, lam, out):  # pragma: no cover - compiled
    """out[v] = x0[v] + sum_i w[v, i] sum_c lam[i, c] deltas[shapes[i, c], v] (deltas shape-major; any
    number of slots c per bundle)."""
    n_v = x0.shape[0]
    for v in nb.prange(n_v):
        a0 = x0[v, 0]
        a1 = x0[v, 1]
        a2 = x0[v, 2]
        for e in range(w_indptr[v], w_indptr[v + 1]):
            i = w_indices[e]
            w = w_data[e]
            for c in range(shapes.shape[1]):
                lc = lam[i, c]
                if lc != 0.0:
                    k = shapes[i, c]
                    f = w * lc
                    a0 += f * deltas[k, v, 0]
                    a1 += f * deltas[k, v, 1]
                    a2 += f * deltas[k, v, 2]
        out[v, 0] = a0
        out[v, 1] = a1
        out[v, 2] = a2


@nb.njit(cache=True, nogil=True)
def blend_on_base(x0, deltas, base_shapes, base_lam, w_sum, c_ptr, c_vert, c_w, ramp, share, rows, d_shapes, d_lam,
                  out):  # pragma: no cover - compiled
    """:func:`blend` of bundles whose weights mostly repeat one base blend (the frame's global fit), with the far
    field: ``out[v] = x0[v] + w_sum[v] B[v] + sum_b N[v, b] (1 - ramp[v] share[b]) D_b[v]``, where
    ``B = sum_c base_lam[c] deltas[base_shapes[c]]`` and ``D_b`` the blend of bundle b's differences from the
    base (``d_shapes``, ``d_lam`` (M, K'), zeros after each row's last; only the bundles in ``rows`` have any).
    The far field's share of the global fit is already in the base term: a vertex's weights sum to w_sum.

    Both terms stream over shape rows, one row at a time (the base over every vertex, a difference over the
    vertices its bundle reaches, from the weights by bundle: CSC ``c_ptr`` (M+1,), ``c_vert``, ``c_w``): reading
    memory in order, as :func:`blend_uniform` does. Flat arrays: ``x0``, ``out`` (3V,), ``deltas`` (S, 3V)."""
    blend_uniform(x0, deltas, w_sum, base_shapes, base_lam, out)
    for b in rows:
        sb = share[b]
        for c in range(d_shapes.shape[1]):
            lc = d_lam[b, c]
            if lc == 0.0:
                break
            row = deltas[d_shapes[b, c]]
            for e in range(c_ptr[b], c_ptr[b + 1]):
                v = c_vert[e]
                f = c_w[e] * (1.0 - ramp[v] * sb) * lc
                for d in range(3):
                    out[3 * v + d] += f * row[3 * v + d]


@nb.njit(cache=True, nogil=True)
def blend_uniform(x0, deltas, w_sum, shapes, lam, out):  # pragma: no cover - compiled
    """:func:`blend` when every bundle has the same shapes (K,) and weights (K,): out[v] = x0[v] + w_sum[v]
    sum_c lam[c] deltas[shapes[c], v], with w_sum[v] the vertex's total blend weight (1 inside the bundles'
    region, 0 where no bundle reaches). Flat arrays: ``x0``, ``out`` (3V,), ``deltas`` (S, 3V), ``w_sum`` (V,).

    One streaming pass over each used shape's row, accumulated in ``out``: the loop vectorises and reads
    memory in order (1.1 ms for 22 of ICT's rows here). Gathering the K rows per vertex instead (the
    per-vertex loop of :func:`blend`) ran 4-10x slower, and so did splitting the rows into chunks over
    threads (numba ``prange``) on this 2-core machine.
    """
    n = out.shape[0]
    for j in range(n):
        out[j] = 0.0
    for c in range(shapes.shape[0]):
        lc = lam[c]
        if lc != 0.0:
            row = deltas[shapes[c]]
            for j in range(n):
                out[j] += lc * row[j]
    for v in range(n // 3):
        ws = w_sum[v]
        for d in range(3):
            out[3 * v + d] = x0[3 * v + d] + ws * out[3 * v + d]


@nb.njit(cache=True, nogil=True)
def skin_points(x, w, t, out):  # pragma: no cover - compiled
    """Linear blend skinning with one moving bone: ``out[n] = x[n] + w[n] (R x[n] + t - x[n])`` for the
    (3, 4) map ``t`` = [R|t]; ``x``, ``out`` (N, 3) float64 (may be the same array), ``w`` (N,) float64.
    One pass without the (N, 3) temporaries of the numpy expression (2.4 -> 0.2 ms on ICT's mesh)."""
    for i in range(x.shape[0]):
        b = w[i]
        p0 = x[i, 0]
        p1 = x[i, 1]
        p2 = x[i, 2]
        q0 = t[0, 0] * p0 + t[0, 1] * p1 + t[0, 2] * p2 + t[0, 3]
        q1 = t[1, 0] * p0 + t[1, 1] * p1 + t[1, 2] * p2 + t[1, 3]
        q2 = t[2, 0] * p0 + t[2, 1] * p1 + t[2, 2] * p2 + t[2, 3]
        out[i, 0] = p0 + b * (q0 - p0)
        out[i, 1] = p1 + b * (q1 - p1)
        out[i, 2] = p2 + b * (q2 - p2)


@nb.njit(cache=True, nogil=True)
def agreement(points, lam, seen, alias_off, class_off, alias_shape, nb_off, nb_idx, n_shapes):  # pragma: no cover
    """(M, S+1) evidence for each shape from the first-pass choices: every corner's weight is split
    over all shapes merged into its cloud point (they are indistinguishable at that bundle), so only a
    shape consistent with many bundles collects much; half from the bundle's natural neighbours, half
    from the whole frame, each relative to its best-supported shape."""
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
def _correction_part(part, half, c_indptr, c_indices, c_data, fix, resid, buf):  # pragma: no cover - compiled
    """Half ``part`` (0 or 1) of :func:`add_correction`'s rows summed into ``buf[part]``."""
    for f in range(part * half, min(fix.shape[0], (part + 1) * half)):
        b = fix[f]
        r0 = resid[f, 0]
        r1 = resid[f, 1]
        r2 = resid[f, 2]
        for e in range(c_indptr[b], c_indptr[b + 1]):
            v = c_indices[e]
            w = c_data[e]
            buf[part, v, 0] += w * r0
            buf[part, v, 1] += w * r1
            buf[part, v, 2] += w * r2


@nb.njit(parallel=True, cache=True, nogil=True)
def add_correction(x, c_indptr, c_indices, c_data, fix, resid):  # pragma: no cover - compiled
    """x[v] += sum_f resid[f] * corr[fix[f], v], the correction basis stored as sparse rows (one per
    bundle): the smooth field carrying the residuals of the bundles in ``fix``. Two threads each sum
    half of the rows into a buffer of their own (no write races), then the buffers are added. A plain
    loop, not BLAS: BLAS threads left spinning after a call would compete with the solver's threads."""
    n_v = x.shape[0]
    buf = np.zeros((2, n_v, 3))
    half = (fix.shape[0] + 1) // 2
    for part in nb.prange(2):
        _correction_part(part, half, c_indptr, c_indices, c_data, fix, resid, buf)
    for v in nb.prange(n_v):
        for k in range(3):
            x[v, k] += buf[0, v, k] + buf[1, v, k]


@nb.njit(cache=True, nogil=True)
def add_correction_serial(x, c_indptr, c_indices, c_data, fix, resid):  # pragma: no cover - compiled
    """:func:`add_correction` on the calling thread alone, summed in the same two halves (the same bits)."""
    n_v = x.shape[0]
    buf = np.zeros((2, n_v, 3))
    half = (fix.shape[0] + 1) // 2
    for part in range(2):
        _correction_part(part, half, c_indptr, c_indices, c_data, fix, resid, buf)
    for v in range(n_v):
        for k in range(3):
            x[v, k] += buf[0, v, k] + buf[1, v, k]


@nb.njit(cache=True)
def _chol_add(h, fl, nf, a, lf):  # pragma: no cover - compiled
    """Append variable ``a`` to the Cholesky factor ``lf`` of h[fl[:nf], fl[:nf]] (O(nf^2)); returns False
    (nothing changed) if the extended block is not numerically positive definite."""
    d = h[a, a]
    for c in range(nf):
        s = h[a, fl[c]]
        for k in range(c):
            s -= lf[nf, k] * lf[c, k]
        lf[nf, c] = s / lf[c, c]
        d -= lf[nf, c] * lf[nf, c]
    if d <= 1e-14 * h[a, a]:
        return False
    lf[nf, nf] = np.sqrt(d)
    fl[nf] = a
    return True


@nb.njit(cache=True)
def _chol_remove(fl, nf, p, lf):  # pragma: no cover - compiled
    """Remove the variable at position ``p`` of ``fl`` from the Cholesky factor ``lf`` (O(nf^2)): its row is
    dropped and the columns it leaves out of shape are rotated back to lower-triangular (Givens)."""
    for i in range(p, nf - 1):
        fl[i] = fl[i + 1]
        for k in range(i + 2):
            lf[i, k] = lf[i + 1, k]
    for c in range(p, nf - 1):
        x0 = lf[c, c]
        y0 = lf[c, c + 1]
        r = np.sqrt(x0 * x0 + y0 * y0)
        cs = x0 / r
        sn = y0 / r
        for i in range(c, nf - 1):
            u = lf[i, c]
            v = lf[i, c + 1]
            lf[i, c] = cs * u + sn * v
            lf[i, c + 1] = -sn * u + cs * v
    for i in range(nf - 1):
        lf[i, nf - 1] = 0.0


@nb.njit(cache=True)
def box_qp(h, g, lo, hi, x, max_iter=0, tol=1e-13, gain=0.0):  # pragma: no cover - compiled
    """Minimise 0.5 x'hx - g'x subject to lo <= x <= hi (h SPD, small), in place from a feasible x.

    Primal active-set method: Newton steps on the free variables, cut at the first bound they reach (which
    joins the active set); at a subspace minimum the bound variable whose multiplier most wants it free is
    released, if releasing it alone would lower the objective by more than ``gain`` (``m^2 / (2 h_aa)`` for
    multiplier ``m``). The Cholesky factor of the free block is updated as variables join and leave
    (O(n^2) per step, not a factorisation). Warm starts from a nearby solution take a few steps.

    Rounding can make a just-released variable's Newton step point back into its bound (redundant columns
    with a ridge of 1e-6 against norms of 1: h's condition is ~1e8 and the multiplier at the rounding
    level); the variable is then returned to its bound and not released again, and a variable whose column
    the free block cannot take (not positive definite) stays at its bound, so the method cannot cycle.
    Returns the iterations, or -1 if the starting free block is not positive definite.
    """
    n = x.shape[0]
    if max_iter <= 0:
        max_iter = 10 * n + 10
    state = np.zeros(n, np.int64)  # 0 free, -1 at the lower bound, +1 at the upper
    for a in range(n):
        if x[a] <= lo[a]:
            x[a] = lo[a]
            state[a] = -1
        elif x[a] >= hi[a]:
            x[a] = hi[a]
            state[a] = 1
    banned = np.zeros(n, np.bool_)
    grad = np.empty(n)
    fl = np.empty(n, np.int64)
    step = np.empty(n)
    lf = np.zeros((n, n))
    nf = 0
    for a in range(n):
        if state[a] == 0:
            if not _chol_add(h, fl, nf, a, lf):
                return -1
            nf += 1
    scale = 0.0
    for a in range(n):
        scale = max(scale, abs(g[a]), abs(h[a, a]))
    tol = max(tol, 1e-12 * scale)
    released = -1
    at_min = False  # after a full Newton step: at the free variables' minimum, up to rounding
    for it in range(max_iter):
        for a in range(n):
            acc = -g[a]
            for b in range(n):
                acc += h[a, b] * x[b]
            grad[a] = acc
        big = 0.0
        if nf > 0 and not at_min:
            for c in range(nf):
                s = -grad[fl[c]]
                for k in range(c):
                    s -= lf[c, k] * step[k]
                step[c] = s / lf[c, c]
            for c in range(nf - 1, -1, -1):
                s = step[c]
                for k in range(c + 1, nf):
                    s -= lf[k, c] * step[k]
                step[c] = s / lf[c, c]
                big = max(big, abs(step[c]))
        if at_min or big <= 1e-14 * (1.0 + scale):
            # (Repeating the Newton step there would only chase rounding: with h's condition ~1e8 its
            # size stays ~1e-11, never below a fixed threshold.)
            at_min = False
            # At the minimum over the free variables: release the most wrongly held bound, if any.
            worst = -1
            worst_v = tol
            for a in range(n):
                if banned[a]:
                    continue
                m = -grad[a] if state[a] == -1 else grad[a] if state[a] == 1 else 0.0
                if m > worst_v and m * m > gain * 2.0 * h[a, a]:
                    worst, worst_v = a, m
            if worst < 0:
                return it
            if not _chol_add(h, fl, nf, worst, lf):
                banned[worst] = True
                at_min = True
                continue
            nf += 1
            state[worst] = 0
            released = worst
            continue
        alpha = 1.0
        block = -1
        for c in range(nf):
            a = fl[c]
            if step[c] < 0.0:
                t = (lo[a] - x[a]) / step[c]
            elif step[c] > 0.0:
                t = (hi[a] - x[a]) / step[c]
            else:
                continue
            if t < alpha:
                alpha = t
                block = c
        if block >= 0 and fl[block] == released and alpha <= 1e-12:
            # The released variable would go straight back to its bound: rounding, not a descent direction.
            state[released] = -1 if step[block] < 0.0 else 1
            banned[released] = True
            _chol_remove(fl, nf, block, lf)
            nf -= 1
            released = -1
            at_min = True
            continue
        released = -1
        for c in range(nf):
            x[fl[c]] += alpha * step[c]
        at_min = block < 0
        if block >= 0:
            a = fl[block]
            if step[block] < 0.0:
                x[a] = lo[a]
                state[a] = -1
            else:
                x[a] = hi[a]
                state[a] = 1
            _chol_remove(fl, nf, block, lf)
            nf -= 1
    return max_iter


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


# The global fit's linearisation (lgi.solve.globalfit.GlobalFit). Bundle i = seen_idx[e] is modelled as
# (1 - b_i) x_i + b_i (R x_i + t), x_i = rest_i + sum_k w_k basis_ki; the derivative in w_k is
# J_k,e = (1 - b_i) d + b_i R d (d = basis_ki). Loops rather than numpy expressions: those allocate
# (S, m, 3) temporaries, which cost more than the arithmetic (10 ms per call at 500 shapes here), and the
# full Jacobian is never stored: the fit needs its product with a vector and a few of its rows.
@nb.njit(cache=True, inline="always")
def _unskinned(rest, basis, nz, w, i, x):  # pragma: no cover - compiled
    """x (3,) = rest[i] + sum_k w[k] basis[k, i] over the nonzero weights ``nz``: bundle i before skinning."""
    for c in range(3):
        x[c] = rest[i, c]
    for k in nz:
        for c in range(3):
            x[c] += w[k] * basis[k, i, c]


@nb.njit(cache=True)
def global_residual(rest, basis, seen_idx, w, rot, trans, bw, p, r_out):  # pragma: no cover - compiled
    """Model minus ``p`` at the seen bundles, ``r_out[3e + c]``."""
    nz = np.flatnonzero(w)
    x = np.empty(3)
    for e in range(seen_idx.shape[0]):
        i = seen_idx[e]
        _unskinned(rest, basis, nz, w, i, x)
        b = bw[i]
        for c in range(3):
            r_out[3 * e + c] = ((1.0 - b) * x[c] + b * (rot[c, 0] * x[0] + rot[c, 1] * x[1] + rot[c, 2] * x[2]
                                                        + trans[c]) - p[i, c])


@nb.njit(cache=True)
def global_gradient(basis, seen_idx, rot, bw, v, out):  # pragma: no cover - compiled
    """``out[k] = J_k . v`` for every shape k: ``sum_e d . ((1 - b) v_e + b R^T v_e)``. One dense product with
    the (S, 3M) basis (BLAS; missing bundles get 0): the gather over the seen bundles did not vectorise and
    took 5x as long."""
    n_m = basis.shape[1]
    u = np.zeros(3 * n_m)
    for e in range(seen_idx.shape[0]):
        i = seen_idx[e]
        b = bw[i]
        for c in range(3):
            u[3 * i + c] = (1.0 - b) * v[3 * e + c] + b * (rot[0, c] * v[3 * e] + rot[1, c] * v[3 * e + 1]
                                                          + rot[2, c] * v[3 * e + 2])
    out[:] = np.dot(basis.reshape(basis.shape[0], 3 * n_m), u)


@nb.njit(cache=True, inline="always")
def _shape_derivative(basis, k, i, b, rot, out):  # pragma: no cover - compiled
    """out (3,) = (1 - b) d + b R d for d = basis[k, i]: bundle i's derivative in shape k's weight."""
    d0 = basis[k, i, 0]
    d1 = basis[k, i, 1]
    d2 = basis[k, i, 2]
    for c in range(3):
        out[c] = (1.0 - b) * basis[k, i, c] + b * (rot[c, 0] * d0 + rot[c, 1] * d1 + rot[c, 2] * d2)


def shape_products(basis):
    """(S, M, 6) products of each shape's displacement at each bundle, (d0^2, d1^2, d2^2, 2 d0 d1, 2 d0 d2,
    2 d1 d2), for :func:`global_col2`."""
    d = basis
    return np.ascontiguousarray(np.stack([d[..., 0] ** 2, d[..., 1] ** 2, d[..., 2] ** 2, 2 * d[..., 0] * d[..., 1],
                                          2 * d[..., 0] * d[..., 2], 2 * d[..., 1] * d[..., 2]], axis=-1))


@nb.njit(cache=True)
def global_col2(prod, seen_idx, rot, bw, out):  # pragma: no cover - compiled
    """``out[k] = |J_k|^2`` for every shape k, from ``prod`` = :func:`shape_products` (S, M, 6).

    ``|(1 - b) d + b R d|^2 = d' Q d`` with ``Q = ((1 - b)^2 + b^2) I + b (1 - b) (R + R')`` (R is a rotation):
    one dense product with the (S, 6M) products instead of a rotation per shape and bundle (0.5 -> 0.05 ms at
    500 shapes)."""
    n_m = prod.shape[1]
    coef = np.zeros(6 * n_m)
    for e in range(seen_idx.shape[0]):
        i = seen_idx[e]
        b = bw[i]
        a0 = (1.0 - b) ** 2 + b * b
        a1 = b * (1.0 - b)
        coef[6 * i + 0] = a0 + 2.0 * a1 * rot[0, 0]
        coef[6 * i + 1] = a0 + 2.0 * a1 * rot[1, 1]
        coef[6 * i + 2] = a0 + 2.0 * a1 * rot[2, 2]
        coef[6 * i + 3] = a1 * (rot[0, 1] + rot[1, 0])
        coef[6 * i + 4] = a1 * (rot[0, 2] + rot[2, 0])
        coef[6 * i + 5] = a1 * (rot[1, 2] + rot[2, 1])
    out[:] = np.dot(prod.reshape(prod.shape[0], 6 * n_m), coef)


@nb.njit(cache=True)
def sg_runs(x, left, mid, right, out):  # pragma: no cover - compiled
    """Savitzky-Golay smoothing of every marker's trajectory, each run of seen frames on its own.

    ``x`` (F, M, 3) with NaN rows for missing frames; ``mid`` (w,) the central coefficients, ``left`` and
    ``right`` (h, w) the fitted values at the first and last h = w // 2 frames of a run from its first and
    last w frames (scipy's ``mode="interp"``). Runs shorter than w are copied; ``out`` must hold a copy of
    ``x`` on entry (missing rows stay NaN).
    """
    n_f, n_m = x.shape[0], x.shape[1]
    w = mid.shape[0]
    h = w // 2
    for m in range(n_m):
        t = 0
        while t < n_f:
            if not (np.isfinite(x[t, m, 0]) and np.isfinite(x[t, m, 1]) and np.isfinite(x[t, m, 2])):
                t += 1
                continue
            a = t
            while t < n_f and np.isfinite(x[t, m, 0]) and np.isfinite(x[t, m, 1]) and np.isfinite(x[t, m, 2]):
                t += 1
            b = t
            if b - a < w:
                continue
            for c in range(3):
                for f in range(a, b):
                    acc = 0.0
                    if f - a < h:
                        for j in range(w):
                            acc += left[f - a, j] * x[a + j, m, c]
                    elif b - 1 - f < h:
                        r = f - b + h  # row of ``right``: 0 .. h-1 for frames b-h .. b-1
                        for j in range(w):
                            acc += right[r, j] * x[b - w + j, m, c]
                    else:
                        for j in range(w):
                            acc += mid[j] * x[f - h + j, m, c]
                    out[f, m, c] = acc


# ---------------------------------------------------------------------------------------------------------
# The global fit (lgi.solve.globalfit.GlobalFit) in one compiled call per frame: Gauss-Newton over the jaw and the
# bounded weights, each step a working-set box QP. In Python the bookkeeping around the kernels above (row
# caches, sets, small arrays) cost 20 ms per frame at 500 shapes, ten times the arithmetic.


@nb.njit(cache=True)
def _jaw_rotations(params):  # pragma: no cover - compiled
    """The opening (x), yaw (y) and roll (z) rotations of the jaw parameters (deg) and their derivatives per
    degree: (rx, ry, rz, drx, dry, drz), each (3, 3)."""
    k = np.pi / 180.0
    ca, sa = np.cos(k * params[0]), np.sin(k * params[0])
    cy, sy = np.cos(k * params[1]), np.sin(k * params[1])
    cz, sz = np.cos(k * params[2]), np.sin(k * params[2])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    drx = k * np.array([[0.0, 0.0, 0.0], [0.0, -sa, -ca], [0.0, ca, -sa]])
    dry = k * np.array([[-sy, 0.0, cy], [0.0, 0.0, 0.0], [-cy, 0.0, -sy]])
    drz = k * np.array([[-sz, -cz, 0.0], [cz, -sz, 0.0], [0.0, 0.0, 0.0]])
    return rx, ry, rz, drx, dry, drz


@nb.njit(cache=True)
def jaw_map(params, pivot, out):  # pragma: no cover - compiled
    """Top (3, 4) rows of the jaw's rigid motion (:func:`lgi.solve.jaw.jaw_matrix`) into ``out``."""
    rx, ry, rz, _, _, _ = _jaw_rotations(params)
    r = ry @ rz @ rx
    for c in range(3):
        for d in range(3):
            out[c, d] = r[c, d]
        out[c, 3] = pivot[c] - (r[c, 0] * pivot[0] + r[c, 1] * pivot[1] + r[c, 2] * pivot[2])
    out[2, 3] += params[3]


@nb.njit(cache=True)
def jaw_map_derivatives(params, pivot, out):  # pragma: no cover - compiled
    """(4, 3, 4) :func:`lgi.solve.jaw.jaw_matrix_derivatives` into ``out``."""
    rx, ry, rz, drx, dry, drz = _jaw_rotations(params)
    out[:] = 0.0
    for i in range(3):
        if i == 0:
            dr = ry @ rz @ drx
        elif i == 1:
            dr = dry @ rz @ rx
        else:
            dr = ry @ drz @ rx
        for c in range(3):
            for d in range(3):
                out[i, c, d] = dr[c, d]
            out[i, c, 3] = -(dr[c, 0] * pivot[0] + dr[c, 1] * pivot[1] + dr[c, 2] * pivot[2])
    out[3, 2, 3] = 1.0


@nb.njit(cache=True)
def _gf_system(rest, basis, seen_idx, p, w, theta, pivot, bw, has_rig, with_jaw, theta_scale, r,
               jaw_rows, rot):  # pragma: no cover - compiled
    """Residuals ``r`` (3m,) of the seen bundles at (theta, w), the jaw map's rotation ``rot`` (3, 3) and,
    with ``with_jaw``, the jaw's Jacobian rows (4, 3m) per unit of ``theta_scale``."""
    t = np.zeros((3, 4))
    if has_rig:
        jaw_map(theta, pivot, t)
    else:
        for c in range(3):
            t[c, c] = 1.0
    for c in range(3):
        for d in range(3):
            rot[c, d] = t[c, d]
    trans = t[:, 3].copy()
    global_residual(rest, basis, seen_idx, w, rot, trans, bw, p, r)
    if not with_jaw:
        return
    dts = np.empty((4, 3, 4))
    jaw_map_derivatives(theta, pivot, dts)
    nz = np.flatnonzero(w)
    x = np.empty(3)
    for e in range(seen_idx.shape[0]):
        i = seen_idx[e]
        _unskinned(rest, basis, nz, w, i, x)
        b = bw[i]
        for q in range(4):
            s = b * theta_scale[q]
            for c in range(3):
                jaw_rows[q, 3 * e + c] = s * (dts[q, c, 0] * x[0] + dts[q, c, 1] * x[1] + dts[q, c, 2] * x[2]
                                              + dts[q, c, 3])


@nb.njit(cache=True)
def _gf_row(basis, seen_idx, rot, bw, jaw_rows, nj, k, out):  # pragma: no cover - compiled
    """Jacobian row (3m,) of variable k (the jaw's first, then the shapes)."""
    if k < nj:
        out[:] = jaw_rows[k]
        return
    d = np.empty(3)
    for e in range(seen_idx.shape[0]):
        _shape_derivative(basis, k - nj, seen_idx[e], bw[seen_idx[e]], rot, d)
        for c in range(3):
            out[3 * e + c] = d[c]


@nb.njit(cache=True)
def _gf_gradient(basis, seen_idx, rot, bw, jaw_rows, nj, r, dz, z, reg, damp, row_pos, rowbuf, g):  # pragma: no cover
    """g = J^T (r + J dz) + reg (z + dz) + damp dz: the objective's gradient at the step ``dz`` (rows of its
    nonzero entries cached in ``rowbuf`` at ``row_pos``)."""
    v = r.copy()
    for k in range(dz.shape[0]):
        if dz[k] != 0.0:
            row = rowbuf[row_pos[k]]
            for j in range(v.shape[0]):
                v[j] += dz[k] * row[j]
    for q in range(nj):
        acc = 0.0
        for j in range(v.shape[0]):
            acc += jaw_rows[q, j] * v[j]
        g[q] = acc
    global_gradient(basis, seen_idx, rot, bw, v, g[nj:])
    for k in range(g.shape[0]):
        g[k] += reg[k] * (z[k] + dz[k]) + damp * dz[k]


@nb.njit(cache=True)
def _gf_top(score, cand, count, work):  # pragma: no cover - compiled
    """Mark in ``work`` the ``count`` variables of ``cand`` with the largest ``score`` (ties: the first in
    ``cand``, as a stable sort would take them). Picked one at a time, O(count x len(cand)) for 16 of a few
    hundred: a sort costs nothing more per call but compiles for 13 s on the first run after an install."""
    taken = np.zeros(cand.shape[0], np.bool_)
    for _ in range(min(count, cand.shape[0])):
        best = -1
        for a in range(cand.shape[0]):
            if not taken[a] and (best < 0 or score[cand[a]] > score[cand[best]]):
                best = a
        taken[best] = True
        work[cand[best]] = True


@nb.njit(cache=True)
def working_set_step(basis, seen_idx, rot, bw, jaw_rows, nj, r, w, reg, damp, col2, gain, grow):  # pragma: no cover
    """The step dz minimising ``|r + J dz|^2 + sum reg (z + dz)^2 + damp |dz|^2`` (z: 0 for the jaw, ``w`` for
    the weights; ``damp``: Levenberg-Marquardt damping of the step) with ``0 <= w + dz_w <= 1``, solved on a
    working set of variables.

    With hundreds of shapes, most of them in-betweens of others, the solution uses few; the others sit at a
    bound. The box QP is solved over the jaw, the shapes in use and the ``grow`` shapes whose gradient most
    wants them, then the optimality of every other shape is checked and violators join; the dense problem
    over all shapes (its normal matrix alone is 500^2 x 3m flops) is never formed. It stops when no shape
    outside the set could lower the objective by more than ``gain`` (cm^2) on its own. ``col2`` (n,): the
    Jacobian's squared column norms (without ``reg``).
    """
    n = nj + w.shape[0]
    m3 = r.shape[0]
    z = np.zeros(n)
    lo = np.full(n, -1e30)
    hi = np.full(n, 1e30)
    for k in range(w.shape[0]):
        z[nj + k] = w[k]
        lo[nj + k] = -w[k]
        hi[nj + k] = 1.0 - w[k]
    dz = np.zeros(n)
    row_pos = np.full(n, -1, np.int64)
    rowbuf = np.empty((max(64, 2 * grow), m3))
    n_rows = 0
    g = np.empty(n)
    col2r = col2 + reg + damp
    _gf_gradient(basis, seen_idx, rot, bw, jaw_rows, nj, r, dz, z, reg, damp, row_pos, rowbuf, g)
    work = np.zeros(n, np.bool_)
    dropped = np.zeros(n, np.bool_)
    for k in range(n):
        if k < nj or w[k - nj] > 0.0:
            work[k] = True
    wants = np.empty(n)
    for k in range(n):
        wants[k] = -g[k] if dz[k] <= lo[k] else (g[k] if dz[k] >= hi[k] else abs(g[k]))
    _gf_top(wants, np.arange(n), grow, work)
    gram = np.empty((rowbuf.shape[0], rowbuf.shape[0]))  # products of the cached rows, filled as they come
    rdot = np.empty(rowbuf.shape[0])  # and of each with r
    n_gram = 0
    for _ in range(50):
        ws = np.flatnonzero(work)
        nw = ws.shape[0]
        for a in range(nw):
            k = ws[a]
            if row_pos[k] < 0:
                if n_rows == rowbuf.shape[0]:
                    bigger = np.empty((2 * n_rows, m3))
                    bigger[:n_rows] = rowbuf
                    rowbuf = bigger
                    g2 = np.empty((2 * n_rows, 2 * n_rows))
                    g2[:n_rows, :n_rows] = gram[:n_rows, :n_rows]
                    gram = g2
                    r2 = np.empty(2 * n_rows)
                    r2[:n_rows] = rdot[:n_rows]
                    rdot = r2
                _gf_row(basis, seen_idx, rot, bw, jaw_rows, nj, k, rowbuf[n_rows])
                row_pos[k] = n_rows
                n_rows += 1
        if n_rows > n_gram:
            # The new rows' products with every cached row and with r (BLAS: the loops did not vectorise).
            blk = np.dot(rowbuf[n_gram:n_rows], rowbuf[:n_rows].T)
            gram[n_gram:n_rows, :n_rows] = blk
            gram[:n_rows, n_gram:n_rows] = blk.T
            rdot[n_gram:n_rows] = np.dot(rowbuf[n_gram:n_rows], r)
            n_gram = n_rows
        h = np.empty((nw, nw))
        rhs = np.empty(nw)
        for a in range(nw):
            pa = row_pos[ws[a]]
            rhs[a] = -rdot[pa] - reg[ws[a]] * z[ws[a]]
            for b in range(nw):
                h[a, b] = gram[pa, row_pos[ws[b]]]
            h[a, a] += reg[ws[a]] + damp
        sub = dz[ws]  # warm start: the last round's solution, zero for the newcomers
        # The QP's objective is half of this one: the same gain threshold for releasing a bound.
        box_qp(h, rhs, lo[ws], hi[ws], sub, np.int64(0), 1e-13, 0.5 * gain)
        dz[:] = 0.0
        for a in range(nw):
            dz[ws[a]] = sub[a]
        _gf_gradient(basis, seen_idx, rot, bw, jaw_rows, nj, r, dz, z, reg, damp, row_pos, rowbuf, g)
        # Outside the set a variable sits at its starting value: optimal only at a bound the gradient pushes
        # it against (weights at 0 with g >= 0, at 1 with g <= 0). A shape joins only if moving it alone would
        # lower the objective by more than ``gain``: with redundant shapes the ridge alone would otherwise pull
        # in every in-between, each for a vanishing gain.
        n_bad = 0
        bad = np.empty(n, np.int64)
        for k in range(n):
            if work[k]:
                continue
            if dz[k] <= lo[k] + 1e-15:
                pull = max(-g[k], 0.0)
            elif dz[k] >= hi[k] - 1e-15:
                pull = max(g[k], 0.0)
            else:
                pull = abs(g[k])
            if pull * pull > gain * col2r[k]:
                bad[n_bad] = k
                n_bad += 1
        if n_bad == 0:
            return dz
        # Shapes of the set that ended at zero with the gradient holding them there leave it (at most once
        # per step, so the set cannot cycle): it stays as small as the solution's support plus the newcomers.
        for a in range(nw):
            k = ws[a]
            if k >= nj and dz[k] <= lo[k] + 1e-15 and g[k] >= 0.0 and not dropped[k]:
                work[k] = False
                dropped[k] = True
        _gf_top(np.abs(g), bad[:n_bad], grow, work)
    return dz


@nb.njit(cache=True, nogil=True)
def global_gauss_newton(rest, basis, prod, seen_idx, p, w0, theta0, pivot, bw, has_rig, with_jaw, l2, gain,
                        theta_scale, max_iter, grow, w_out, theta_out, r_out):  # pragma: no cover - compiled
    """Minimise |r|^2 + l2 |w|^2 over the weights in [0, 1] (and, with ``with_jaw``, the jaw) by Gauss-Newton
    steps from (w0, theta0), each a box QP on a working set (:func:`working_set_step`) with
    Levenberg-Marquardt damping of the jaw (``grow``: shapes joining the working set per round). ``prod``:
    :func:`shape_products` of ``basis``. Writes ``w_out``
    (S,), ``theta_out`` (4,) and the residuals ``r_out`` (3m,) of the seen bundles at the result. Returns the
    Gauss-Newton steps taken.

    Alternating between the jaw and the weights stalls where a shape and the jaw move the same bundles
    (ICT's mouthLowerDown and a degree of opening): each step undoes the other's gain; a joint step moves
    both along that valley. Without the jaw the problem is linear and one step solves it.
    """
    n_s = basis.shape[0]
    nj = 4 if with_jaw else 0
    m3 = 3 * seen_idx.shape[0]
    w = np.minimum(np.maximum(w0, 0.0), 1.0)
    th = theta0.copy()
    reg = np.zeros(nj + n_s)
    reg[nj:] = l2
    r = np.empty(m3)
    rot = np.empty((3, 3))
    jaw_rows = np.zeros((nj, m3))
    _gf_system(rest, basis, seen_idx, p, w, th, pivot, bw, has_rig, with_jaw, theta_scale, r, jaw_rows, rot)
    # The shapes' column norms serve only the joining test; a step's change of the jaw barely moves them.
    col2 = np.empty(nj + n_s)
    global_col2(prod, seen_idx, rot, bw, col2[nj:])
    for q in range(nj):
        col2[q] = np.sum(jaw_rows[q] ** 2)
    c = np.sum(r**2) + l2 * np.sum(w**2)
    mu = 0.0
    r_new = np.empty(m3)
    rot_new = np.empty((3, 3))
    jaw_new = np.zeros((nj, m3))
    steps = 0
    for _ in range(max_iter):
        steps += 1
        dz = working_set_step(basis, seen_idx, rot, bw, jaw_rows, nj, r, w, reg, mu, col2, gain, grow)
        w_new = np.minimum(np.maximum(w + dz[nj:], 0.0), 1.0)
        th_new = th.copy()
        for q in range(nj):
            th_new[q] += dz[q] * theta_scale[q]
        _gf_system(rest, basis, seen_idx, p, w_new, th_new, pivot, bw, has_rig, with_jaw, theta_scale, r_new,
                   jaw_new, rot_new)
        c_new = np.sum(r_new**2) + l2 * np.sum(w_new**2)
        if not with_jaw:
            w, th = w_new, th_new
            r[:] = r_new
            break
        if c_new <= c:
            step = 0.0
            for k in range(dz.shape[0]):
                step = max(step, abs(dz[k]))
            stalled = c_new > c * (1 - 1e-10)
            w, th, c = w_new, th_new, c_new
            r[:] = r_new
            rot[:] = rot_new
            jaw_rows[:] = jaw_new
            for q in range(nj):
                col2[q] = np.sum(jaw_rows[q] ** 2)
            mu *= 0.1
            # Stalled: redundant shapes can trade weight without changing the cost, so the step need not
            # vanish; a relative gain of 1e-10 does not move the surface.
            if step < 1e-9 or stalled:
                break
        elif c_new <= c * (1 + 1e-10):
            break  # at the minimum: the step only moves the cost by rounding
        else:
            # The jaw is nonlinear: damp toward gradient steps (in the scaled parameters) until it helps. The
            # damping penalises the step, not the weights (a ridge on w + dz would pull every weight to 0 and
            # could never be accepted: measured, 22 wasted steps on 2 % of frames).
            mu = max(mu * 10, 1e-6 * np.mean(col2))
            if mu > 1e12:
                break
    w_out[:] = w
    theta_out[:] = th
    r_out[:] = r
    return steps


@nb.njit(cache=True, nogil=True)
def global_fit_frame(rest, basis, prod, seen_idx, p, w0, theta0, pivot, bw, has_rig, with_jaw, l2, gain,
                     theta_scale, max_iter, grow, w_out, theta_out, r_out):  # pragma: no cover - compiled
    """One frame's global fit (:class:`lgi.solve.globalfit.GlobalFit`): :func:`global_gauss_newton` over the jaw
    and the weights, then (with ``with_jaw``) the weights again at the final jaw exactly, since the joint
    solve stops at a tolerance. Arguments as for :func:`global_gauss_newton`."""
    steps = global_gauss_newton(rest, basis, prod, seen_idx, p, w0, theta0, pivot, bw, has_rig, with_jaw, l2,
                                gain, theta_scale, max_iter, grow, w_out, theta_out, r_out)
    if with_jaw:
        w1 = w_out.copy()
        th1 = theta_out.copy()
        # ``not with_jaw`` (False) rather than the literal: a literal argument is a type of its own, and numba
        # would compile the whole fit a second time for it.
        steps += global_gauss_newton(rest, basis, prod, seen_idx, p, w1, th1, pivot, bw, has_rig, not with_jaw, l2,
                                     gain, theta_scale, max_iter, grow, w_out, theta_out, r_out)
    return steps
