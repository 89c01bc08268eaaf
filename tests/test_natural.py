from pathlib import Path

import numpy as np
import pytest

from lgi.dataset.markers import read_layout
from lgi.dataset.mesh import triangulate
from lgi.index.natural import natural_neighbour_weights, uv_metric_graph
from lgi.io.obj import read_obj
from lgi.paths import shipped
from lgi.synthetic import actor as synth


def _layout(actor: synth.SyntheticActor, n: int = 30, seed: int = 0):
    rng = np.random.default_rng(seed)
    v = actor.neutral
    cand = np.flatnonzero((np.abs(v[:, 0]) < 6) & (np.abs(v[:, 1]) < 8) & (np.abs(v[:, 1] - synth.MOUTH_Y) > 0.5))
    tris = actor.triangles
    first = {}
    for t, row in enumerate(tris):
        for c in row:
            first.setdefault(int(c), t)
    picks = rng.choice(cand, n, replace=False)
    tri = np.array([first[int(p)] for p in picks])
    bary = np.array([(tris[t] == p).astype(float) for t, p in zip(tri, picks, strict=True)])
    return picks, tri, bary


@pytest.fixture(scope="module")
def nn_small(small_actor):
    a = small_actor
    picks, tri, bary = _layout(a)
    nn = natural_neighbour_weights(a.neutral, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs, tri, bary)
    return a, picks, tri, bary, nn


def test_partition_of_unity_and_interpolation(nn_small) -> None:
    a, picks, tri, bary, nn = nn_small
    w = nn.weights.toarray()
    assert w.min() >= 0
    np.testing.assert_allclose(w.sum(1), 1, atol=1e-6)
    # A vertex coincident with its bundle: 1 for it, 0 for every other bundle.
    np.testing.assert_allclose(w[picks], np.eye(len(picks)), atol=1e-6)
    assert all(len(n) >= 1 for n in nn.neighbours) and np.mean([len(n) for n in nn.neighbours]) > 3
    # Natural neighbours are symmetric.
    for i, ns in enumerate(nn.neighbours):
        for j in ns:
            assert i in nn.neighbours[j]


def test_weights_blend_several_bundles(nn_small) -> None:
    """Natural-neighbour (Sibson) weights blend the bundles around a vertex, not only the nearest one's: measured,
    94 % of the marked region's vertices draw on two bundles or more, 3.5 on average (the nearest bundle's weights
    alone would give 0 % and 1)."""
    a, picks, tri, bary, nn = nn_small
    w = nn.weights.toarray()[nn.region]
    n = (w > 1e-6).sum(1)
    assert (n > 1).mean() > 0.8 and n.mean() > 2.5


def test_weights_fall_off_with_distance(nn_small) -> None:
    a, picks, tri, bary, nn = nn_small
    w = nn.weights.toarray()
    i = 0
    d = np.linalg.norm(a.neutral - a.neutral[picks[i]], axis=1)
    # Mean weight falls with distance (a border bundle's cell may still reach far vertices).
    bins = [w[(d > lo) & (d < hi), i].mean() for lo, hi in ((0, 1.2), (2, 4), (6, 99))]
    assert bins[0] > 0.5 > bins[1] > bins[2] and bins[2] < 0.05


def test_uv_seam_changes_nothing(small_actor) -> None:
    """Cutting the UV chart in two (the right half moved to another tile) leaves the weights unchanged:
    distances run on the welded mesh, each edge measured in its own chart."""
    a = small_actor
    picks, tri, bary = _layout(a, seed=1)
    # float64 UVs: a float32 tile shift rounds lengths by 1e-7, enough to flip samples on Voronoi ties.
    uv64 = a.uvs.astype(np.float64)
    base = natural_neighbour_weights(a.neutral, a.face_vertices, a.face_offsets, uv64, a.face_uvs, tri, bary)
    # Seam along x = 0: vertices right of it get a second UV, shifted by one tile, used by right faces.
    uvs = np.vstack([uv64, uv64 + [1.0, 0.0]])
    n_uv = len(a.uvs)
    fo = a.face_offsets
    cx = a.neutral[a.face_vertices, 0].reshape(-1, 4).mean(1)
    right = np.repeat(cx > 0, 4)
    face_uvs = np.where(right, a.face_uvs + n_uv, a.face_uvs)
    seam_vertices = np.intersect1d(a.face_vertices[right], a.face_vertices[~right])
    assert seam_vertices.size > 20
    cut = natural_neighbour_weights(a.neutral, a.face_vertices, fo, uvs, face_uvs, tri, bary)
    np.testing.assert_allclose(cut.weights.toarray(), base.weights.toarray(), atol=1e-6)


def test_outside_region_copies_a_region_vertex(small_actor) -> None:
    a = small_actor
    picks, tri, bary = _layout(a, n=12, seed=2)
    nn = natural_neighbour_weights(a.neutral, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs, tri, bary,
                                   region_radius=1.5)
    w = nn.weights.toarray()
    outside = np.flatnonzero(~nn.region)
    assert outside.size > 100
    inside_rows = {tuple(np.round(r, 6)) for r in w[nn.region]}
    assert all(tuple(np.round(w[v], 6)) in inside_rows for v in outside[:50])
    np.testing.assert_allclose(w.sum(1), 1, atol=1e-6)


def test_ict_weights_continuous_across_seams(ict_dir: Path) -> None:
    mesh = read_obj(ict_dir / "generic_neutral_mesh.obj")
    tris, _ = triangulate(mesh.face_vertices, mesh.face_offsets)
    layout = read_layout(shipped("markers_ict.csv"), tris)
    nn = natural_neighbour_weights(mesh.vertices, mesh.face_vertices, mesh.face_offsets, mesh.uvs, mesh.face_uvs,
                                   layout.triangles, layout.weights)
    w = nn.weights.tocsr()
    np.testing.assert_allclose(np.asarray(w.sum(1)).ravel(), 1, atol=1e-5)
    # Edges whose two ends have several UVs (seam edges) vs all edges, inside the marked region.
    pairs = np.unique(np.stack([mesh.face_vertices, mesh.face_uvs], 1), axis=0)
    seam = np.bincount(pairs[:, 0], minlength=len(mesh.vertices)) > 1
    g, _ = uv_metric_graph(mesh.vertices, mesh.face_vertices, mesh.face_offsets, mesh.uvs, mesh.face_uvs)
    g = g.tocoo()
    keep = nn.region[g.row] & nn.region[g.col]
    r, c = g.row[keep], g.col[keep]
    diff = np.abs(w[r] - w[c]).max(axis=1).toarray().ravel()
    on_seam = seam[r] & seam[c]
    assert on_seam.sum() > 100
    assert np.percentile(diff[on_seam], 99) <= 1.5 * np.percentile(diff, 99)
