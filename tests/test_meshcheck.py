"""``lgi import`` refuses a neutral mesh the index cannot use (pymeshlab's topological measures), naming the
problem, the file and where; a sound mesh is imported with its measures in the summary."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lgi.cli import main
from lgi.io.obj import write_obj


def grid(n: int = 8) -> tuple[np.ndarray, list[list[int]]]:
    """A curved n x n patch of quads (cm), counter-clockwise seen from +z."""
    x, y = np.meshgrid(np.linspace(-3, 3, n), np.linspace(-3, 3, n))
    v = np.c_[x.ravel(), y.ravel(), 0.05 * (x.ravel() ** 2 + y.ravel() ** 2)]
    quads = [[i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j] for i in range(n - 1)
             for j in range(n - 1)]
    return v, quads


def write_folder(folder: Path, v: np.ndarray, faces: list[list[int]]) -> Path:
    fv = np.concatenate(faces)
    off = np.concatenate([[0], np.cumsum([len(f) for f in faces])])
    write_obj(folder / "neutral.obj", v, fv, off)
    rng = np.random.default_rng(0)
    for name in ("smile", "pucker"):
        write_obj(folder / f"{name}.obj", v + rng.normal(scale=0.05, size=v.shape), fv, off)
    return folder


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_sound_mesh_is_imported_with_its_measures(tmp_path: Path, capsys) -> None:
    v, q = grid()
    folder = write_folder(tmp_path / "shapes", v, q)
    code, out, err = run(["import", str(folder), "--out", str(tmp_path / "ds"), "--rigid-vertices", "none", "-q"],
                         capsys)
    assert code == 0, err
    assert "mesh checked (pymeshlab" in out and "1 piece(s), 1 boundary loop(s)" in out


def broken(kind: str) -> tuple[np.ndarray, list[list[int]], str]:
    """A grid with one defect, and what the message must say."""
    v, q = grid()
    n = 8
    if kind == "non-manifold edge":
        a, b = 3 * n + 3, 3 * n + 4  # an interior edge shared by two quads gets a third face
        v = np.r_[v, [[0.0, 0.0, 2.0]]]
        q = [*q, [a, b, len(v) - 1]]
    elif kind == "flipped face":
        q[20] = q[20][::-1]
    elif kind == "isolated piece":
        v = np.r_[v, [[10.0, 0, 0], [11.0, 0, 0], [10.0, 1.0, 0]]]
        q = [*q, [len(v) - 3, len(v) - 2, len(v) - 1]]
    elif kind == "degenerate face":
        v = np.r_[v, [0.5 * (v[0] + v[1])]]
        q = [*q, [1, 0, len(v) - 1]]  # on the outline, wound as its neighbour, its corners collinear (to rounding)
    elif kind == "unreferenced vertex":
        v = np.r_[v, [[0.0, 0.0, 5.0]]]
    return v, q, kind


@pytest.mark.parametrize("kind", ["non-manifold edge", "flipped face", "isolated piece", "degenerate face",
                                  "unreferenced vertex"])
def test_broken_mesh_exits_2_naming_the_problem(tmp_path: Path, capsys, kind: str) -> None:
    v, q, said = broken(kind)
    folder = write_folder(tmp_path / "shapes", v, q)
    out = tmp_path / "ds"
    code, _, err = run(["import", str(folder), "--out", str(out), "--rigid-vertices", "none", "-q"], capsys)
    assert code == 2 and "Traceback" not in err
    assert said in err and str(folder / "neutral.obj") in err and "cannot be indexed" in err
    assert not out.exists()
    if kind == "flipped face":
        assert "faces 20 (0-based, in file order, the first on line" in err
    if kind == "isolated piece":
        assert f"faces {len(q) - 1} " in err
    if kind == "non-manifold edge":
        assert "vertices 27-28" in err
    assert err.count("face(s)") + err.count("vertex(es)") + err.count("edge(s)") + err.count("piece(s)") == 1
