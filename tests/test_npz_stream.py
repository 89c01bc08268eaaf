"""The meshes' store for long takes: an npz written block by block and read by frame range."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from lgi.errors import InputError
from lgi.io.npz import NpzWriter, npz_member, save_npz
from lgi.io.stored import ScratchArray, StoredArray


def test_an_npz_written_in_blocks_has_the_bytes_of_one_written_whole(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    v = rng.normal(size=(37, 101, 3)).astype(np.float32)
    arrays = {"vertices": v, "frames": np.arange(37) * 2, "jaw": rng.normal(size=(37, 4)).astype(np.float32)}
    save_npz(tmp_path / "whole.npz", **arrays)
    with NpzWriter(tmp_path / "blocks.npz") as w:
        w.begin("vertices", v.shape, v.dtype)
        for lo in range(0, 37, 10):
            w.write(v[lo:lo + 10])
        w.end()
        w.add("frames", arrays["frames"])
        w.add("jaw", arrays["jaw"])
    assert (tmp_path / "whole.npz").read_bytes() == (tmp_path / "blocks.npz").read_bytes()
    with np.load(tmp_path / "blocks.npz") as z:
        assert np.array_equal(z["vertices"], v)


def test_a_member_is_read_by_frame_range_without_loading_it(tmp_path: Path) -> None:
    v = np.arange(20 * 7 * 3, dtype=np.float32).reshape(20, 7, 3)
    save_npz(tmp_path / "m.npz", frames=np.arange(20), vertices=v)
    m = npz_member(tmp_path / "m.npz", "vertices")
    assert isinstance(m, StoredArray) and m.shape == v.shape and len(m) == 20 and m.dtype == np.float32
    assert np.array_equal(m[5:9], v[5:9]) and np.array_equal(m[-1], v[-1]) and np.array_equal(m[3, 2], v[3, 2])
    assert np.array_equal(m[1:19:4], v[1:19:4]) and np.array_equal(m[[0, 1, 2, 9, 4]], v[[0, 1, 2, 9, 4]])
    assert np.array_equal(m[np.arange(20) % 3 == 0], v[::3]) and np.array_equal(m[2:6, :, 1], v[2:6, :, 1])
    assert np.array_equal(np.asarray(m), v) and np.array_equal(np.stack(list(m)), v)
    assert m[7:7].shape == (0, 7, 3) and m[15:40].shape == (5, 7, 3)
    with pytest.raises(IndexError):
        m[20]
    assert np.array_equal(npz_member(tmp_path / "m.npz", "frames"), np.arange(20))
    with pytest.raises(InputError, match="no array 'jaw'"):
        npz_member(tmp_path / "m.npz", "jaw")


def test_a_scratch_array_gives_back_what_was_written_and_leaves_no_file(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    v = rng.normal(size=(50, 4, 3))
    v[7] = np.nan
    s = ScratchArray.of(v, dir=tmp_path)
    assert s.shape == v.shape and s.dtype == np.float64 and list(tmp_path.iterdir()) == []
    assert np.array_equal(np.asarray(s), v, equal_nan=True) and np.array_equal(s[10:13, 1], v[10:13, 1])
    s.write(3, v[:2] * 2)
    assert np.array_equal(s[3:5], v[:2] * 2) and np.array_equal(s[5], v[5])
    with pytest.raises(ValueError, match="do not fit"):
        s.write(49, v[:2])


def test_a_cut_or_foreign_archive_is_refused_with_its_name(tmp_path: Path) -> None:
    v = np.ones((50, 9, 3), np.float32)
    save_npz(tmp_path / "m.npz", vertices=v)
    cut = tmp_path / "cut.npz"
    data = (tmp_path / "m.npz").read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as err:
        npz_member(cut, "vertices")
    assert err.value.path == str(cut)
    packed = tmp_path / "packed.npz"
    np.savez_compressed(packed, vertices=v)
    with pytest.raises(InputError, match="compressed"):
        npz_member(packed, "vertices")
    with zipfile.ZipFile(tmp_path / "short.npz", "w") as zf:  # an entry shorter than its header says
        zf.writestr("vertices.npy", data[data.index(b"\x93NUMPY"):][:200])
    with pytest.raises(InputError, match="truncated"):
        npz_member(tmp_path / "short.npz", "vertices")
    m = npz_member(tmp_path / "m.npz", "vertices")
    with open(tmp_path / "m.npz", "r+b") as fp:  # cut while a reader holds it
        fp.truncate(len(data) // 2)
    assert m[:3].shape == (3, 9, 3)
    with pytest.raises(InputError, match="rows 30:50 .* past the file's end") as err:
        m[30:]
    assert err.value.path == str(tmp_path / "m.npz")


def test_a_block_that_does_not_fit_is_refused(tmp_path: Path) -> None:
    with NpzWriter(tmp_path / "x.npz") as w:
        w.begin("vertices", (4, 2, 3), np.float32)
        w.write(np.zeros((3, 2, 3)))
        with pytest.raises(ValueError, match="do not fit"):
            w.write(np.zeros((2, 2, 3)))
        with pytest.raises(ValueError, match="3 of its 4 rows"):
            w.end()
        w.abort()


def test_readers_read_lgis_meshes_by_range_and_load_anyone_elses(tmp_path: Path) -> None:
    from lgi.io.arrays import nonfinite_frames
    from lgi.io.npz import load_meshes

    v = np.zeros((300, 5, 3), np.float32)
    v[[7, 250], 2, 1] = np.nan
    v[130, 0, 0] = np.inf
    save_npz(tmp_path / "ours.npz", vertices=v, frames=np.arange(300))
    np.savez_compressed(tmp_path / "theirs.npz", vertices=v, frames=np.arange(300))
    ours, theirs = load_meshes(tmp_path / "ours.npz", ("vertices", "frames")), load_meshes(tmp_path / "theirs.npz")
    assert isinstance(ours["vertices"], StoredArray) and isinstance(ours["frames"], np.ndarray)
    assert isinstance(theirs["vertices"], np.ndarray)
    for m in (ours, theirs):
        assert np.array_equal(nonfinite_frames(m["vertices"]), [7, 130, 250])
    with pytest.raises(InputError, match="missing arrays \\['jaw'\\]"):
        load_meshes(tmp_path / "ours.npz", ("vertices", "jaw"))


def test_a_table_appended_in_parts_is_the_table_written_whole(tmp_path: Path) -> None:
    import pandas as pd

    from lgi.io.csvio import CsvAppender, write_csv

    t = pd.DataFrame({"frame": np.repeat(np.arange(5), 3), "marker": ["a", "b,c", 'd"e'] * 5,
                      "x": np.linspace(0, 1, 15), "far_share": [np.nan] * 7 + list(np.linspace(0, 1, 8))})
    write_csv(t, tmp_path / "whole.csv")
    out = CsvAppender(tmp_path / "parts.csv")
    for lo in range(0, 15, 6):
        out.append(t.iloc[lo:lo + 6])
    out.close()
    assert (tmp_path / "whole.csv").read_bytes() == (tmp_path / "parts.csv").read_bytes()
