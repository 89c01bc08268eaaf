"""A built wheel works on its own: installed into a fresh virtual environment, run from another directory."""

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow  # 46 s even interpreted: the default suite has to stay under 10 minutes on a fresh clone
@pytest.mark.parametrize("compiled", [
    # Compiling the kernels afresh for the new install takes about 3 minutes on 2 cores; the packaging is what is
    # tested here, so this run interprets them (same code paths).
    False,
    True,
])
def test_wheel_installs_and_runs_elsewhere(tmp_path: Path, compiled: bool) -> None:
    # Built from a copy: setuptools leaves build/ and *.egg-info beside the sources it builds.
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    shutil.copytree(ROOT / "lgi", src / "lgi", ignore=shutil.ignore_patterns("__pycache__"))
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(dist),
                    str(src)], check=True, cwd=tmp_path)
    wheel = next(dist.glob("lgi-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    assert "lgi/data/markers_synth.csv" in names and "lgi/data/markers_ict.csv" in names
    assert not [n for n in names if n.split("/")[0] in ("flows", "tasks")]  # no generic top-level packages

    # The dependencies come from this environment; lgi only from the wheel.
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    py, lgi = venv / "bin" / "python", venv / "bin" / "lgi"
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)], check=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH",)}
    env.update(PREFECT_HOME=str(tmp_path / "prefect"), PREFECT_LOGGING_LEVEL="WARNING",
               PREFECT_SERVER_ANALYTICS_ENABLED="false", NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    if not compiled:
        env["NUMBA_DISABLE_JIT"] = "1"
    where = subprocess.run([str(py), "-c", "import lgi; print(lgi.__file__)"], cwd=elsewhere, env=env, check=True,
                           capture_output=True, text=True).stdout
    assert str(venv) in where

    def run(*argv: str) -> subprocess.CompletedProcess:
        r = subprocess.run([str(lgi), *argv], cwd=elsewhere, env=env, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr[-2000:]
        return r

    run("demo", "--vertices", "1500", "--frames", "6", "--out", "demo", "-q")
    m = np.load(elsewhere / "demo" / "meshes.npz")
    assert m["vertices"].shape[0] == 6
    if compiled:
        run("reconstruct", "demo/index", "--bundles", "demo/bundles.csv", "--out", "rec", "--flow", "-q")
        np.testing.assert_array_equal(np.load(elsewhere / "rec" / "meshes.npz")["vertices"], m["vertices"])
    else:  # the flows are in the package: importable from the wheel alone
        subprocess.run([str(py), "-c", "import lgi.orchestration.reconstruct, lgi.orchestration.rebuild"],
                       cwd=elsewhere, env=env, check=True)
