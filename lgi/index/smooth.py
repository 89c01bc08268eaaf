"""Smooth interpolation of values given at bundle points over the mesh (linear shell deformation).

Minimises stretching and bending of a per-vertex field ``d`` (Bickel et al. 2007; Bhat et al. 2013)::

    E(d) = ks d^T L d + kb d^T L M^-1 L d + eps d^T M d      subject to  C d = r

with ``L`` the cotangent Laplacian, ``M`` the lumped (barycentric) mass matrix and ``C`` the
barycentric rows of the bundle points; the stationarity condition is ``(ks L + kb L M^-1 L) d = 0`` away
from the constraints. ``eps`` (tiny) makes parts with no constraint (eyeballs, teeth) decay to zero
instead of leaving the system singular. The KKT system is factorised once; every solve reuses it.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu


def cotangent_laplacian(vertices: np.ndarray, triangles: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """Cotangent Laplacian (positive semi-definite, ``L = D - W``) and lumped vertex areas.

    Parameters
    ----------
    vertices : (V, 3) float; triangles : (T, 3) int

    Returns
    -------
    L : (V, V) csr_matrix
    area : (V,) float64
        One third of the incident triangle areas.
    """
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    n = len(v)
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, o = t[:, (k + 1) % 3], t[:, (k + 2) % 3], t[:, k]
        a, b = v[i] - v[o], v[j] - v[o]
        cross = np.linalg.norm(np.cross(a, b), axis=1)
        cot = np.einsum("ij,ij->i", a, b) / np.maximum(cross, 1e-12)
        rows += [i, j]
        cols += [j, i]
        vals += [0.5 * cot, 0.5 * cot]
    w = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    lap = sp.diags(np.asarray(w.sum(1)).ravel()) - w
    tri_area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    area = np.bincount(t.ravel(), weights=np.repeat(tri_area / 3, 3), minlength=n)
    return lap.tocsr(), area


class SmoothInterpolator:
    """Interpolate values at bundle points smoothly over a mesh; factorised once, solved per frame.

    Parameters
    ----------
    vertices : (V, 3) float, cm; triangles : (T, 3) int
        The neutral mesh.
    point_vertices : (M, 3) int; point_bary : (M, 3) float
        The constrained points (each bundle's triangle and barycentric coordinates).
    ks, kb : float
        Stretching and bending stiffness (defaults 1 and 100).
    eps : float
        Decay weight (relative to the mass matrix).
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, point_vertices: np.ndarray,
                 point_bary: np.ndarray, ks: float = 1.0, kb: float = 100.0, eps: float = 1e-6) -> None:
        lap, area = cotangent_laplacian(vertices, triangles)
        n = len(vertices)
        m = len(point_vertices)
        mass = np.maximum(area, 1e-12 * max(area.max(), 1e-12))
        a = ks * lap + kb * (lap @ sp.diags(1.0 / mass) @ lap) + eps * sp.diags(mass)
        rows = np.repeat(np.arange(m), 3)
        c = sp.csr_matrix((np.asarray(point_bary, np.float64).ravel(), (rows, np.asarray(point_vertices).ravel())),
                          shape=(m, n))
        kkt = sp.bmat([[a, c.T], [c, None]], format="csc")
        self._lu = splu(kkt)
        self.n_vertices = n
        self.n_points = m
        self.constraints = c

    def solve(self, values: np.ndarray) -> np.ndarray:
        """Field taking ``values`` (M, k) at the points: (V, k) float64."""
        values = np.asarray(values, np.float64)
        rhs = np.zeros((self.n_vertices + self.n_points, values.shape[1]))
        rhs[self.n_vertices:] = values
        return self._lu.solve(rhs)[: self.n_vertices]

    def basis(self) -> np.ndarray:
        """(V, M) float64: the field of each point's unit value (all others zero)."""
        return self.solve(np.eye(self.n_points))
