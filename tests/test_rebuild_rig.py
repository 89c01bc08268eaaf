"""The jaw-rig fit as a cached stage of the rebuild flow: the same rig as ``lgi rig``, used for the index,
published as ``rig/``, reused on a re-run."""

from __future__ import annotations

import filecmp
from pathlib import Path

import numpy as np
import pytest

from lgi.cli import main


@pytest.mark.slow  # 42 s: two rebuilds
def test_rebuild_fits_the_jaw_rig_as_a_cached_stage(prefect_harness, tmp_path: Path, obj_folder: Path,
                                                     small_actor, layout_csv: Path) -> None:
    from flows.rebuild_dataset import rebuild_dataset

    markers = layout_csv
    jaw = tmp_path / "jaw.txt"
    np.savetxt(jaw, np.flatnonzero(small_actor.jaw_weights > 0.999), fmt="%d")
    rig = {"jaw_vertices": str(jaw), "shapes": "jaw*"}
    s = rebuild_dataset(str(obj_folder), str(tmp_path / "out"), markers=str(markers), rig=rig)
    assert s["stages"]["rig"] is False and s["rig"]["n_shapes"] == 1
    out = tmp_path / "out"
    # The command line's rig from the same dataset, byte for byte.
    assert main(["rig", str(out / "dataset"), "--jaw-vertices", str(jaw), "--shapes", "jaw*", "--out",
                 str(tmp_path / "cli_rig.npz")]) == 0
    assert filecmp.cmp(out / "rig" / "jaw_rig.npz", tmp_path / "cli_rig.npz", shallow=False)
    index = np.load(out / "index" / "index.npz")
    assert "jaw_pivot" in index.files
    again = rebuild_dataset(str(obj_folder), str(out), markers=str(markers), rig=rig)
    assert all(again["stages"].values()), again["stages"]
