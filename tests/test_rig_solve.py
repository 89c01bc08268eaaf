"""lgi rig-solve: curves from a mesh the rig made, no lag from the temporal term, robust weights, the USD
animation read back by UsdSkel, clean errors for bad input."""

from pathlib import Path

import numpy as np
import pytest

from lgi.cli import main
from lgi.dataset.shapes import ShapeDataset, ShapeMeta
from lgi.io.npz import load_npz, save_npz
from lgi.synthetic import actor as A

N_VERTICES = 2500
PAIRS = [("smile_L", "smile_R"), ("jaw_open", "pucker"), ("sneer_L", "brow_lower")]


def make_rig(n_vertices: int = N_VERTICES, tags: bool = True) -> ShapeDataset:
    """A rig dataset as lgi rig-generate writes it: the default actor's 13 extremes as controls, its true
    correctives for three pairs."""
    act = A.make_actor(n_vertices)
    eye = np.eye(len(A.CONTROLS))
    x0 = act.neutral
    d = [act.evaluate(eye[k]) - x0 for k in range(len(A.CONTROLS))]
    corr = [act.evaluate(eye[A.C[a]] + eye[A.C[b]]) - x0 - d[A.C[a]] - d[A.C[b]] for a, b in PAIRS]
    meta = [ShapeMeta(source="test", tags=["control"] if tags else []) for _ in A.CONTROLS]
    meta += [ShapeMeta(source="test", tags=["corrective", "combination"], extra={"combination": list(p)})
             for p in PAIRS]
    ds0 = A.make_dataset(act, list(A.CONTROLS), eye)
    return ShapeDataset(neutral=x0, deltas=np.stack(d + corr).astype(np.float32),
                        names=[*A.CONTROLS, *("+".join(p) for p in PAIRS)], face_vertices=ds0.face_vertices,
                        face_offsets=ds0.face_offsets, units="cm", shape_meta=meta)


@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> dict:
    from lgi.export.formats import write_usd_rig
    from lgi.jobs.rig_solve import load_rig

    d = tmp_path_factory.mktemp("rigsolve")
    ds = make_rig()
    ds.save(d / "rig")
    write_usd_rig(d / "rig.usda", ds.neutral, ds.face_vertices, ds.face_offsets, ds.names, ds.deltas,
                  [None] * len(A.CONTROLS) + list(PAIRS))
    return {"dir": d, "ds": ds, "rig": load_rig(d / "rig")[0]}


def write_recon(path: Path, meshes: np.ndarray) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    save_npz(path / "meshes.npz", vertices=np.asarray(meshes, np.float32), frames=np.arange(len(meshes)))
    return path


def curves_of(out: Path, controls: list[str]) -> np.ndarray:
    import pandas as pd

    t = pd.read_csv(out / "curves.csv")
    return t.pivot(index="frame", columns="control", values="value")[controls].to_numpy()


def test_exact_curves_from_a_mesh_the_rig_made(rig) -> None:
    """Weights (with correctives, at bounds and inside) come back to 1e-4 from meshes the rig played."""
    r = rig["rig"]
    rng = np.random.default_rng(3)
    w = rng.uniform(0, 1, (12, r.n_controls))
    w[rng.uniform(size=w.shape) < 0.4] = 0.0
    w[rng.uniform(size=w.shape) < 0.1] = 1.0
    meshes = np.stack([r.evaluate(x) for x in w])
    recon = write_recon(rig["dir"] / "exact", meshes)
    out = rig["dir"] / "exact_out"
    assert main(["rig-solve", str(recon), "--rig", str(rig["dir"] / "rig"), "--out", str(out), "--smooth", "0",
                 "--vertices", "0", "-q"]) == 0
    got = curves_of(out, r.controls)
    assert np.abs(got - w).max() <= 1e-4
    res = np.loadtxt(out / "residuals.csv", delimiter=",", skiprows=1)
    assert res[:, 1].max() < 1e-3 and res[:, 2].max() < 1e-2  # mm (float32 meshes)
    z = load_npz(out / "vertex_error.npz", required=("rms_mm", "max_mm", "region"))
    assert z["rms_mm"].shape == (len(r.neutral),) and z["region"].sum() > 100
    assert (out / "vertex_error.png").stat().st_size > 1000


def test_temporal_term_does_not_lag_a_step_and_calms_holds(rig) -> None:
    """A control stepping 0 -> 0.8 in one frame, others held, with 0.1 mm of noise on every vertex: the smoothed
    curve crosses halfway within a frame of the step (a causal filter crosses late), rises 10-90 % within three
    frames, and the held control's second differences are far below the per-frame fit's."""
    from lgi.retarget.solve import RigSolver, solve_shot, step_lag

    r = rig["rig"]
    n_f, step = 60, 30
    k, held = A.C["smile_L"], A.C["brow_raise_R"]
    w = np.zeros((n_f, r.n_controls))
    w[step:, k] = 0.8
    w[:, held] = 0.4
    rng = np.random.default_rng(0)
    meshes = np.stack([r.evaluate(x) for x in w]) + rng.normal(0, 0.01, (n_f, len(r.neutral), 3))
    solver = RigSolver(r, np.flatnonzero(r.face_region()))
    curves, raw, _ = solve_shot(solver, meshes, smooth_frames=4.0)
    lag = step_lag(curves[:, k], step, 0.0, 0.8)
    assert abs(lag) <= 1.0, lag
    c = curves[:, k]
    assert np.flatnonzero(c >= 0.72)[0] - np.flatnonzero(c >= 0.08)[0] <= 3
    assert np.abs(np.diff(curves[:, held], 2)).mean() < 0.5 * np.abs(np.diff(raw[:, held], 2)).mean()
    # A causal smoother of the same strength would be measured late: the check can fail.
    ema = np.zeros(n_f)
    for f in range(n_f):
        ema[f] = raw[f, k] if f == 0 else 0.7 * ema[f - 1] + 0.3 * raw[f, k]
    assert step_lag(ema, step, 0.0, 0.8) > 1.0


def test_robust_to_a_few_bad_vertices(rig) -> None:
    """Thirty vertices thrown 1 cm off: the Huber fit stays within 0.01 of the weights, plain least squares not."""
    from lgi.retarget.solve import RigSolver

    r = rig["rig"]
    region = np.flatnonzero(r.face_region())
    w = np.zeros(r.n_controls)
    w[A.C["smile_L"]], w[A.C["jaw_open"]] = 0.6, 0.3
    y = r.evaluate(w)[region]
    bad = np.random.default_rng(1).choice(len(region), 30, replace=False)
    y[bad] += np.array([0.0, 0.0, 1.0])
    robust = RigSolver(r, region, robust=3.0).fit_frame(y).weights
    plain = RigSolver(r, region, robust=0.0).fit_frame(y).weights
    assert np.abs(robust - w).max() < 0.01
    assert np.abs(plain - w).max() > np.abs(robust - w).max()


def test_usd_animation_plays_the_curves(rig) -> None:
    """pxr reads the animation back; UsdSkel's own bake gives the rig's playback to 1e-4 cm; UsdValidation
    finds no error."""
    from lgi.export.rig_anim import usd_playback, validate_usd
    from lgi.jobs.rig_solve import playback

    r = rig["rig"]
    t = np.linspace(0, 1, 8)[:, None]
    w = np.clip(np.sin(np.pi * t * (1 + np.arange(r.n_controls)) / 3) * 0.9, 0, 1)
    recon = write_recon(rig["dir"] / "usd", np.stack([r.evaluate(x) for x in w]))
    out, anim = rig["dir"] / "usd_out", rig["dir"] / "anim" / "shot.usda"
    assert main(["rig-solve", str(recon), "--rig", str(rig["dir"] / "rig"), "--out", str(out), "--usd", str(anim),
                 "--rig-usd", str(rig["dir"] / "rig.usda"), "-q"]) == 0
    curves = curves_of(out, r.controls)
    baked = usd_playback(anim, list(range(len(w))))
    assert np.abs(baked - playback(r, curves)).max() <= 1e-4
    assert validate_usd(anim) == []


def test_bad_input_is_a_clean_error(rig, tmp_path, capsys) -> None:
    r = rig["rig"]
    ok = write_recon(tmp_path / "ok", np.stack([r.evaluate(np.zeros(r.n_controls))] * 3))
    rig_dir, rig_usd = str(rig["dir"] / "rig"), str(rig["dir"] / "rig.usda")

    def fails(args: list[str], *words: str) -> None:
        capsys.readouterr()
        assert main(["rig-solve", *args, "-q"]) == 2
        err = capsys.readouterr().err
        assert all(w in err for w in words), err
        assert not (tmp_path / "out").exists()  # nothing written

    # another topology
    other = write_recon(tmp_path / "other", np.zeros((3, len(r.neutral) - 7, 3), np.float32))
    fails([str(other), "--rig", rig_dir, "--out", str(tmp_path / "out")], "meshes.npz", "topology")
    # a rig dataset without control tags
    make_rig(tags=False).save(tmp_path / "untagged")
    fails([str(ok), "--rig", str(tmp_path / "untagged"), "--out", str(tmp_path / "out")], "manifest.json",
          "control")
    # a rig USD of another rig (another face's neutral)
    from lgi.export.formats import write_usd_rig

    ds = rig["ds"]
    write_usd_rig(tmp_path / "wrong.usda", ds.neutral + 0.1, ds.face_vertices, ds.face_offsets, ds.names, ds.deltas,
                  [None] * len(A.CONTROLS) + list(PAIRS))
    fails([str(ok), "--rig", rig_dir, "--out", str(tmp_path / "out"), "--usd", str(tmp_path / "a.usda"),
           "--rig-usd", str(tmp_path / "wrong.usda")], "wrong.usda", "another rig")
    assert not (tmp_path / "a.usda").exists()
    # --usd without the rig's USD; a reconstruction folder without meshes.npz
    fails([str(ok), "--rig", rig_dir, "--out", str(tmp_path / "out"), "--usd", str(tmp_path / "a.usda")],
          "--rig-usd")
    (tmp_path / "empty").mkdir()
    fails([str(tmp_path / "empty"), "--rig", rig_dir, "--out", str(tmp_path / "out")], "meshes.npz")
    assert Path(rig_usd).is_file()
