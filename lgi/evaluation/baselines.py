"""The approaches LGI is compared with (paper sections 7.3-7.4), behind the solver interface of
:class:`lgi.solve.solver.LGISolver`: ``solve_frame(bundles, previous=None)`` returning a
:class:`~lgi.solve.solver.FrameResult`-like object with ``vertices`` and ``residual``, and ``solve_sequence``.

* :class:`SmoothSolver`: the bundles' displacements interpolated by a linear shell (stretching and
  bending, Bickel et al. 2007; Bhat et al. 2013); no detail beyond the neutral's.
* :class:`BlendshapeSolver`: shape weights in [0, 1] minimising the bundles' distances (bounded least
  squares), optionally L2-regularised.
* :class:`RiggedBlendshapeSolver`: the same fit with a jaw rig: the jaw and the weights of the unskinned
  shapes solved together (:class:`~lgi.solve.globalfit.GlobalFit`, the jaw estimate LGI uses too).

With a rigged index every baseline is given the same rig and the same jaw estimate as LGI: the shell
interpolates the bundles' displacements from the neutral skinned by the estimated jaw, and RBF blends
LGI's weights of unskinned shapes and skins the result.
* :class:`RBFSolver`: LGI's per-bundle shape weights spread over the mesh by Gaussian radial basis
  functions instead of natural-neighbour weights, then the remaining bundle displacements interpolated
  by the smooth method so the surface passes through the bundles (section 7.4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import lsq_linear
from scipy.spatial import cKDTree

from lgi.dataset.markers import MarkerLayout
from lgi.dataset.shapes import ShapeDataset
from lgi.index.build import LGIIndex
from lgi.index.smooth import SmoothInterpolator
from lgi.solve._blend_kernels import blend
from lgi.solve.globalfit import GlobalFit, GlobalFitResult
from lgi.solve.jaw import JawRig
from lgi.solve.solver import LGISolver
from lgi.threads import one_blas_thread


@dataclass
class SimpleResult:
    """A baseline's frame: vertices (V, 3) float32 cm; residual (M,) cm (NaN for missing bundles);
    weights: shape weights (S,) where the method has global ones."""

    vertices: np.ndarray
    residual: np.ndarray
    weights: np.ndarray | None = None
    fit: GlobalFitResult | None = None


class _SequenceMixin:
    @one_blas_thread
    def solve_sequence(self, positions: np.ndarray) -> np.ndarray:
        """(F, V, 3) float32 for bundle positions (F, M, 3)."""
        prev = None
        out = []
        for p in positions:
            prev = self.solve_frame(p, prev)
            out.append(prev.vertices)
        return np.stack(out)


def _residual(layout: MarkerLayout, x: np.ndarray, p: np.ndarray) -> np.ndarray:
    seen = np.all(np.isfinite(p), axis=1)
    r = np.linalg.norm(layout.evaluate(x) - np.where(seen[:, None], p, 0), axis=1)
    return np.where(seen, r, np.nan)


class SmoothSolver(_SequenceMixin):
    """Linear shell interpolation of bundle displacements; factorised once.

    Parameters
    ----------
    neutral : (V, 3) float, cm; triangles : (T, 3) int
    layout
        The markers (constraint points).
    ks, kb
        Stretching and bending stiffness (1 and 100).
    rig, jaw_fit
        Optional jaw rig and the estimator of each frame's jaw (the one LGI uses): the displacements are
        then interpolated from the neutral skinned by the estimated jaw.
    """

    name = "smooth"

    def __init__(self, neutral: np.ndarray, triangles: np.ndarray, layout: MarkerLayout, ks: float = 1.0,
                 kb: float = 100.0, rig: JawRig | None = None, jaw_fit: GlobalFit | None = None) -> None:
        self.layout = layout
        self.x0 = np.asarray(neutral, np.float64)
        self.rest = layout.evaluate(self.x0)
        self.interp = SmoothInterpolator(self.x0, triangles, layout.vertices, layout.weights, ks, kb)
        self.rig = rig
        self.jaw_fit = jaw_fit

    def solve_frame(self, bundles: np.ndarray, previous: SimpleResult | None = None) -> SimpleResult:
        p = np.asarray(bundles, np.float64)
        seen = np.all(np.isfinite(p), axis=1)
        base, fit = self.x0, None
        if self.rig is not None:
            fit = self.jaw_fit.solve(p, init=None if previous is None else previous.fit)
            base = self.rig.skin(self.x0, fit.jaw)
        rest = self.layout.evaluate(base)
        disp = np.where(seen[:, None], p - rest, 0.0)
        if previous is not None and not seen.all():
            # A missing bundle keeps its previous displacement rather than snapping back to rest.
            disp[~seen] = (self.layout.evaluate(previous.vertices.astype(np.float64)) - rest)[~seen]
        x = base + self.interp.solve(disp)
        return SimpleResult(x.astype(np.float32), _residual(self.layout, x, p), fit=fit)


class BlendshapeSolver(_SequenceMixin):
    """Bounded least-squares blendshape fit: min ||B w - (p - p0)||^2 + l2 ||w||^2, 0 <= w <= 1.

    Parameters
    ----------
    dataset
        The shapes (the blendshape basis).
    layout
        The markers.
    l2 : float
        Regularisation weight (cm^2 per unit weight^2); 0 for none.
    """

    name = "blendshape"

    def __init__(self, dataset: ShapeDataset, layout: MarkerLayout, l2: float = 0.0) -> None:
        self.layout = layout
        self.x0 = np.asarray(dataset.neutral, np.float64)
        self.deltas = np.asarray(dataset.deltas, np.float32)
        self.rest = layout.evaluate(self.x0)
        self.basis = layout.evaluate(self.deltas.astype(np.float64))  # (S, M, 3)
        self.l2 = float(l2)

    def solve_frame(self, bundles: np.ndarray, previous: SimpleResult | None = None) -> SimpleResult:
        p = np.asarray(bundles, np.float64)
        seen = np.all(np.isfinite(p), axis=1)
        a = self.basis[:, seen].reshape(len(self.basis), -1).T
        b = (p[seen] - self.rest[seen]).ravel()
        if self.l2 > 0:
            a = np.vstack([a, np.sqrt(self.l2) * np.eye(a.shape[1])])
            b = np.concatenate([b, np.zeros(a.shape[1])])
        w = lsq_linear(a, b, bounds=(0.0, 1.0), method="bvls").x
        x = self.x0 + np.tensordot(w, self.deltas, axes=1)
        return SimpleResult(x.astype(np.float32), _residual(self.layout, x, p), w)


class RBFSolver(_SequenceMixin):
    """LGI's per-bundle shape weights blended by Gaussian RBFs, then smoothly corrected to the bundles.

    The RBF interpolation matrix ``R = Phi_vb Phi_bb^-1`` (Gaussian of 3D distance on the neutral,
    width ``sigma``, default half the median distance from a bundle to its nearest bundle) reproduces each
    bundle's own weights at its point; rows are normalised to sum to 1, Shepard weights where the
    interpolant vanishes, entries below 1e-6 dropped. Distances are Euclidean (as RBFs usually are), so
    kernels reach across the mouth opening: that is where this baseline's largest errors are.
    """

    name = "rbf"

    def __init__(self, index: LGIIndex, sigma: float | None = None) -> None:
        # The paper's variant (7.4): the weights of LGI's simplex choice, the jaw from the global fit.
        self.lgi = LGISolver(index, method="simplex")
        self.layout = self.lgi.layout
        x0 = np.asarray(index.arrays["neutral"], np.float64)
        self.x0 = x0
        rest = self.layout.evaluate(x0)
        if sigma is None:
            # Half the median bundle spacing: measured best on the synthetic held-out performance
            # (RMS 0.43 / 0.49 / 0.97 / 2.13 mm at 0.35 / 0.5 / 0.75 / 1 x spacing); wider kernels'
            # negative lobes push shape weights far outside [0, 1].
            d, _ = cKDTree(rest).query(rest, k=2)
            sigma = 0.5 * float(np.median(d[:, 1]))
        self.sigma = sigma
        dvb = np.linalg.norm(x0[:, None, :] - rest[None], axis=2)
        dbb = np.linalg.norm(rest[:, None, :] - rest[None], axis=2)
        phi_vb = np.exp(-(dvb**2) / (2 * sigma**2))
        phi_bb = np.exp(-(dbb**2) / (2 * sigma**2))
        r = np.linalg.solve(phi_bb + 1e-9 * np.eye(len(rest)), phi_vb.T).T  # (V, M)
        # Rows are normalised to sum to 1 (a blend of shape weights, not a scaling of them); at a bundle
        # the row is already that bundle's unit vector. Where the interpolant vanishes (far from every
        # bundle) the normalised Gaussians (Shepard weights) are used instead.
        tot = r.sum(1, keepdims=True)
        shepard = phi_vb / np.maximum(phi_vb.sum(1, keepdims=True), 1e-300)
        r = np.where(np.abs(tot) > 0.5, r / np.where(np.abs(tot) > 0.5, tot, 1.0), shepard)
        r[np.abs(r) < 1e-6] = 0.0
        rm = sp.csr_matrix(r)
        self._indptr = rm.indptr.astype(np.int64)
        self._indices = rm.indices.astype(np.int64)
        self._data = rm.data.astype(np.float64)

    def solve_frame(self, bundles: np.ndarray, previous: SimpleResult | None = None) -> SimpleResult:
        prev_sel = None if previous is None else previous.fit
        sel = self.lgi.select_frame(bundles, prev_sel)  # LGI's shapes and weights per bundle (and the jaw)
        x = np.empty_like(self.x0)
        blend(self.x0, self.lgi.deltas, self._indptr, self._indices, self._data, sel.shapes, sel.weights, x)
        if self.lgi.rig is not None:
            x = self.lgi.rig.skin(x, sel.jaw)
        seen = np.all(np.isfinite(sel.bundles), axis=1)
        residual = self.lgi.correct(x, sel.bundles, seen)
        return SimpleResult(x.astype(np.float32), residual, fit=sel)


class RiggedBlendshapeSolver(_SequenceMixin):
    """Bounded blendshape fit of an index's shapes with its jaw rig: jaw and weights of the unskinned
    shapes solved together for every frame (:class:`~lgi.solve.globalfit.GlobalFit`), then the blend skinned.
    Without a rig it is the plain bounded fit of the index's shapes."""

    name = "blendshape_rig"

    def __init__(self, index: LGIIndex) -> None:
        self.lgi = LGISolver(index)
        self.layout = self.lgi.layout
        self.fit = self.lgi.global_fit
        self.x0 = self.lgi.neutral
        self.deltas = np.asarray(index.deltas[1:])

    def solve_frame(self, bundles: np.ndarray, previous: SimpleResult | None = None) -> SimpleResult:
        p = np.asarray(bundles, np.float64)
        fit = self.fit.solve(p, init=None if previous is None else previous.fit)
        x = self.x0 + np.tensordot(fit.weights, self.deltas, axes=1)
        if self.lgi.rig is not None:
            x = self.lgi.rig.skin(x, fit.jaw)
        return SimpleResult(x.astype(np.float32), _residual(self.layout, x, p), fit.weights, fit)


class LGIMethod(_SequenceMixin):
    """LGI behind the same small interface (sequence with the previous-frame preference)."""

    name = "lgi"

    def __init__(self, index: LGIIndex, **kw) -> None:
        self.solver = LGISolver(index, **kw)
        self.layout = self.solver.layout

    def solve_frame(self, bundles: np.ndarray, previous=None):
        return self.solver.solve_frame(bundles, previous)
