from pathlib import Path

import numpy as np
import pytest

from lgi.capture.bundles import Bundles, read_bundles, write_bundles
from lgi.errors import InputError

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
