"""The command line is a contract that outside scripts call: a value accepted once stays accepted (with what it
meant), and the first release's documented invocations still work."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lgi.cli import build_parser, main
from lgi.dataset.shapes import ShapeDataset
from lgi.io.obj import write_obj
from lgi.synthetic import actor as synth

ROOT = Path(__file__).resolve().parents[1]
#: The commit of the first README (the first release's documentation).
FIRST_README = "9dba29a"
#: The ``lgi`` command lines it documents, as written there (checked against the commit when the history is here).
FIRST_COMMANDS = [
    "lgi demo",
    "lgi import ../shared/data/ict-facekit --out datasets/ict --rigid-vertices "
    "../shared/data/ict-facekit/vertex_indices.json",
    "lgi bundles datasets/ict --markers data/markers_ict.csv --out ict-bundles.csv",
    "lgi synth --out synth --frames 300 --seed 1",
]
#: Small sizes for the runs (the documented options are all kept; these only scale the synthetic actor down).
SMALL = {"demo": ["--vertices", "2000", "--frames", "8"], "synth": ["--vertices", "2000"]}


def _first_readme() -> str | None:
    r = subprocess.run(["git", "show", f"{FIRST_README}:README.md"], cwd=ROOT, capture_output=True, text=True)
    return r.stdout if r.returncode == 0 else None


def _documented_commands(readme: str) -> list[str]:
    """The ``lgi ...`` command lines in the README's code blocks (``... && lgi demo`` counts as ``lgi demo``)."""
    commands = []
    for block in re.findall(r"```\n(.*?)```", readme, re.S):
        for line in block.splitlines():
            if "lgi " in line and (line.startswith("lgi ") or "&& lgi " in line):
                commands.append(line[line.index("lgi "):].strip())
    return commands


def test_the_recorded_commands_are_the_first_readmes() -> None:
    readme = _first_readme()
    if readme is None:
        pytest.skip(f"the history is not here (git show {FIRST_README} failed): the recorded list stands")
    assert _documented_commands(readme) == FIRST_COMMANDS


def _lgi(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """``lgi ARGS`` as a script calls it: a process of its own, from ``cwd`` (relative paths as written)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "lgi", *argv], cwd=cwd, capture_output=True, text=True, env=env,
                          timeout=900)


def _ict_like_folder(folder: Path) -> None:
    """The small synthetic actor where the first README's import reads ICT FaceKit: a neutral, three shapes and a
    vertex_indices.json in ICT's form (the skull's vertices under idx_to_rigid_verts): those no shape moves."""
    a = synth.make_actor(1500)
    write_obj(folder / "generic_neutral_mesh.obj", a.neutral, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs)
    eye = np.eye(len(synth.CONTROLS))
    moved = np.zeros(a.n_vertices)
    for name in ("jaw_open", "smile_L", "pucker"):
        shape = a.evaluate(eye[synth.C[name]])
        moved = np.maximum(moved, np.linalg.norm(shape - a.neutral, axis=1))
        write_obj(folder / f"{name}.obj", shape, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs)
    rigid = np.flatnonzero(moved == 0.0)
    assert len(rigid) >= 3
    (folder / "vertex_indices.json").write_text(json.dumps({"idx_to_rigid_verts": rigid.tolist()}))


def test_first_release_invocations_still_work(tmp_path: Path, layout_csv: Path) -> None:
    """Each command line of the first README, run as written from a folder laid out as it assumes (the shared
    data beside it holding a small synthetic actor in ICT's place, the layout at data/markers_ict.csv), with only
    the synthetic actor's size scaled down: exit 0 and the outputs it documents."""
    work = tmp_path / "work"
    (work / "data").mkdir(parents=True)
    ict = tmp_path / "shared" / "data" / "ict-facekit"
    ict.mkdir(parents=True)
    _ict_like_folder(ict)
    (work / "data" / "markers_ict.csv").write_bytes(layout_csv.read_bytes())  # the small actor's layout
    for command in FIRST_COMMANDS:
        argv = command.split()[1:]
        argv += SMALL.get(argv[0], [])
        r = _lgi(argv, work)
        assert r.returncode == 0, f"{command}: exit {r.returncode}\n{r.stderr}"
    demo = work / "lgi-demo"  # the documented default
    for name in ("dataset", "markers.csv", "bundles.csv", "truth.npz", "index", "meshes.npz", "diagnostics.csv"):
        assert (demo / name).exists(), name
    with np.load(demo / "meshes.npz") as z:
        assert z["vertices"].shape[0] == 8 and np.isfinite(z["vertices"]).all()
    ds = ShapeDataset.load(work / "datasets" / "ict", verify=True)
    assert sorted(ds.names) == ["jaw_open", "pucker", "smile_L"]
    bundles = (work / "ict-bundles.csv").read_text().splitlines()
    assert bundles[0].startswith("frame,marker,x,y,z")
    shapes = (work / "ict-bundles.shapes.csv").read_text().splitlines()
    assert shapes[0] == "frame,shape" and len(shapes) == 1 + ds.n_shapes
    for name in ("dataset", "markers.csv", "bundles.csv", "truth.npz"):
        assert (work / "synth" / name).exists(), name
    with np.load(work / "synth" / "truth.npz") as z:
        assert z["vertices"].shape[0] == 300  # --frames 300 as documented


def _first_table(readme: str) -> list[str]:
    return [m for m in re.findall(r"^\| `(lgi [^`]*)` \|", readme, re.M)]


def test_first_release_options_still_parse() -> None:
    """Every option the first README's command table lists is still accepted, with every value it spelt out
    (``--units mm|cm|m|in``, ``--rigid-vertices FILE|auto|none``)."""
    readme = _first_readme()
    if readme is None:
        pytest.skip(f"the history is not here (git show {FIRST_README} failed)")
    rows = _first_table(readme)
    assert len(rows) == 4
    parser = build_parser()
    subs = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction").choices
    checked = 0
    for row in rows:
        words = row.replace("\\|", "|").replace("[", " ").replace("]", " ").split()
        command, sub = words[1], subs[words[1]]
        base = [command] + ["x" for a in sub._actions if not a.option_strings]
        base += [w for a in sub._actions if a.required and a.option_strings for w in (a.option_strings[-1], "x")]
        for i, word in enumerate(words):
            if not word.startswith("-"):
                continue
            action = sub._option_string_actions[word]  # KeyError: an option of the first release is gone
            if action.nargs == 0:
                values = [[]]
            else:
                spelt = words[i + 1].split("|") if i + 1 < len(words) else []
                values = [[v] for v in spelt if v.islower()] or [["1"]]
            for value in values:
                build_parser().parse_args([*base, word, *value])  # SystemExit 2 if refused
                checked += 1
    assert checked >= 20


# ------------------------------------------------------------------------------------------- values kept


@pytest.fixture(scope="module")
def shot(tmp_path_factory) -> Path:
    t = tmp_path_factory.mktemp("contract")
    assert main(["synth", "--out", str(t / "s"), "--vertices", "2000", "--frames", "12", "-q"]) == 0
    assert main(["build", str(t / "s" / "dataset"), "--markers", str(t / "s" / "markers.csv"), "--jaw-rig",
                 str(t / "s" / "jaw_rig.npz"), "--out", str(t / "idx"), "-q"]) == 0
    assert main(["build", str(t / "s" / "dataset"), "--markers", str(t / "s" / "markers.csv"), "--out",
                 str(t / "idx_plain"), "-q"]) == 0
    return t


def _meshes(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def test_smooth_zero_is_no_smoothing(shot: Path) -> None:
    """``--smooth 0`` (accepted by the first release: no smoothing) gives the meshes of ``--smooth 1`` bit for bit;
    so do the other values it took as none (below 0, ``--jaw-smooth 0``, ``--max-gap -1``) and ``--smooth auto``,
    an early default. ``--smooth 3`` differs, so the equality is not vacuous."""
    runs = {"1": ["--smooth", "1"], "0": ["--smooth", "0"], "auto": ["--smooth", "auto"],
            "below": ["--smooth", "-3", "--jaw-smooth", "0", "--max-gap", "-1"], "3": ["--smooth", "3"]}
    for name, extra in runs.items():
        code = main(["reconstruct", str(shot / "idx"), "--bundles", str(shot / "s" / "bundles.csv"), "--out",
                     str(shot / f"r{name}"), "-q", *extra])
        assert code == 0, name
    ref = _meshes(shot / "r1" / "meshes.npz")
    assert set(ref) >= {"vertices", "frames", "jaw"}
    for name in ("0", "auto", "below"):
        got = _meshes(shot / f"r{name}" / "meshes.npz")
        assert set(got) == set(ref), name
        for key in ref:
            assert got[key].dtype == ref[key].dtype and np.array_equal(got[key], ref[key]), (name, key)
    assert not np.array_equal(_meshes(shot / "r3" / "meshes.npz")["vertices"], ref["vertices"])


def test_smooth_still_refuses_what_it_never_took(shot: Path, capsys) -> None:
    """Not a whole number: refused by argparse (exit 2), as it always was."""
    argv = ["reconstruct", str(shot / "idx"), "--bundles", str(shot / "s" / "bundles.csv"), "--out",
            str(shot / "bad"), "-q", "--smooth"]
    for value in ("1.5", "three"):
        with pytest.raises(SystemExit) as exc:
            main([*argv, value])
        assert exc.value.code == 2
        assert "--smooth" in capsys.readouterr().err
    assert not (shot / "bad").exists()


def test_options_once_ignored_are_warned_about_not_refused(tmp_path: Path, obj_folder: Path, layout_csv: Path,
                                                          capsys) -> None:
    """``lgi import --markers`` without ``--flow`` and ``lgi synth``'s footage options without ``--hmc`` were
    ignored by the releases before they were checked: they still run (exit 0), saying what is ignored."""
    assert main(["import", str(obj_folder), "--out", str(tmp_path / "ds"), "-q", "--markers", str(layout_csv)]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "--markers" in err and "--flow" in err, err
    assert ShapeDataset.load(tmp_path / "ds").n_shapes == 3 and not (tmp_path / "ds" / "index").exists()
    assert main(["synth", "--out", str(tmp_path / "s"), "--vertices", "1500", "--frames", "2", "-q",
                 "--rig-flex", "5", "--lens", "pinhole"]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "--lens, --rig-flex" in err and "--hmc" in err, err
    assert (tmp_path / "s" / "bundles.csv").is_file() and not (tmp_path / "s" / "hmc").exists()


# ------------------------------------------------------------------------------------ defects, through the CLI


def test_import_names_both_files_of_one_shape(tmp_path: Path, obj_folder: Path, capsys) -> None:
    (obj_folder / "jaw_open.OBJ").write_bytes((obj_folder / "jaw_open.obj").read_bytes())
    code = main(["import", str(obj_folder), "--out", str(tmp_path / "ds"), "-q"])
    err = capsys.readouterr().err
    assert code == 2
    assert "jaw_open.obj" in err and "jaw_open.OBJ" in err and "'jaw_open'" in err, err
    assert "Traceback" not in err and not (tmp_path / "ds").exists()


def test_rig_refuses_an_npy_of_python_objects(shot: Path, tmp_path: Path, capsys) -> None:
    bad = tmp_path / "jaw_vertices.npy"
    np.save(bad, np.array([[1, 2, 3], [4, 5]], dtype=object), allow_pickle=True)
    code = main(["rig", str(shot / "s" / "dataset"), "--jaw-vertices", str(bad), "--out", str(tmp_path / "rig.npz")])
    err = capsys.readouterr().err
    assert code == 2
    assert str(bad) in err and "Python objects" in err and "allow_pickle" not in err, err
    assert "Traceback" not in err and not (tmp_path / "rig.npz").exists()


def test_verify_on_non_finite_data_warns_nothing(shot: Path, tmp_path: Path) -> None:
    """A non-finite index fails the check (exit 1, said) without numpy's 'All-NaN slice' RuntimeWarning."""
    import shutil

    idx = tmp_path / "idx"
    shutil.copytree(shot / "idx_plain", idx)
    np.save(idx / "deltas.npy", np.load(idx / "deltas.npy") * np.nan)
    r = _lgi(["verify", str(idx), "-q"], tmp_path)
    assert r.returncode == 1, r.stderr
    assert "non-finite" in r.stdout + r.stderr
    assert "RuntimeWarning" not in r.stderr and "All-NaN" not in r.stderr, r.stderr
