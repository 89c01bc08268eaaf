from pathlib import Path

import numpy as np
import pytest

from lgi.evaluation.accuracy import format_table
from lgi.evaluation.baselines import BlendshapeSolver, RBFSolver, SmoothSolver
from lgi.evaluation.render import heatmap_row


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


def test_benchmark_table_and_heatmap(tmp_path: Path) -> None:
    from lgi.evaluation.accuracy import build_set_index, methods_for, run_set
    from lgi.evaluation.benchsets import synthetic_set

    bs = synthetic_set(frames=8, n_vertices=3000)
    index = build_set_index(bs)
    table, maps = run_set(bs, methods_for(bs, index, noisy=False))
    assert list(table.method) == ["LGI (default)", "LGI simplex (paper)", "blendshape fit", "blendshape fit + rig",
                                  "RBF weights + smooth", "smooth (shell) + rig"]
    assert {"rms_mm", "p95_mm", "max_mm", "lips_rms_mm", "bundle_residual_mm", "frames_per_s",
            "rms_vs_best_baseline"} <= set(table.columns)
    by = table.set_index("method")
    # Interpolating methods pass through clean bundles; the fits do not.
    assert by.loc["LGI (default)", "bundle_residual_mm"] < 1e-4
    assert by.loc["smooth (shell) + rig", "bundle_residual_mm"] < 1e-4
    assert by.loc["blendshape fit", "bundle_residual_mm"] > 1e-3
    assert "| LGI (default) |" in format_table(table)
    png = heatmap_row(tmp_path / "h.png", bs.dataset.neutral, bs.triangles, maps)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
