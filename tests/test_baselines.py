from pathlib import Path

import numpy as np
import pytest

from lgi import synth
from lgi.baselines import BlendshapeSolver, RBFSolver, SmoothSolver
from lgi.bench import format_table, run_methods
from lgi.render import heatmap_row


@pytest.fixture(scope="module")
def setup(small_index):
    return small_index[:4]


def test_smooth_interpolates_bundles_and_keeps_translations(setup) -> None:
    a, ds, layout, _ = setup
    s = SmoothSolver(a.neutral, a.triangles, layout)
    p = layout.evaluate(ds.shape(ds.index("smile_L")))
    r = s.solve_frame(p)
    assert np.nanmax(r.residual) < 1e-7
    t = np.array([0.1, -0.2, 0.3])
    moved = s.solve_frame(layout.evaluate(a.neutral) + t).vertices - a.neutral
    assert np.abs(moved - t).max() < 1e-3  # a rigid shift is reproduced (up to the tiny decay term)


def test_blendshape_fit_recovers_a_dataset_shape(setup) -> None:
    a, ds, layout, _ = setup
    b = BlendshapeSolver(ds, layout)
    k = ds.index("jaw_open+pucker")
    r = b.solve_frame(layout.evaluate(ds.shape(k)))
    assert r.weights.min() >= 0 and r.weights.max() <= 1
    assert np.linalg.norm(r.vertices - ds.shape(k), axis=1).max() < 0.05  # cm
    reg = BlendshapeSolver(ds, layout, l2=1.0).solve_frame(layout.evaluate(ds.shape(k)))
    assert np.sum(reg.weights**2) < np.sum(r.weights**2)  # L2 shrinks the squared weights (and spreads them)


def test_rbf_passes_through_bundles_and_reproduces_shapes(setup) -> None:
    a, ds, layout, index = setup
    rbf = RBFSolver(index)
    k = ds.index("brow_raise_L")
    r = rbf.solve_frame(layout.evaluate(ds.shape(k)))
    assert np.nanmax(r.residual) < 1e-5
    assert np.linalg.norm(r.vertices - ds.shape(k), axis=1).max() < 1e-3


def test_benchmark_table_and_heatmap(setup, tmp_path: Path) -> None:
    a, ds, layout, index = setup
    truth = a.evaluate_many(synth.random_performance(6, seed=2)).astype(np.float64)
    b = layout.evaluate(truth)
    methods = [SmoothSolver(a.neutral, a.triangles, layout), BlendshapeSolver(ds, layout)]
    table, maps = run_methods(methods, truth, b, a.triangles, noisy=b + 0.01)
    assert list(table.method) == ["smooth (shell)", "blendshape fit"]
    assert {"rms_mm", "p95_mm", "max_mm", "bundle_residual_mm", "normal_deg", "jitter_mm2", "frames_per_s"} <= set(
        table.columns)
    assert table.bundle_residual_mm.iloc[0] < 1e-5 < table.bundle_residual_mm.iloc[1]
    assert "| smooth (shell) |" in format_table(table)
    png = heatmap_row(tmp_path / "h.png", a.neutral, a.triangles, maps)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
