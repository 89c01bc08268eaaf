"""ClosestPointQuery: the exact closest point of a triangle mesh, on meshes whose triangles differ greatly in size
(ICT's largest is 7 times its median), with its working arrays bounded."""

from __future__ import annotations

import numpy as np
import pytest

from lgi.dataset.mesh import ClosestPointQuery, closest_point_on_triangles


def mixed_mesh(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A fine, bumpy 30 x 30 grid (cm) and, beside it, a few triangles 40 times its cells' size."""
    n = 30
    x, y = np.meshgrid(np.linspace(0, 3, n), np.linspace(0, 3, n))
    z = 0.05 * np.sin(4 * x) * np.cos(3 * y)
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).ravel()
    t = np.concatenate([np.stack([a, a + 1, a + n], 1), np.stack([a + 1, a + n + 1, a + n], 1)])
    big = np.array([[3.2, 0, 0], [7, 0, 0.4], [3.2, 4, -0.3], [7, 4, 0.2]]) + rng.normal(0, 0.01, (4, 3))
    t_big = np.array([[0, 1, 2], [1, 3, 2]]) + len(v)
    return np.concatenate([v, big]), np.concatenate([t, t_big])


def brute(v: np.ndarray, t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N,) distance to the closest of all triangles."""
    q = np.repeat(p, len(t), axis=0)
    tt = np.tile(t, (len(p), 1))
    w = closest_point_on_triangles(q, v[tt[:, 0]], v[tt[:, 1]], v[tt[:, 2]])
    cp = np.einsum("nk,nkd->nd", w, v[tt])
    return np.linalg.norm(cp - q, axis=1).reshape(len(p), -1).min(axis=1)


@pytest.mark.parametrize("pairs", [1 << 19, 64])
def test_exact_on_triangles_of_very_different_sizes(pairs: int, monkeypatch) -> None:
    rng = np.random.default_rng(3)
    v, t = mixed_mesh(rng)
    monkeypatch.setattr(ClosestPointQuery, "PAIRS", pairs)
    q = ClosestPointQuery(v, t)
    p = np.concatenate([rng.uniform([-0.5, -0.5, -0.5], [7.5, 4.5, 0.5], (300, 3)), v[::7]])
    tri, bary, dist = q.query(p)
    np.testing.assert_allclose(dist, brute(v, t, p), rtol=0, atol=1e-12)
    # The triangle and barycentrics returned give that point.
    cp = np.einsum("nk,nkd->nd", bary, v[t[tri]])
    np.testing.assert_allclose(np.linalg.norm(cp - p, axis=1), dist, rtol=0, atol=1e-12)
    assert np.all(bary >= -1e-12) and np.allclose(bary.sum(1), 1)


def test_samples_bound_the_search_radius() -> None:
    """The big triangles are split, so the bound is near the grid's cells, not the big triangles' size."""
    v, t = mixed_mesh(np.random.default_rng(4))
    q = ClosestPointQuery(v, t)
    corners = v[t]
    radius = np.linalg.norm(corners - corners.mean(1, keepdims=True), axis=2).max(1)
    assert q._radius <= ClosestPointQuery.SAMPLE_RADIUS * np.median(radius) + 1e-12
    assert q._radius < radius.max() / 10
    # A vertex of the mesh is found on the mesh, at distance 0, and its triangle holds it.
    tri, bary, dist = q.query(v)
    assert np.all(dist < 1e-12)
    assert np.all(np.any(t[tri] == np.arange(len(v))[:, None], axis=1))
