"""The code's shape, checked: short functions with few parameters, and a task package that lists every task."""

from __future__ import annotations

import ast
import importlib
import pkgutil
from pathlib import Path

import pytest

from lgi.paths import REPO_ROOT

#: At most this many lines per function, and parameters per function (``self``, ``cls`` and a flow's ``**options``,
#: its declared job options, not counted).
MAX_LINES = 150
MAX_PARAMS = 12
ROOTS = ("lgi", "flows", "tasks", "scripts")


def _functions(root: Path):
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield path.relative_to(REPO_ROOT), node


def _n_params(node: ast.FunctionDef) -> int:
    a = node.args
    names = [p.arg for p in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    return len([n for n in names if n not in ("self", "cls")]) + (a.vararg is not None)


@pytest.mark.parametrize("root", ROOTS)
def test_functions_are_short_and_take_few_parameters(root: str) -> None:
    found = list(_functions(REPO_ROOT / root))
    too_long = [f"{p}:{n.lineno} {n.name} ({n.end_lineno - n.lineno + 1} lines)" for p, n in found
                if n.end_lineno - n.lineno + 1 > MAX_LINES]
    too_many = [f"{p}:{n.lineno} {n.name} ({_n_params(n)} parameters)" for p, n in found if _n_params(n) > MAX_PARAMS]
    assert not too_long and not too_many, "\n".join(too_long + too_many)


def test_the_shape_check_sees_a_long_function(tmp_path: Path) -> None:
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES))
    src = f"def f({', '.join(f'a{i}' for i in range(MAX_PARAMS + 1))}):\n{body}\n"
    node = ast.parse(src).body[0]
    assert node.end_lineno - node.lineno + 1 > MAX_LINES and _n_params(node) == MAX_PARAMS + 1


def test_the_tasks_package_lists_every_task() -> None:
    """``tasks/`` is where a studio's own flows import the tasks from: each Prefect task the orchestration defines
    is there."""
    from prefect import Task

    import lgi.orchestration as orch

    defined = set()
    for info in pkgutil.iter_modules(orch.__path__, "lgi.orchestration."):
        module = importlib.import_module(info.name)
        defined |= {name for name, obj in vars(module).items()
                    if isinstance(obj, Task) and obj.fn.__module__ == module.__name__}
    exported = set()
    for path in sorted((REPO_ROOT / "tasks").glob("*.py")):
        module = importlib.import_module(f"tasks.{path.stem}")
        exported |= {name for name in getattr(module, "__all__", []) if isinstance(getattr(module, name), Task)}
    assert defined == exported, (sorted(defined - exported), sorted(exported - defined))
