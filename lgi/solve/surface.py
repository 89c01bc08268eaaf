"""A frame's surface from its chosen weights: the natural-neighbour blend of the bundles' shapes (toward the
global fit in the far field), skinned with a jaw rig, and taken through the bundles by the smooth residual
correction."""

from __future__ import annotations

import dataclasses

import numpy as np

from lgi.errors import InputError
from lgi.solve._blend_kernels import add_correction, add_correction_serial, blend, blend_on_base, blend_uniform
from lgi.solve._jaw_kernels import skin_points
from lgi.solve.jaw import jaw_matrix
from lgi.solve.results import FrameResult
from lgi.units import MM_PER_CM

# A bundle's weights give way to the global fit in the far field where they predict the bundles beyond their
# neighbourhood this many times worse (RMS) than the global fit does (measured on captured-scan datasets: 1
# left the rigged session 12 % above its local-only error, 4 within 5 %, with the scans' extrapolation caught).
FAR_MARGIN = 2.0


class Surface:
    """Vertices for chosen shapes and weights (:meth:`surface`, :meth:`blend_frame`), the far field's shares
    (:meth:`far_shares`) and the correction through the bundles (:meth:`correct`).

    A part of :class:`~lgi.solve.solver.LGISolver`, which composes the stages: its methods read the state that
    ``LGISolver.__init__`` sets up from the index (``_a`` its arrays, ``_basis``, ``_rest``, the natural-neighbour
    pairs ``_pair_i``/``_pair_j``, ``layout``, ``rig``, ``global_fit``, ...).
    """

    @property
    def neutral(self) -> np.ndarray:
        """(V, 3) float64, cm: the mesh the shapes' deltas are added to (read only: the solver's own array)."""
        return self._x0

    @property
    def deltas(self) -> np.ndarray:
        """(S+1, V, 3), cm: each extended shape's displacement of the vertices, row 0 the neutral's (zeros)."""
        return self._deltas

    @property
    def skin_weights(self) -> np.ndarray | None:
        """(V,) float64: each vertex's jaw skinning weight (None without a rig)."""
        return self._skin_w if self.rig is not None else None

    def surface(self, shapes: np.ndarray, weights: np.ndarray, jaw: np.ndarray | None,
                far_share: np.ndarray | None = None) -> np.ndarray:
        """(V, 3) float64: the natural-neighbour blend of the bundles' shapes, skinned when there is a rig.

        ``shapes``, ``weights``: (M, K) slots per bundle, or (M + 1, K) with the frame's global fit last
        (:meth:`blend_slots`), which the far field blends toward with the bundles' far shares ``far_share``
        (M,) (:meth:`far_shares`; default: every bundle's share 1)."""
        a = self._a
        x = np.empty_like(self._x0)
        if (shapes == shapes[0]).all() and (weights == weights[0]).all():
            # Every bundle has the same weights (noisy bundles: the global fit's): no per-vertex mixing.
            blend_uniform(self._x0.reshape(-1), self._deltas_flat, self._w_sum,
                            shapes[0], weights[0], x.reshape(-1))
        elif len(shapes) == self.index.n_markers + 1:
            # The last row is the global fit's, which the far field blends toward. Most bundles of an exact
            # frame keep the global weights too: blend that row once over the mesh and, per vertex, only the
            # other bundles' differences from it (12.5 -> 1.6 ms per frame at 500 ICT shapes).
            m = self.index.n_markers
            if self._far.active:
                ramp = self._far.r
                share = np.ones(m) if far_share is None else np.clip(np.asarray(far_share, np.float64), 0.0, 1.0)
            else:
                ramp, share = self._no_ramp, np.zeros(m)
            d_shapes, d_lam = _differences(shapes, weights)
            rows = np.flatnonzero(d_lam[:m, 0] != 0)
            blend_on_base(self._x0.reshape(-1), self._deltas_flat, shapes[-1], weights[-1], self._w_sum,
                            self._reach, ramp, share, rows, d_shapes, d_lam, x.reshape(-1))
        else:
            blend(self._x0, self._deltas, a["w_indptr"], a["w_indices"], a["w_data"], shapes[:self.index.n_markers],
                    weights[:self.index.n_markers], x)
        if self.rig is not None:
            skin_points(x, self._skin_w, np.ascontiguousarray(jaw_matrix(jaw, self.rig.pivot)[:3]), x)
        return x

    def blend_slots(self, sel: FrameResult) -> tuple[np.ndarray, np.ndarray]:
        """A frame's slots for :meth:`surface`: the bundles' (M, K), and the global fit's weights as one more
        row (the far field's, and the base the bundles' weights are blended as differences from)."""
        if sel.fit is None:
            return sel.shapes, sel.weights
        shapes, weights = _append_rows([sel.shapes], [sel.weights], [sel.fit.weights])
        return shapes[0], weights[0]

    def blend_frame(self, sel: FrameResult, shapes: np.ndarray, weights: np.ndarray,
                    jaw: np.ndarray | None, bundles: np.ndarray | None = None) -> FrameResult:
        """Vertices for chosen (possibly smoothed) shapes and weights, skinned and taken through the bundles.

        ``bundles`` are the positions to pass through (default: those the selection was made for).
        """
        t = self.far_global_share(sel.far_share) if len(shapes) == self.index.n_markers + 1 and self._far.active \
            else None
        x = self.surface(shapes, weights, jaw, sel.far_share)
        p = sel.bundles if bundles is None else np.asarray(bundles, np.float64)
        seen = np.all(np.isfinite(p), axis=1)
        at = self.layout.evaluate(x)
        before = np.where(seen, np.linalg.norm(np.where(seen[:, None], p, 0) - at, axis=1), np.nan)
        # One frame on its own: the noise left is all of it.
        left = None if self.noise == 0 else (self.shot_noise.sigma / MM_PER_CM) ** 2
        step = self.correction_step(np.where(seen[:, None], p - at, np.nan), left)
        self.correct(x, at + step, seen)
        self.correct_far(x, step, seen, 1.0, t)
        residual = np.where(seen, np.linalg.norm(np.nan_to_num(p) - self.layout.evaluate(x), axis=1), np.nan)
        return dataclasses.replace(sel, vertices=x.astype(np.float32), residual=residual, jaw=jaw, bundles=p,
                                   residual_before=before)

    def correct(self, x: np.ndarray, p: np.ndarray, seen: np.ndarray, serial: bool = False) -> np.ndarray:
        """Take surface ``x`` (V, 3) through the seen bundles (in place); returns the residuals (M,) cm.
        ``serial``: on the calling thread alone (the same bits)."""
        a = self._a
        resid_vec = np.where(seen[:, None], p - self.layout.evaluate(x), 0.0)
        if self.correct_residuals:
            for _ in range(3):  # the stored basis is truncated: reapplying it removes what is left
                # 1e-7 cm is a hundredth of the 1e-4 mm a bundle may be off the surface.
                fix = np.flatnonzero(np.abs(resid_vec).max(axis=1) > 1e-7)
                if not fix.size:
                    break
                _add_correction(serial, x, a["corr_indptr"], a["corr_indices"], a["corr_data"], fix,
                                resid_vec[fix])
                resid_vec = np.where(seen[:, None], p - self.layout.evaluate(x), 0.0)
        return np.where(seen, np.linalg.norm(resid_vec, axis=1), np.nan)

    def meet_rays(self, x: np.ndarray, on: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Move surface ``x`` (V, 3) float64 cm, in place, so that the markers ``on`` (M,) bool meet their viewing
        rays (``origin`` (n, 3) cm, ``direction`` (n, 3) unit): each marker across its ray to the closest point, by
        the correction fields (1 at the marker, 0 at every other marker, which keep their points). Returns each
        marker's distance from its ray after it, (n,) mm.

        Noisy bundles are fitted, not interpolated (``ray_gain`` 0): a ray's point, from the same noisy
        observations, is then fitted like them, and the surface is moved the same share of the way."""
        pts = self.layout.evaluate(x)
        target = pts.copy()
        closest = origin + np.einsum("ij,ij->i", pts[on] - origin, direction)[:, None] * direction
        target[on] = pts[on] + self.shot_noise.ray_gain * (closest - pts[on])
        self.correct(x, target, np.ones(len(pts), bool))
        p = self.layout.evaluate(x)[on] - origin
        return np.linalg.norm(p - np.einsum("ij,ij->i", p, direction)[:, None] * direction, axis=1) * MM_PER_CM

    def correct_far(self, x: np.ndarray, resid: np.ndarray, seen: np.ndarray, gain: float | np.ndarray,
                    t: np.ndarray | None, serial: bool = False) -> None:
        """Leave the far field's share of the global fit uncorrected (in place): :meth:`correct` took ``x``
        through the bundles by the smooth field of the blend's residuals ``resid`` (M, 3); where the far field
        gives the global fit the share t (V,), that share of the field is taken off again, so those vertices
        are the global fit's surface as it is. The field carries what the bundles' local geometry left to
        meet them; far from them it is an extrapolation (measured: with it the far vertices of the rigged
        synthetic set were at 0.124 mm max against the global fit's 0.081). t is 0 at the bundles, which are
        still met exactly."""
        if t is None or not self.correct_residuals or not np.any(gain) or not t.any():
            return
        d = np.where(seen[:, None], -np.nan_to_num(resid), 0.0) * gain
        fix = np.flatnonzero(np.abs(d).max(axis=1) > 1e-7)
        if not fix.size:
            return
        a = self._a
        y = np.zeros_like(x)
        _add_correction(serial, y, a["corr_indptr"], a["corr_indices"], a["corr_data"], fix, d[fix])
        x += t[:, None] * y

    def far_global_share(self, share: np.ndarray | None) -> np.ndarray:
        """(V,) the far field's share t of the global fit per vertex, given the bundles' far shares (M,) (None:
        all 1): a vertex at ramp r (:class:`_FarField`) keeps ``N_vb (1 - r s_b)`` of bundle b's weights and gives
        ``t = r sum_b N_vb s_b`` to the global fit."""
        return self._far.global_share(share)

    def far_shares(self, q: np.ndarray, seen: np.ndarray, weights: np.ndarray, global_weights: np.ndarray
                   ) -> np.ndarray:
        """(M,) each bundle's far share: how much worse its weights predict the seen bundles of its second
        ring of natural neighbours (not fitted to them) than the global fit's do.

        With ``e_b`` its RMS misfit there and ``g_b`` the global fit's, the share is
        ``(e_b^2 - c g_b^2) / (e_b^2 + c g_b^2)`` clipped to [0, 1], ``c = FAR_MARGIN^2``: 0 unless the bundle's
        weights miss the ring clearly worse than the global fit (which was fitted to it), near 1 where the
        bundle's geometry leaves its neighbourhood (a captured scan that fits a bundle's neighbours and not the
        face beyond).

        Parameters
        ----------
        q : (M, 3) float, cm
            Bundles (unskinned with a rig); rows of unseen ones are ignored.
        seen : (M,) bool
        weights : (M, S) float
            Each bundle's shape weights.
        global_weights : (S,) float
        """
        i, j = self._ring_i, self._ring_j
        ok = seen[j]
        i, j = i[ok], j[ok]
        used = np.flatnonzero(np.any(weights != 0, axis=0))
        pred = self._rest[j] + np.einsum("ek,kec->ec", weights[i][:, used], self._basis[used][:, j])
        d_own = np.sum((pred - q[j]) ** 2, axis=1)
        g = global_weights != 0
        glob = self._rest + np.tensordot(global_weights[g], self._basis[g], axes=1)
        d_glob = np.sum((glob[j] - q[j]) ** 2, axis=1)
        cnt = np.maximum(np.bincount(i, minlength=len(q)), 1)
        e2 = np.bincount(i, d_own, minlength=len(q)) / cnt
        g2 = np.bincount(i, d_glob, minlength=len(q)) / cnt
        # The global fit was fitted to the ring, the bundle's weights were not: the global fit takes a share
        # only where the bundle's weights miss the ring by more than FAR_MARGIN times its RMS misfit.
        c = FAR_MARGIN**2
        return np.clip((e2 - c * g2) / (e2 + c * g2 + 1e-12), 0.0, 1.0)


class _FarField:
    """The natural-neighbour weights with a far field (see :class:`LGISolver`, ``far_field``).

    A vertex at UV-geodesic distance d from its nearest bundle has the ramp r (V,): 0 up to ``far_field[0]`` cm,
    1 from ``far_field[1]``, a smoothstep between, and 0 on every bundle's own triangle (the surface passes
    through the bundles) and where no bundle's weights reach. Per frame, given each bundle's far share s (M,),
    the vertex keeps ``N_vb (1 - r_v s_b)`` of bundle b's weights and gives ``t_v = r_v sum_b N_vb s_b`` to
    the frame's global fit (:meth:`global_share`; :func:`lgi.solve._blend_kernels.blend_on_base` blends them).
    """

    def __init__(self, arrays, n_markers: int, far_field: tuple[float, float] | None) -> None:
        self.n_markers = n_markers
        self.active = False
        if far_field is None:
            return
        d0, d1 = far_field
        if not (np.isfinite(d0) and d0 >= 0 and d1 > d0):
            raise InputError(f"far field must be two distances 0 <= start < end (cm), not {far_field}")
        indptr, indices, data = arrays["w_indptr"], arrays["w_indices"], arrays["w_data"]
        dist = np.asarray(arrays["nn_distance"], np.float64)
        u = np.clip((dist - d0) / (d1 - d0), 0.0, 1.0) if np.isfinite(d1) else np.zeros_like(dist)
        r = u * u * (3.0 - 2.0 * u)
        r[np.diff(indptr) == 0] = 0.0
        # A bundle's own triangle keeps its weights whatever its size: the surface passes through the bundle.
        r[np.asarray(arrays["marker_vertices"]).ravel()] = 0.0
        if not (r > 0).any():
            return
        self.active = True
        self.n_v = len(indptr) - 1
        self.row = np.repeat(np.arange(self.n_v), np.diff(indptr))  # the vertex of each weight
        self.col = np.asarray(indices, np.int64)
        self.nn = np.asarray(data, np.float64)
        self.r = r

    def global_share(self, share: np.ndarray | None) -> np.ndarray:
        """(V,) t for the bundles' far shares (M,) (None: 1)."""
        s = np.ones(self.n_markers) if share is None else np.clip(np.asarray(share, np.float64), 0.0, 1.0)
        return np.bincount(self.row, self.nn * self.r[self.row] * s[self.col], minlength=self.n_v)


def _differences(shapes: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row's slots minus the last row's, as slots: ``(N, K')`` shapes and weight differences, each row's
    nonzero differences first and the rest 0 (a row that equals the last one has none).

    Parameters
    ----------
    shapes : (N, K) int64
        Extended shape indices (0: the neutral, with weight 0).
    weights : (N, K) float64
    """
    n = len(shapes)
    width = int(shapes.max()) + 1
    dense = np.zeros((n, width))
    np.add.at(dense, (np.repeat(np.arange(n), shapes.shape[1]), shapes.ravel()), weights.ravel())
    dense -= dense[-1]
    dense[:, 0] = 0.0
    nz = dense != 0.0
    k = max(1, int(nz.sum(1).max()))
    order = np.argsort(~nz, axis=1, kind="stable")[:, :k]
    taken = np.take_along_axis(nz, order, axis=1)
    return (np.ascontiguousarray(np.where(taken, order, 0), np.int64),
            np.ascontiguousarray(np.where(taken, np.take_along_axis(dense, order, axis=1), 0.0)))


def _append_rows(shapes: list[np.ndarray], weights: list[np.ndarray], fit_weights: list[np.ndarray]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(F, M + 1, K) slots: each frame's bundles' slots and, as the last row, its global fit's weights (S,)
    as slots (extended shape indices)."""
    rows_s, rows_w = [], []
    for s, w, g in zip(shapes, weights, fit_weights, strict=True):
        nz = np.flatnonzero(np.asarray(g) > 0)
        k = max(s.shape[1], len(nz), 1)
        out_s = np.zeros((s.shape[0] + 1, k), np.int64)
        out_w = np.zeros((s.shape[0] + 1, k))
        out_s[:-1, :s.shape[1]] = s
        out_w[:-1, :w.shape[1]] = w
        out_s[-1, :len(nz)] = nz + 1
        out_w[-1, :len(nz)] = np.asarray(g)[nz]
        rows_s.append(out_s)
        rows_w.append(out_w)
    return _stack_slots(rows_s, rows_w)


def _stack_slots(shapes: list[np.ndarray], weights: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(F, M, K) shapes and weights of frames whose bundles use different numbers of slots (zero-padded)."""
    k = max(s.shape[1] for s in shapes)
    out_s = np.zeros((len(shapes), shapes[0].shape[0], k), np.int64)
    out_w = np.zeros((len(shapes), shapes[0].shape[0], k))
    for f, (s, w) in enumerate(zip(shapes, weights, strict=True)):
        out_s[f, :, :s.shape[1]] = s
        out_w[f, :, :w.shape[1]] = w
    return out_s, out_w


def _add_correction(serial: bool, *args) -> None:
    """:func:`~lgi.solve._blend_kernels.add_correction`, or its one-thread twin with ``serial``."""
    (add_correction_serial if serial else add_correction)(*args)
