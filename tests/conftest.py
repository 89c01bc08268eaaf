"""Shared fixtures. Prefect settings are set before Prefect is imported anywhere."""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest

_PREFECT_HOME = tempfile.mkdtemp(prefix="lgi-test-prefect-")
os.environ.setdefault("PREFECT_HOME", _PREFECT_HOME)
os.environ.setdefault("PREFECT_LOCAL_STORAGE_PATH", os.path.join(_PREFECT_HOME, "storage"))
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")

from lgi.io.obj import write_obj  # noqa: E402
from lgi.paths import shared_data  # noqa: E402
from lgi.synthetic import actor as synth  # noqa: E402

ICT = shared_data("ict-facekit")
REAL_PERFORMANCES = shared_data("real-performances")


@pytest.fixture(scope="session")
def ict_dir() -> Path:
    if not (ICT / "generic_neutral_mesh.obj").is_file():
        pytest.skip(f"ICT FaceKit data not found at {ICT} (set LGI_SHARED_DATA to the shared data folder)")
    return ICT


@pytest.fixture(scope="session")
def real_dir() -> Path:
    """The real performances (Live Link Face takes, facial mocap: ABOUT.md there), read in place."""
    if not (REAL_PERFORMANCES / "ABOUT.md").is_file():
        pytest.skip(f"real performances not found at {REAL_PERFORMANCES} (set LGI_SHARED_DATA to the shared data "
                    "folder)")
    return REAL_PERFORMANCES


@pytest.fixture(scope="session")
def small_actor() -> synth.SyntheticActor:
    return synth.make_actor(1500)


@pytest.fixture()
def obj_folder(tmp_path: Path, small_actor: synth.SyntheticActor) -> Path:
    """A folder with neutral.obj and three full-mesh shapes of the small synthetic actor."""
    folder = tmp_path / "shapes"
    a = small_actor
    write_obj(folder / "neutral.obj", a.neutral, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs)
    eye = np.eye(len(synth.CONTROLS))
    for name in ("jaw_open", "smile_L", "pucker"):
        write_obj(folder / f"{name}.obj", a.evaluate(eye[synth.C[name]]), a.face_vertices, a.face_offsets,
                  a.uvs, a.face_uvs)
    return folder


@pytest.fixture(scope="session")
def small_index(small_actor):
    """(actor, dataset, layout, index, reports) for the small synthetic actor."""
    from lgi.index.build import build_index

    ds = synth.make_dataset(small_actor)
    layout, _ = synth.default_layout(small_actor)
    index, reports = build_index(ds, layout, show_progress=False)
    return small_actor, ds, layout, index, reports


@pytest.fixture()
def layout_csv(tmp_path: Path, small_actor) -> Path:
    """The small actor's default marker layout as a CSV (with neutral positions)."""
    from lgi.dataset.markers import write_layout

    layout, _ = synth.default_layout(small_actor)
    path = tmp_path / "markers.csv"
    write_layout(path, layout, small_actor.neutral)
    return path


@pytest.fixture(scope="session")
def prefect_harness():
    """One temporary Prefect API for the whole session (starting one takes seconds)."""
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=180):
        yield


@pytest.fixture(scope="session")
def prefect_api(prefect_harness) -> str:
    """The session's temporary Prefect API URL: flows run in subprocesses (kills, interrupts, concurrent runs)
    connect to it through ``PREFECT_API_URL`` instead of each starting and migrating a server of their own."""
    from prefect.settings import PREFECT_API_URL

    return str(PREFECT_API_URL.value())


@pytest.fixture(autouse=True)
def _no_stale_prefect_console():
    """Prefect's logging setup (a flow run in this process) gives the root logger a console handler bound to the
    stderr of that moment: in pytest a capture stream, closed by the time a later test logs, which then finds
    "--- Logging error ---" tracebacks in its own stderr. The handler goes after each test."""
    yield
    root = logging.getLogger()
    for h in list(root.handlers):
        if type(h).__name__ == "PrefectConsoleHandler":
            root.removeHandler(h)
