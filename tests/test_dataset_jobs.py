"""The dataset and index jobs: the plain commands and the rebuild flow take the same options and agree."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgi.cli import main
from lgi.dataset.markers import write_layout
from lgi.dataset.shapes import ShapeDataset
from lgi.errors import InputError
from lgi.io.obj import write_obj
from lgi.synthetic import actor as synth


@pytest.fixture()
def with_identity(obj_folder: Path, small_actor) -> Path:
    """The OBJ folder plus an identity mode (a smooth change of proportions)."""
    a = small_actor
    x = a.neutral * np.array([1.05, 0.97, 1.0])
    write_obj(obj_folder / "identity_wide.obj", x, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs)
    return obj_folder


def test_import_identity_and_augment_same_through_the_flow(prefect_harness, tmp_path: Path, with_identity: Path,
                                                           small_actor) -> None:
    layout, _ = synth.default_layout(small_actor)
    markers = tmp_path / "m.csv"
    write_layout(markers, layout, small_actor.neutral)
    plain = tmp_path / "plain"
    assert main(["import", str(with_identity), "--out", str(plain), "--identity", "identity_wide=0.5", "-q"]) == 0
    aug_args = ["--linear", "--levels", "0.25,0.75", "--orders", "2", "--seed", "5", "--budget", "2",
                "--include", "jaw_open,smile_L"]
    assert main(["augment", str(plain), "--out", str(tmp_path / "plain_aug"), *aug_args]) == 0
    assert main(["verify", str(tmp_path / "idx"), "-q"]) == 2  # no index yet: bad input, not a failed check

    from flows.rebuild_dataset import rebuild_dataset

    s = rebuild_dataset(str(with_identity), str(tmp_path / "flow"), identity="identity_wide=0.5",
                        markers=str(markers), verify_shapes="jaw_open",
                        augmentation={"linear": True, "levels": [0.25, 0.75], "orders": [2], "seed": 5, "budget": 2,
                                      "include": "jaw_open,smile_L"})
    a = ShapeDataset.load(plain, verify=True)
    b = ShapeDataset.load(tmp_path / "flow" / "dataset", verify=True)
    assert a.content_hash() == b.content_hash() and a.info["identity_weights"] == {"identity_wide": 0.5}
    c = ShapeDataset.load(tmp_path / "plain_aug", verify=True)
    d = ShapeDataset.load(tmp_path / "flow" / "dataset_augmented", verify=True)
    assert c.content_hash() == d.content_hash()
    info = d.info["augmented"]
    assert info["levels"] == [0.25, 0.75] and info["orders"] == [2] and info["seed"] == 5
    assert all(set(m.extra["sources"]) <= {"jaw_open", "smile_L"} for m in d.shape_meta[3:])
    table = pd.read_csv(tmp_path / "flow" / "verification" / "verification.csv")
    assert list(table["shape"]) == ["jaw_open"]  # --shapes of lgi verify: verify_shapes
    assert s["verification"]["shapes"] == 1


def test_flow_parameters_checked(prefect_harness, tmp_path: Path, obj_folder: Path) -> None:
    from prefect.exceptions import ParameterTypeError

    from flows.rebuild_dataset import rebuild_dataset

    # Typed parameters: checked by Prefect before the flow run starts (no task runs), the field named.
    with pytest.raises(ParameterTypeError, match="linaer"):
        rebuild_dataset(str(obj_folder), str(tmp_path / "o"), augmentation={"linaer": True})
    with pytest.raises(ParameterTypeError, match="--budget"):
        rebuild_dataset(str(obj_folder), str(tmp_path / "o"), augmentation={"linear": True, "budget": 0})
    assert not (tmp_path / "o").exists()
    with pytest.raises(InputError, match="knn"):
        rebuild_dataset(str(obj_folder), str(tmp_path / "o"), markers="m.csv", index_options={"knn": -3})


def test_import_converts_to_cm(tmp_path: Path, obj_folder: Path) -> None:
    """A dataset in mm is stored in cm, so every figure in mm downstream is right."""
    mm = tmp_path / "mm"
    mm.mkdir()
    from lgi.io.obj import read_obj

    for p in obj_folder.glob("*.obj"):
        m = read_obj(p)
        write_obj(mm / p.name, m.vertices * 10, m.face_vertices, m.face_offsets, m.uvs, m.face_uvs)
    assert main(["import", str(obj_folder), "--out", str(tmp_path / "cm"), "-q"]) == 0
    assert main(["import", str(mm), "--out", str(tmp_path / "from_mm"), "--units", "mm", "-q"]) == 0
    a = ShapeDataset.load(tmp_path / "cm")
    b = ShapeDataset.load(tmp_path / "from_mm")
    assert b.units == "cm" and b.info["source_units"] == "mm"
    np.testing.assert_allclose(b.neutral, a.neutral, atol=1e-5)
    np.testing.assert_allclose(np.asarray(b.deltas), np.asarray(a.deltas), atol=1e-5)


@pytest.mark.parametrize("argv,flag", [
    (["build", "D", "--markers", "M", "--out", "O", "--knn", "-3"], "--knn"),
    (["build", "D", "--markers", "M", "--out", "O", "--subset-fraction", "2"], "--subset-fraction"),
    (["augment", "D", "--out", "O", "--linear", "--orders", "9"], "--orders"),
    (["augment", "D", "--out", "O", "--linear", "--levels", "0,1.5"], "--levels"),
    (["verify", "I", "--tolerance", "-1"], "--tolerance"),
])
def test_bad_option_values_refused(tmp_path: Path, argv: list[str], flag: str, capsys) -> None:
    assert main([a if a not in ("D", "M", "O", "I") else str(tmp_path / a) for a in argv]) == 2
    assert flag in capsys.readouterr().err
    assert not (tmp_path / "O").exists()


def test_rig_needs_three_jaw_vertices(tmp_path: Path, obj_folder: Path, capsys) -> None:
    assert main(["import", str(obj_folder), "--out", str(tmp_path / "d"), "-q"]) == 0
    assert main(["rig", str(tmp_path / "d"), "--jaw-vertices", "5:6", "--shapes", "jaw_*",
                 "--out", str(tmp_path / "r.npz")]) == 2
    assert "at least 3" in capsys.readouterr().err
    assert not (tmp_path / "r.npz").exists()
