import json
from pathlib import Path

import numpy as np

from lgi.dataset.importing import load_vertex_indices, read_shape_folder, stabilise_raw
from lgi.dataset.stabilise import find_rigid_vertices, random_rigid, rigid_fit, stabilise
from lgi.synthetic import actor as synth


def _apply(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    return x @ m[:3, :3].T + m[:3, 3]


def test_rigid_fit_ignores_outliers() -> None:
    rng = np.random.default_rng(3)
    src = rng.normal(size=(400, 3)) * 5
    m = random_rigid(rng, 20, 5)
    dst = _apply(m, src)
    dst[:60] += rng.normal(size=(60, 3)) * 2  # 15 % of points move non-rigidly
    fit = rigid_fit(src, dst)
    np.testing.assert_allclose(fit.matrix(), m, atol=1e-9)
    assert (fit.weights[:60] == 0).mean() > 0.9
    plain = rigid_fit(src, dst, robust=False)
    assert np.abs(plain.matrix() - m).max() > 1e-3  # the non-robust fit is biased


def test_stabilise_synthetic_with_auto_rigid_vertices(small_actor: synth.SyntheticActor) -> None:
    rng = np.random.default_rng(0)
    names, acts = synth.default_dataset_activations()
    truth = small_actor.evaluate_many(acts[:12]).astype(np.float64)
    moved = np.stack([_apply(random_rigid(rng, 20, 5), s) for s in truth])
    idx = find_rigid_vertices(small_actor.neutral, moved, fraction=0.1)
    deltas, transforms, rms = stabilise(small_actor.neutral, moved, idx)
    err = np.abs(deltas + small_actor.neutral - truth).max()
    assert err < 1e-4, err


def test_ict_rigid_motions_removed(ict_dir: Path) -> None:
    """Random rigid motions (<= 20 deg, 5 cm) on ICT shapes are removed to 1e-4 cm RMS on the rigid
    vertices, and the expression displacements are kept."""
    raw = read_shape_folder(ict_dir, show_progress=False)
    assert len(raw.names) == 57
    rigid = load_vertex_indices(ict_dir / "vertex_indices.json", raw.mesh.n_vertices)
    clean = raw.positions.copy()
    rng = np.random.default_rng(7)
    motions = np.stack([random_rigid(rng, 20, 5) for _ in range(len(clean))])
    raw.positions = np.stack([_apply(m, s) for m, s in zip(motions, clean, strict=True)])
    deltas, transforms, info = stabilise_raw(raw, ict_dir / "vertex_indices.json")
    stab = raw.neutral + deltas.astype(np.float64)
    rms_rigid = np.sqrt(((stab[:, rigid] - clean[:, rigid]) ** 2).sum(-1).mean(1))
    assert rms_rigid.max() < 1e-4, rms_rigid.max()
    expr = clean - raw.neutral
    moving = np.linalg.norm(expr, axis=2) > 0.05
    err = np.linalg.norm(deltas - expr, axis=2)
    assert err[moving].max() < 1e-4  # cm; measured 1.6e-5 (float32 storage of ~20 cm coordinates)
    assert np.abs(transforms - motions).max() < 1e-4
    assert info["count"] == len(json.loads((ict_dir / "vertex_indices.json").read_text())["idx_to_rigid_verts"])


def test_ict_auto_rigid_vertices_match_the_skull(ict_dir: Path) -> None:
    raw = read_shape_folder(ict_dir, include="jaw*,mouth*", show_progress=False)
    rng = np.random.default_rng(1)
    clean = raw.positions.copy()
    raw.positions = np.stack([_apply(random_rigid(rng, 20, 5), s) for s in clean])
    deltas, _, info = stabilise_raw(raw, "auto")
    err = np.abs(raw.neutral + deltas - clean).max()
    assert err < 1e-4, err
