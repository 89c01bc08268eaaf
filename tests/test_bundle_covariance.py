"""Bundles carry their uncertainty: the bundles file's optional ``sigma`` / ``cov_*`` columns, and the covariance
``lgi track`` computes for each triangulated bundle (calibrated against the synthetic HMC shot's truth)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgi.capture.bundles import COV_COLUMNS, Bundles, read_bundles, write_bundles
from lgi.capture.camera import triangulation_covariance
from lgi.errors import InputError
from lgi.synthetic.hmc import hmc_rig

HEAD = "frame,marker,x,y,z"
COV_HEAD = HEAD + "," + ",".join(COV_COLUMNS) + "\n"


def _random_covariances(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    A = rng.normal(size=(*shape, 3, 3)) * rng.uniform(0.01, 0.2, (*shape, 1, 1))
    return A @ np.swapaxes(A, -1, -2)


@pytest.mark.parametrize("ext", [".csv", ".parquet"])
def test_covariance_round_trips_exactly(tmp_path: Path, ext: str) -> None:
    rng = np.random.default_rng(0)
    pos = rng.uniform(-5, 5, (3, 4, 3))
    pos[1, 2] = np.nan  # not seen: no row
    cov = _random_covariances(rng, (3, 4))
    cov[1, 2] = np.nan
    cov[2, 0] = np.nan  # seen, no uncertainty given: a row with empty cov_* cells
    cov[0, 3] = np.diag([1e-300, 0.0, 2.5])  # rank-deficient and tiny values survive
    b = Bundles(frames=np.array([0, 1, 5]), markers=["a", "b", "c", "d"], positions=pos, covariance=cov)
    path = tmp_path / f"b{ext}"
    write_bundles(path, b)
    back = read_bundles(path, ["a", "b", "c", "d", "e"])
    assert back.covariance is not None and back.covariance.shape == (3, 5, 3, 3)
    assert np.array_equal(back.covariance[:, :4], cov, equal_nan=True)  # bit for bit
    assert np.isnan(back.covariance[:, 4]).all() and np.isnan(back.covariance[2, 0]).all()
    np.testing.assert_allclose(back.positions[:, :4], pos, rtol=1e-8)
    if ext == ".csv":
        rows = pd.read_csv(path, keep_default_na=False, dtype=str)
        assert list(rows.columns) == ["frame", "marker", "x", "y", "z", *COV_COLUMNS]
        assert (rows[(rows.frame == "5") & (rows.marker == "a")][COV_COLUMNS] == "").all(axis=None)
    # Written again from what was read: the same file.
    write_bundles(tmp_path / f"c{ext}", back)
    again = read_bundles(tmp_path / f"c{ext}", ["a", "b", "c", "d", "e"])
    assert np.array_equal(again.covariance, back.covariance, equal_nan=True)


@pytest.mark.parametrize("ext", [".csv", ".parquet"])
def test_no_uncertainty_columns_no_covariance(tmp_path: Path, ext: str) -> None:
    b = Bundles(frames=np.array([0]), markers=["a"], positions=np.ones((1, 1, 3)))
    write_bundles(tmp_path / f"b{ext}", b)
    assert read_bundles(tmp_path / f"b{ext}").covariance is None
    if ext == ".csv":
        assert (tmp_path / "b.csv").read_text().splitlines()[0] == HEAD


def test_sigma_is_isotropic(tmp_path: Path) -> None:
    (tmp_path / "b.csv").write_text(HEAD + ",sigma\n0,a,1,2,3,0.02\n0,b,1,2,3,\n1,a,1,2,3,0\n1,b,,,,\n")
    b = read_bundles(tmp_path / "b.csv", ["a", "b"])
    np.testing.assert_array_equal(b.covariance[0, 0], 0.02**2 * np.eye(3))
    np.testing.assert_array_equal(b.covariance[1, 0], np.zeros((3, 3)))
    assert np.isnan(b.covariance[:, 1]).all()  # no value given / not seen
    # The text path (a field pyarrow cannot parse elsewhere) reads the same values.
    (tmp_path / "c.csv").write_text(HEAD + ",sigma,note\n0,a,1,2,3,0.02,x\n0,b,1,2,3,,\"y, z\"\n1,a,1,2,3,0,\n")
    c = read_bundles(tmp_path / "c.csv", ["a", "b"])
    np.testing.assert_array_equal(c.covariance[0, 0], 0.02**2 * np.eye(3))


GOOD_COV = "0.04,0.01,0,0.09,0,0.01"


@pytest.mark.parametrize(
    "head, rows, line, frame, marker, words",
    [
        ("sigma", "0,a,1,2,3,0.1\n3,b,1,2,3,oops\n", 3, 3, "b", "non-numeric sigma value 'oops'"),
        ("sigma", "0,a,1,2,3,0.1\n4,b,1,2,3,-0.1\n", 3, 4, "b", "negative sigma"),
        ("sigma", "0,a,1,2,3,0.1\n5,a,1,2,3,inf\n", 3, 5, "a", "non-finite uncertainty"),
        ("sigma", "0,a,1,2,3,0.1\n6,b,,,,0.1\n", 3, 6, "b", "without a position"),
        ("cov", f"0,a,1,2,3,{GOOD_COV}\n7,b,1,2,3,1,2,0,1,0,1\n", 3, 7, "b", "not positive semi-definite"),
        ("cov", f"0,a,1,2,3,{GOOD_COV}\n8,b,1,2,3,-1,0,0,1,0,1\n", 3, 8, "b", "not positive semi-definite"),
        ("cov", f"0,a,1,2,3,{GOOD_COV}\n2,a,1,2,3,0.04,0.01,,0.09,0,0.01\n", 3, 2, "a", "some covariance entries"),
        ("cov", f"0,a,1,2,3,{GOOD_COV}\n9,b,1,2,3,0.04,x,0,0.09,0,0.01\n", 3, 9, "b", "non-numeric cov_xy"),
        ("cov", f"0,a,1,2,3,{GOOD_COV}\n1,a,,,,{GOOD_COV}\n", 3, 1, "a", "without a position"),
        ("cov", f"0,a,1,2,3,{GOOD_COV}\n1,b,1,2,3,0.04,0.01,0,nan,0,-inf\n", 3, 1, "b", "some covariance entries"),
        ("cov", f"0,a,1,2,3,{GOOD_COV}\n1,b,1,2,3,0.04,0.01,0,0.09,0,inf\n", 3, 1, "b", "non-finite uncertainty"),
    ],
)
def test_bad_uncertainty_names_line_frame_and_marker(tmp_path: Path, head: str, rows: str, line: int, frame: int,
                                                      marker: str, words: str) -> None:
    text = (HEAD + ",sigma\n" if head == "sigma" else COV_HEAD) + rows
    (tmp_path / "b.csv").write_text(text)
    with pytest.raises(InputError, match=words) as e:
        read_bundles(tmp_path / "b.csv", ["a", "b"])
    assert (e.value.line, e.value.frame, e.value.marker) == (line, frame, marker)
    assert f"b.csv:{line}" in str(e.value) and f"frame {frame}" in str(e.value) and repr(marker) in str(e.value)


def test_bad_uncertainty_in_parquet_names_the_row(tmp_path: Path) -> None:
    df = pd.DataFrame({"frame": [0, 4], "marker": ["a", "b"], "x": 1.0, "y": 2.0, "z": 3.0, "sigma": [0.1, -2.0]})
    df.to_parquet(tmp_path / "b.parquet", index=False)
    with pytest.raises(InputError, match="negative sigma") as e:
        read_bundles(tmp_path / "b.parquet", ["a", "b"])
    assert "(row 1)" in str(e.value) and e.value.frame == 4 and e.value.marker == "b"


@pytest.mark.parametrize(
    "columns, words",
    [
        (["sigma", *COV_COLUMNS], "both a 'sigma' column and covariance columns"),
        (COV_COLUMNS[:5], "covariance columns cov_zz missing"),
        (["cov_xx", "cov_yy", "cov_zz"], "cov_xy, cov_xz, cov_yz missing"),
    ],
)
def test_bad_uncertainty_columns_name_the_file(tmp_path: Path, columns: list[str], words: str) -> None:
    (tmp_path / "b.csv").write_text(HEAD + "," + ",".join(columns) + "\n0,a,1,2,3" + ",0.1" * len(columns) + "\n")
    with pytest.raises(InputError, match=words) as e:
        read_bundles(tmp_path / "b.csv", ["a"])
    assert str(e.value).startswith(str(tmp_path / "b.csv"))


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_triangulation_covariance_matches_monte_carlo(model: str) -> None:
    """The first-order covariance is what triangulating noisy pixels gives, its long axis along the rays."""
    rig = hmc_rig(model)
    X = np.array([[0.0, -5.0, 30.0], [45.0, 40.0, 10.0], [-40.0, -70.0, 15.0]])
    C = triangulation_covariance(rig.cameras, X, 0.25)
    rng = np.random.default_rng(1)
    n = 3000
    uv = [np.repeat(c.project(X), n, axis=0) + rng.normal(0, 0.25, (len(X) * n, 2)) for c in rig.cameras]
    Y = rig.triangulate(*uv)[0].reshape(len(X), n, 3)
    for k in range(len(X)):
        emp = np.cov(Y[k].T)
        w, v = np.linalg.eigh(C[k])
        we = np.einsum("ij,jk,ki->i", v.T, emp, v)  # the empirical variance along each predicted axis
        np.testing.assert_allclose(we, w, rtol=0.12)
        ray = X[k] - 0.5 * (rig.cameras[0].center + rig.cameras[1].center)
        assert abs(v[:, 2] @ ray) / np.linalg.norm(ray) > 0.99  # the long axis is the depth
        assert np.sqrt(w[2] / w[1]) > 4
    assert np.isnan(triangulation_covariance(rig.cameras, np.full((1, 2, 3), np.nan), 0.25)).all()


@pytest.fixture(scope="module")
def hmc_cov_shot(tmp_path_factory) -> Path:
    from lgi.cli import main

    out = tmp_path_factory.mktemp("hmc-cov")
    assert main(["synth", "--out", str(out), "--frames", "20", "--vertices", "12000", "--hmc", "--board-views", "3",
                 "-q"]) == 0
    return out


def test_track_covariances_are_calibrated(hmc_cov_shot: Path, tmp_path: Path) -> None:
    """On the synthetic shot (true rig), the triangulated bundles' errors whitened by their covariances have a mean
    squared Mahalanobis distance near 3, the covariance's long axis is the viewing direction, several times the
    short ones; the file holds them in the head frame (cm^2), carried there like the positions."""
    from lgi.capture.camera import StereoRig
    from lgi.jobs.capture import track_shot

    shot = hmc_cov_shot
    out = tmp_path / "tracked.csv"
    st, _ = track_shot(shot / "hmc", shot / "hmc" / "cameras_true.json", shot / "markers.csv", out)
    truth = read_bundles(shot / "bundles.csv")
    true_h = truth.positions[:, [truth.markers.index(m) for m in st.names]] * 10  # mm, head frame
    t2 = np.load(shot / "hmc" / "truth.npz")
    cam0 = StereoRig.from_calibration(json.loads((shot / "hmc" / "cameras_true.json").read_text())["head_frame"]
                                      ).cameras[0]
    true_rig = (np.einsum("fij,fmj->fmi", t2["head_rotation"], true_h) + t2["head_translation"][:, None]) @ cam0.R.T \
        + cam0.t
    C = triangulation_covariance(st.rig.cameras, st.tracks.X, 0.25)
    ok = np.all(np.isfinite(st.tracks.X), axis=2)
    assert ok.mean() > 0.9
    e, c = (st.tracks.X - true_rig)[ok], C[ok]
    d2 = np.einsum("ni,ni->n", e, np.linalg.solve(c, e[..., None])[..., 0])
    assert 2.4 < d2.mean() < 3.8, d2.mean()
    w, v = np.linalg.eigh(c)
    X = st.tracks.X[ok]
    ray = sum((X - cam.center) / np.linalg.norm(X - cam.center, axis=1, keepdims=True) for cam in st.rig.cameras)
    cos = np.abs(np.einsum("ni,ni->n", ray / np.linalg.norm(ray, axis=1, keepdims=True), v[:, :, 2]))
    assert np.percentile(cos, 5) > np.cos(np.radians(3))
    ratio = np.sqrt(w[:, 2] / w[:, 1])
    assert 4 < np.median(ratio) < 9, np.median(ratio)
    # The errors are that much larger along the long axis too.
    along = np.einsum("ni,ni->n", e, v[:, :, 2])
    across = np.einsum("ni,nik->nk", e, v[:, :, :2])
    assert np.std(along) > 4 * np.sqrt(np.mean(across**2))
    # The file: the head-frame covariance, cm^2, NaN exactly where there is no bundle.
    b = read_bundles(out, st.names)
    R = st.head_R
    expect = np.einsum("fji,fmjk,fkl->fmil", R, C, R) / 100
    assert np.array_equal(np.isnan(b.covariance), np.isnan(expect) | np.isnan(b.positions)[..., None])
    np.testing.assert_allclose(np.nan_to_num(b.covariance), np.nan_to_num(expect), rtol=1e-12, atol=0)
    assert np.array_equal(b.covariance, st.head_cov / 100, equal_nan=True)  # written bit for bit


def test_pixel_noise_option() -> None:
    """``lgi track --pixel-noise`` reaches the tracker with the measured default, and must be a positive number."""
    from lgi.capture.settings import PIXEL_NOISE_PX
    from lgi.capture.tracking import TrackOptions
    from lgi.cli import build_parser
    from lgi.jobs.capture import TrackFootageOptions

    base = ["track", "shot", "--calib", "c.json", "--markers", "m.csv", "--out", "b.csv"]
    assert build_parser().parse_args(base).pixel_noise == PIXEL_NOISE_PX == TrackOptions().pixel_noise_px
    assert TrackFootageOptions().pixel_noise == PIXEL_NOISE_PX
    assert build_parser().parse_args([*base, "--pixel-noise", "0.4"]).pixel_noise == 0.4
    for bad in (0, -0.1, float("nan"), True):
        with pytest.raises(InputError, match="--pixel-noise must be a positive number of px"):
            TrackFootageOptions(pixel_noise=bad)
