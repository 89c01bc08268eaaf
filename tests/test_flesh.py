"""The volumetric flesh model behind simulated in-betweens."""

import numpy as np
import pytest

from lgi.augment.combinations import Blender, compatible, pick_combinations
from lgi.augment.flesh import FleshModel, prism_tets
from lgi.synthetic import actor as synth


def test_prism_tets_conform_and_fill_the_layer() -> None:
    # A flat 6x6 grid of triangles, both diagonal directions, extruded by 1.
    n = 6
    g = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    tris = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = g[i, j], g[i, j + 1], g[i + 1, j + 1], g[i + 1, j]
            tris += [[a, b, c], [a, c, d]] if (i + j) % 2 else [[a, b, d], [b, c, d]]
    tris = np.array(tris)
    V = (n + 1) ** 2
    xy = np.column_stack([np.indices((n + 1, n + 1))[1].ravel(), np.indices((n + 1, n + 1))[0].ravel()])
    pts = np.vstack([np.column_stack([xy, np.ones(V)]), np.column_stack([xy, np.zeros(V)])]).astype(float)
    tets = prism_tets(tris, V)
    vol = np.abs(np.linalg.det(np.transpose(pts[tets[:, 1:]] - pts[tets[:, :1]], (0, 2, 1)))) / 6
    assert vol.min() > 1e-9 and np.isclose(vol.sum(), n * n)
    # Conforming: every face is shared by two tetrahedra or lies on the layer's boundary.
    faces = np.sort(np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]]),
                    axis=1)
    _, count = np.unique(faces, axis=0, return_counts=True)
    boundary_faces = 2 * len(tris) + 2 * 4 * n  # top and bottom triangles, two per side quad
    assert count.max() == 2 and (count == 1).sum() == boundary_faces


@pytest.fixture(scope="module")
def actor_model():
    actor = synth.make_actor(5000)
    ds = synth.make_dataset(actor)
    rig = synth.jaw_rig(actor)
    blender = Blender(ds, rig)
    model = FleshModel(ds.neutral, ds.triangles, blender.deltas, rig=rig, shape_jaw=blender.params)
    return ds, blender, model


def test_rest_is_an_equilibrium(actor_model) -> None:
    ds, _, model = actor_model
    r = model.solve(ds.neutral, np.zeros(4))
    assert np.abs(r.positions - ds.neutral).max() < 1e-6 and abs(r.volume_change) < 1e-9


@pytest.mark.slow  # 26 s; the default suite keeps test_cli.py::test_augment_linear's volume check of simulated shapes
def test_simulated_in_betweens_keep_volume_where_linear_blends_do_not(actor_model) -> None:
    ds, blender, model = actor_model
    picks = pick_combinations(ds.names, 4, levels=(0.5, 1.0), seed=3)
    lin, sim = [], []
    for combo in picks:
        target, jaw = blender.target(combo)
        sim.append(model.solve(target, jaw).volume_change)
        lin.append(model.solve(target, jaw, hard_skin=True).volume_change)
    lin, sim = np.abs(lin), np.abs(sim)
    assert sim.max() < 0.02 and lin.max() > 0.03 and np.all(sim <= lin + 1e-3)


def test_lips_do_not_pass_through_each_other(actor_model) -> None:
    ds, blender, model = actor_model
    lower, upper = model.lip_pairs[:, 0], model.lip_pairs[:, 1]
    assert len(lower) > 20
    # Push the lower lip 2 mm up through the upper lip.
    target = ds.neutral.copy()
    target[model.verts[lower]] += 0.2 * model.up
    before = (target[model.verts[lower]] - target[model.verts[upper]]) @ model.up
    r = model.solve(target, np.zeros(4))
    after = (r.positions[model.verts[lower]] - r.positions[model.verts[upper]]) @ model.up
    assert before.max() > 0.15 and after.max() < 1e-6 and r.contacts > 0


def test_combination_rules() -> None:
    assert not compatible(["jaw_open+pucker", "jaw_open_50+smile_R"])  # the jaw twice
    assert not compatible(["jawLeft", "jawRight"]) and not compatible(["mouthClose", "mouthSmile_L"])
    assert compatible(["jawOpen", "mouthClose"]) and compatible(["smile_L", "sneer_R"])
