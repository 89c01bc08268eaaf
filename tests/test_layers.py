"""The package's layers (pyproject.toml, [tool.importlinter]): the library below the jobs, the jobs below the
Prefect flows, the flows below the command line. A module importing upward breaks the contract."""

from __future__ import annotations

import os
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT = shutil.which("lint-imports")
pytestmark = pytest.mark.skipif(LINT is None, reason="import-linter is not installed (pip install -e '.[dev]')")


def lint(package_parent: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(package_parent)}
    return subprocess.run([LINT, "--no-cache", "--config", str(ROOT / "pyproject.toml")], cwd=package_parent,
                          env=env, capture_output=True, text=True, timeout=300)


def test_each_layer_imports_only_those_below() -> None:
    r = lint(ROOT)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "1 kept, 0 broken" in r.stdout


def test_every_module_is_in_a_layer() -> None:
    """A new package outside every layer would escape the contract."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"][0]
    named = {m.strip() for layer in config["layers"] for m in layer.replace("|", ":").split(":")}
    children = {f"lgi.{p.stem}" for p in (ROOT / "lgi").iterdir()
                if (p.suffix == ".py" and p.stem != "__init__") or (p / "__init__.py").is_file()}
    assert children - named == set()
    assert named - children == set()


def test_an_upward_import_breaks_the_contract(tmp_path: Path) -> None:
    shutil.copytree(ROOT / "lgi", tmp_path / "lgi", ignore=shutil.ignore_patterns("__pycache__"))
    solver = tmp_path / "lgi" / "solve" / "solver.py"
    solver.write_text(solver.read_text() + "\n\ndef _planted():\n    from lgi.jobs.reconstruct import options\n")
    r = lint(tmp_path)
    assert r.returncode == 1, r.stdout[-3000:] + r.stderr[-2000:]
    assert "BROKEN" in r.stdout and "lgi.solve.solver -> lgi.jobs.reconstruct.options" in r.stdout
