from pathlib import Path

import pytest

from lgi.dataset import ShapeDataset
from lgi.importers import import_obj_folder


@pytest.fixture(scope="session")
def prefect_harness():
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=180):
        yield


def test_rebuild_dataset_flow_matches_library(prefect_harness, tmp_path: Path, obj_folder: Path) -> None:
    from flows.rebuild_dataset import rebuild_dataset

    summary = rebuild_dataset(str(obj_folder), str(tmp_path / "ds"), rigid_vertices="auto")
    ds = ShapeDataset.load(tmp_path / "ds", verify=True)
    assert summary["n_shapes"] == 3 == ds.n_shapes
    assert summary["content_hash"] == import_obj_folder(obj_folder, show_progress=False).content_hash()
