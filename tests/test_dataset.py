from pathlib import Path

import numpy as np
import pytest

from lgi.dataset.shapes import ShapeDataset, read_content_hash
from lgi.errors import InputError
from lgi.synthetic import actor as synth


def _ds(actor: synth.SyntheticActor) -> ShapeDataset:
    names, acts = synth.default_dataset_activations()
    return synth.make_dataset(actor, names[:6], acts[:6])


def test_save_load_roundtrip_and_hash(tmp_path: Path, small_actor: synth.SyntheticActor) -> None:
    ds = _ds(small_actor)
    ds.save(tmp_path / "d")
    back = ShapeDataset.load(tmp_path / "d", verify=True)
    assert back.names == ds.names and back.units == "cm"
    assert back.deltas.dtype == np.float32
    np.testing.assert_array_equal(back.deltas, ds.deltas)
    np.testing.assert_array_equal(back.face_offsets, ds.face_offsets)
    assert back.shape_meta[0].extra == ds.shape_meta[0].extra
    assert back.content_hash() == ds.content_hash() == read_content_hash(tmp_path / "d")
    mm = ShapeDataset.load(tmp_path / "d", mmap=True)
    assert isinstance(mm.deltas, np.memmap)


def test_hash_changes_with_content(small_actor: synth.SyntheticActor) -> None:
    ds = _ds(small_actor)
    h = ds.content_hash()
    d2 = ds.take(range(ds.n_shapes))
    d2.deltas = d2.deltas.copy()
    d2.deltas[0, 0, 0] += 1e-3
    assert d2.content_hash() != h
    d3 = ds.take(range(ds.n_shapes))
    d3.units = "mm"
    assert d3.content_hash() != h


def test_select_patterns(small_actor: synth.SyntheticActor) -> None:
    ds = _ds(small_actor)
    sel = ds.select(include="jaw_*", exclude="*_50")
    assert sel.names == ["jaw_open", "jaw_left", "jaw_right"]
    np.testing.assert_array_equal(sel.deltas[0], ds.deltas[ds.index("jaw_open")])


def test_corrupt_dataset_is_detected(tmp_path: Path, small_actor: synth.SyntheticActor) -> None:
    ds = _ds(small_actor)
    ds.save(tmp_path / "d")
    d = np.load(tmp_path / "d" / "deltas.npy")
    d[1, 2, 0] += 0.5
    np.save(tmp_path / "d" / "deltas.npy", d)
    with pytest.raises(InputError, match="content hash"):
        ShapeDataset.load(tmp_path / "d", verify=True)
    with pytest.raises(InputError, match="manifest.json"):
        ShapeDataset.load(tmp_path)
