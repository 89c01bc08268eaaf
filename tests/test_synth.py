import numpy as np

from lgi.dataset.mesh import triangle_areas
from lgi.synthetic import actor as synth


def test_default_actor_size_uvs_and_determinism() -> None:
    a = synth.make_actor()
    b = synth.make_actor()
    assert a.n_vertices >= 20000
    np.testing.assert_array_equal(a.neutral, b.neutral)
    assert a.uvs.min() >= 0 and a.uvs.max() <= 1
    assert triangle_areas(a.neutral, a.triangles).min() > 1e-4
    acts = synth.random_performance(50, seed=3)
    np.testing.assert_array_equal(acts, synth.random_performance(50, seed=3))
    assert not np.array_equal(acts, synth.random_performance(50, seed=4))


def test_mouth_opens_and_jaw_rotates(small_actor: synth.SyntheticActor) -> None:
    a = small_actor
    x = a.evaluate(np.eye(len(synth.CONTROLS))[synth.C["jaw_open"]])
    dup = np.flatnonzero(a.lower_lip & (np.abs(a.neutral[:, 1] - synth.MOUTH_Y) < 1e-9))
    assert dup.size > 5
    gap = np.linalg.norm(x[dup] - a.neutral[dup], axis=1)
    assert gap.min() > 1.0  # cm: the lower lip leaves the upper one
    chin = np.argmin(np.linalg.norm(a.neutral - [0, -8.0, 5.0], axis=1))
    r, t = synth.jaw_transform(a.jaw_parameters(np.eye(len(synth.CONTROLS))[synth.C["jaw_open"]]))
    np.testing.assert_allclose(x[chin], r @ a.neutral[chin] + t, atol=1e-6)  # rigid with the jaw there


def test_truth_is_not_a_linear_blend(small_actor: synth.SyntheticActor) -> None:
    e = np.eye(len(synth.CONTROLS))
    combos = np.array([e[synth.C["jaw_open"]] + e[synth.C["smile_L"]],
                       e[synth.C["jaw_open"]] * 0.5,
                       e[synth.C["smile_L"]] + e[synth.C["sneer_L"]]])
    nl = synth.nonlinearity(small_actor, combos)
    assert nl[:, 1].min() > 2.0  # mm, max per expression
    assert nl[0, 1] > 3.0
    # A single extreme is reproduced exactly by its own blend weight.
    single = synth.nonlinearity(small_actor, e[[synth.C["smile_L"]]])
    assert single[0, 1] < 1e-9


def test_performance_is_smooth_and_bounded() -> None:
    acts = synth.random_performance(300, seed=0)
    assert acts.min() >= 0 and acts.max() <= 1
    assert np.abs(np.diff(acts, axis=0)).max() < 0.15  # no jumps between frames at 30 fps
    assert acts[:, synth.C["jaw_open"]].max() > 0.3


def test_dataset_records_activations_and_jaw(small_actor: synth.SyntheticActor) -> None:
    ds = synth.make_dataset(small_actor)
    i = ds.index("jaw_open+smile_L")
    assert ds.shape_meta[i].extra["activations"] == {"jaw_open": 1.0, "smile_L": 1.0}
    assert ds.shape_meta[i].extra["jaw"][0] == synth.JAW_OPEN_DEG
    assert "combination" in ds.shape_meta[i].tags
