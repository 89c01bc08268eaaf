from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import lgi.capture.bundles as bundles_module
from lgi.capture.bundles import COV_COLUMNS, Bundles, read_bundles, write_bundles
from lgi.errors import InputError
from lgi.io.stored import ScratchArray

HEAD = "frame,marker,x,y,z\n"


@pytest.mark.parametrize("ext", [".csv", ".parquet"])
def test_roundtrip_with_missing(tmp_path: Path, ext: str) -> None:
    pos = np.arange(3 * 4 * 3, dtype=float).reshape(3, 4, 3) / 7
    pos[1, 2] = np.nan
    b = Bundles(frames=np.array([0, 1, 5]), markers=["a", "b", "c", "d"], positions=pos)
    write_bundles(tmp_path / f"b{ext}", b)
    back = read_bundles(tmp_path / f"b{ext}", ["a", "b", "c", "d", "e"])
    assert back.frames.tolist() == [0, 1, 5]
    np.testing.assert_allclose(back.positions[:, :4], pos, rtol=1e-8)
    assert np.isnan(back.positions[:, 4]).all() and not back.seen[1, 2]


def test_nan_row_means_not_seen(tmp_path: Path) -> None:
    (tmp_path / "b.csv").write_text(HEAD + "0,a,1,2,3\n0,b,,,\n1,b,nan,nan,nan\n1,a,1,2,3\n")
    b = read_bundles(tmp_path / "b.csv", ["a", "b"])
    assert b.seen.tolist() == [[True, False], [True, False]]


@pytest.mark.parametrize(
    "rows, frame, marker, words",
    [
        ("0,a,1,2,3\n3,zz,1,2,3\n", 3, "zz", "unknown marker"),
        ("0,a,1,2,3\n2,b,1,2,3\n2,b,1,2,4\n", 2, "b", "duplicate"),
        ("0,a,1,2,3\n4,b,1,oops,3\n", 4, "b", "non-numeric y"),
        ("0,a,1,2,3\n7,a,1,inf,3\n", 7, "a", "non-finite"),
        ("0,a,1,2,3\n6,b,1,,3\n", 6, "b", "some coordinates missing"),
    ],
)
def test_bad_rows_name_frame_and_marker(tmp_path: Path, rows: str, frame: int, marker: str, words: str) -> None:
    (tmp_path / "b.csv").write_text(HEAD + rows)
    with pytest.raises(InputError, match=words) as e:
        read_bundles(tmp_path / "b.csv", ["a", "b"])
    assert e.value.frame == frame and e.value.marker == marker
    assert f"frame {frame}" in str(e.value) and repr(marker) in str(e.value)


def test_bad_frame_and_columns(tmp_path: Path) -> None:
    (tmp_path / "b.csv").write_text(HEAD + "0,a,1,2,3\n1.5,a,1,2,3\n")
    with pytest.raises(InputError, match="not an integer") as e:
        read_bundles(tmp_path / "b.csv", ["a"])
    assert e.value.line == 3 and e.value.marker == "a"
    (tmp_path / "c.csv").write_text("frame,marker,x,y\n0,a,1,2\n")
    with pytest.raises(InputError, match="missing columns"):
        read_bundles(tmp_path / "c.csv", ["a"])


# --- reading in batches ---------------------------------------------------------------------------------------------

MARKERS = ["a", "b", "c", "d", "e"]


def _take(rng: np.random.Generator, uncertainty: str | None) -> tuple[pd.DataFrame, Bundles]:
    """A 12-frame take of five markers as bundles rows (some markers missing, some given as empty rows, values exact
    in any float format) and the Bundles they are."""
    frames = np.array([0, 1, 2, 3, 5, 8, 9, 10, 11, 13, 20, 21])
    pos = rng.integers(-800, 800, (len(frames), len(MARKERS), 3)) / 8
    pos[rng.random(pos.shape[:2]) < 0.2] = np.nan
    f, m = np.nonzero(rng.random(pos.shape[:2]) < 0.9)  # the other seen-or-not cells have no row
    df = pd.DataFrame({"frame": frames[f], "marker": np.array(MARKERS)[m], "x": pos[f, m, 0], "y": pos[f, m, 1],
                       "z": pos[f, m, 2]})
    expect = np.full_like(pos, np.nan)
    expect[f, m] = pos[f, m]
    seen = ~np.isnan(expect[..., 0])
    cov = None
    if uncertainty == "sigma":
        sigma = np.where(seen & (rng.random(seen.shape) < 0.7), rng.integers(0, 9, seen.shape) / 16, np.nan)
        df["sigma"] = sigma[f, m]
        cov = sigma[..., None, None] ** 2 * np.eye(3)
    elif uncertainty == "cov":
        A = rng.integers(-4, 5, (*seen.shape, 3, 3)) / 4
        cov = A @ np.swapaxes(A, -1, -2)
        cov[~seen | (rng.random(seen.shape) < 0.3)] = np.nan
        for name, (i, j) in zip(COV_COLUMNS, bundles_module._COV_INDEX, strict=True):
            df[name] = cov[f, m, i, j]
    return df, Bundles(frames=frames, markers=MARKERS, positions=expect, covariance=cov)


def _write(df: pd.DataFrame, path: Path) -> None:
    if path.suffix == ".parquet":
        df.to_parquet(path, index=False)
    else:
        df.to_csv(path, index=False)


def _count_batches(monkeypatch) -> list[int]:
    """The first row (in the file) of each batch the reader checks, as it reads them."""
    bases: list[int] = []
    checked = bundles_module._batch_rows

    def spy(batch, *args):
        bases.append(batch.base)
        return checked(batch, *args)

    monkeypatch.setattr(bundles_module, "_batch_rows", spy)
    return bases


@pytest.mark.parametrize("ext", [".csv", ".parquet"])
@pytest.mark.parametrize("shuffle", [False, True])
@pytest.mark.parametrize("uncertainty", [None, "sigma", "cov"])
def test_batches_read_as_the_whole_file(tmp_path: Path, monkeypatch, ext: str, shuffle: bool,
                                        uncertainty: str | None) -> None:
    """Read in batches of 3 rows (CSV: of 60-byte blocks, some rows longer than a block), in memory or on disk
    (windows of one or two frames): the values written, and those read in one batch."""
    rng = np.random.default_rng(len(ext) + 2 * shuffle + 4 * len(uncertainty or ""))
    df, expect = _take(rng, uncertainty)
    if shuffle:
        df = df.sample(frac=1, random_state=1)
    path = tmp_path / f"b{ext}"
    _write(df, path)
    whole = read_bundles(path, MARKERS)
    monkeypatch.setattr(bundles_module, "BATCH_ROWS", 3)
    monkeypatch.setattr(bundles_module, "CSV_ROW_BYTES", 20)
    monkeypatch.setattr(bundles_module, "WINDOW_BYTES", 2 * len(MARKERS) * 3 * 8)
    bases = _count_batches(monkeypatch)
    for on_disk in (False, True):
        bases.clear()
        b = read_bundles(path, MARKERS, on_disk=on_disk)
        assert len(bases) > 6 and bases == sorted(bases)
        kind = ScratchArray if on_disk else np.ndarray
        assert type(b.positions) is kind and (uncertainty is None) == (b.covariance is None)
        assert b.frames.tolist() == whole.frames.tolist() == expect.frames.tolist() and b.markers == MARKERS
        for got, one, want in ((b.positions, whole.positions, expect.positions),
                               (b.covariance, whole.covariance, expect.covariance)):
            if want is not None:
                assert type(got) is kind
                assert np.array_equal(np.asarray(got), one, equal_nan=True)
                assert np.array_equal(one, want, equal_nan=True)


def test_markers_in_order_of_first_appearance_across_batches(tmp_path: Path, monkeypatch) -> None:
    (tmp_path / "b.csv").write_text(HEAD + "".join(f"{f},{m},1,2,3\n" for f in range(4) for m in "cab"[: f + 1]))
    monkeypatch.setattr(bundles_module, "CSV_ROW_BYTES", 1)  # a batch per line
    b = read_bundles(tmp_path / "b.csv", on_disk=True)
    assert b.markers == ["c", "a", "b"] and b.seen.tolist() == [[1, 0, 0], [1, 1, 0], [1, 1, 1], [1, 1, 1]]


@pytest.mark.parametrize("ext", [".csv", ".parquet"])
@pytest.mark.parametrize("cell, value, words", [("marker", "zz", "unknown marker"), ("x", 5000.0, "beyond 1000 cm"),
                                                ("frame", 2.5, "not an integer")])
def test_error_in_a_later_batch_names_its_line(tmp_path: Path, monkeypatch, ext: str, cell: str, value,
                                               words: str) -> None:
    """A bad row in the third batch: the error gives its line (the header is line 1) or its row in the file."""
    rows = pd.DataFrame({"frame": np.repeat(np.arange(10), 2), "marker": ["a", "b"] * 10, "x": 1.5, "y": 2.5,
                         "z": -3.5})
    # CSV: the other cells written as before (frames as integers); Parquet: a column of the value's type.
    rows = rows.astype({cell: object if ext == ".csv" else type(value)})
    rows.loc[13, cell] = value
    path = tmp_path / f"b{ext}"
    _write(rows, path)
    # Batches of 5 rows; a CSV's lines are 17 bytes ("6,b,1.5,2.5,-3.5"), so blocks of 85 bytes are 5 of them.
    monkeypatch.setattr(bundles_module, "BATCH_ROWS", 5)
    monkeypatch.setattr(bundles_module, "CSV_ROW_BYTES", 17)
    bases = _count_batches(monkeypatch)
    with pytest.raises(InputError, match=words) as e:
        read_bundles(path, ["a", "b"])
    assert bases == [0, 5, 10] and e.value.marker == ("zz" if cell == "marker" else "b")
    if cell != "frame":
        assert e.value.frame == 6
    if ext == ".csv":
        assert e.value.line == 15 and "b.csv:15" in str(e.value)
    else:
        assert "b.parquet (row 13)" in str(e.value)


def test_unparsed_field_in_a_later_batch_reads_the_file_as_text(tmp_path: Path, monkeypatch) -> None:
    (tmp_path / "b.csv").write_text(HEAD + "".join(f"{f},a,1,2,3\n" for f in range(40)).replace("30,a,1,2", "30,a,1,x"))
    monkeypatch.setattr(bundles_module, "BATCH_ROWS", 1)
    with pytest.raises(InputError, match="non-numeric y value 'x'") as e:
        read_bundles(tmp_path / "b.csv", ["a"])
    assert (e.value.line, e.value.frame, e.value.marker) == (32, 30, "a")


@pytest.mark.parametrize("ext", [".csv", ".parquet"])
@pytest.mark.parametrize("on_disk", [False, True])
def test_duplicate_across_batches_names_the_second_row(tmp_path: Path, monkeypatch, ext: str, on_disk: bool) -> None:
    """A (frame, marker) given again batches later is refused at its second row; of several, the first to repeat in
    the file, whichever frame (on disk: window) it is in."""
    rows = pd.DataFrame({"frame": list(range(30)), "marker": "a", "x": 1.0, "y": 2.0, "z": 3.0})
    rows = pd.concat([rows, rows.iloc[[20, 2, 25]]], ignore_index=True)  # rows 30 to 32 repeat 20, 2 and 25
    path = tmp_path / f"b{ext}"
    _write(rows, path)
    monkeypatch.setattr(bundles_module, "BATCH_ROWS", 4)
    monkeypatch.setattr(bundles_module, "WINDOW_BYTES", 2 * 3 * 8)  # a window of one frame (of two markers)
    bases = _count_batches(monkeypatch)
    with pytest.raises(InputError, match="duplicate") as e:
        read_bundles(path, ["a", "b"], on_disk=on_disk)
    assert len(bases) >= 3 and max(b for b in bases if b <= 20) < 30  # rows 20 and 30 in different batches
    assert (e.value.frame, e.value.marker) == (20, "a")
    assert e.value.line == 32 if ext == ".csv" else "b.parquet (row 30)" in str(e.value)
    rows.loc[30, "marker"], rows.loc[31, "frame"], rows.loc[32, "frame"] = "b", 40, 41
    _write(rows, path)
    assert read_bundles(path, ["a", "b"], on_disk=on_disk).seen.sum() == 33
