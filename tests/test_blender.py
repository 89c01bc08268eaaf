"""What Blender shows of lgi's files: the shot (``lgi export --dcc blender``) and the solved rig (``lgi rig-generate
--usd --dcc blender``, then ``lgi rig-solve --usd``), each imported through the script lgi writes beside it, in
Blender's own Python (bpy 4.2 LTS, Blender's module from the package registry, in a Python of its own).

Set ``LGI_BLENDER_PYTHON`` to that Python (``.ci/run`` makes one when bpy installs); without it these tests skip.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from lgi.cli import main
from lgi.synthetic import actor as A

BLENDER_PYTHON = os.environ.get("LGI_BLENDER_PYTHON", "")
CHECK = Path(__file__).with_name("blender_check.py")
FRAMES = 8
PAIRS = (("jaw_open", "smile_L"), ("jaw_open", "smile_R"))


def _blender_python() -> str:
    if not BLENDER_PYTHON:
        pytest.skip("LGI_BLENDER_PYTHON is not set: no Python with bpy (Blender 4.2's module; .ci/run installs it "
                    "in a Python 3.11 of its own)")
    r = subprocess.run([BLENDER_PYTHON, "-c", "import bpy; print(bpy.app.version_string)"], capture_output=True,
                       text=True)
    if r.returncode != 0:
        pytest.skip(f"LGI_BLENDER_PYTHON={BLENDER_PYTHON} cannot import bpy: {r.stderr.strip()[-300:]}")
    return BLENDER_PYTHON


def _blender(script: Path, frames: list[int], out: Path, control: str | None = None) -> dict:
    argv = [_blender_python(), str(CHECK), str(script), ",".join(map(str, frames)), str(out)]
    r = subprocess.run([*argv, *([control] if control else [])], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def shot(tmp_path_factory) -> Path:
    _blender_python()
    t = tmp_path_factory.mktemp("blender")
    s = t / "s"
    assert main(["synth", "--out", str(s), "--vertices", "2500", "--frames", str(FRAMES), "-q"]) == 0
    assert main(["build", str(s / "dataset"), "--markers", str(s / "markers.csv"), "--jaw-rig",
                 str(s / "jaw_rig.npz"), "--out", str(t / "idx"), "-q"]) == 0
    assert main(["reconstruct", str(t / "idx"), "--bundles", str(s / "bundles.csv"), "--out", str(t / "rec"),
                 "-q"]) == 0
    # A template rig: the synthetic actor's 13 controls and two of its combination shapes.
    eye = np.eye(len(A.CONTROLS))
    combos = [eye[A.C[a]] + eye[A.C[b]] for a, b in PAIRS]
    A.make_dataset(A.make_actor(2500), [*A.CONTROLS, *("+".join(p) for p in PAIRS)],
                   np.vstack([eye, *combos])).save(t / "template")
    return t


def test_the_shot_in_blender(shot: Path) -> None:
    """Imported through its script, with no manual scale: the vertices within 1e-3 mm of meshes.npz (in Blender's
    metres, Z up) at several frames, 30 fps and the shot's frame range."""
    from lgi.export.convention import Convention

    assert main(["export", str(shot / "rec"), "--index", str(shot / "idx"), "--usd", str(shot / "shot.usdc"),
                 "--dcc", "blender", "-q"]) == 0
    frames = [0, 3, FRAMES - 1]
    got = _blender(shot / "shot.blender.py", frames, shot / "shot.json")
    want = Convention.of("blender").points(np.load(shot / "rec" / "meshes.npz")["vertices"], np.float64)
    worst = max(np.abs(np.asarray(got["frames"][str(f)]["vertices"]) - want[f]).max() for f in frames) * 1000
    print(f"Blender: the shot's vertices within {worst:.2e} mm of meshes.npz; {got['fps']:g} fps, frames "
          f"{got['range']}")
    assert worst < 1e-3 and got["fps"] == 30.0 and got["range"] == [0, FRAMES - 1]
    assert got["scale"] == [1.0, 1.0, 1.0]
    # lgi reconstruct --usd --dcc blender writes the same file and script into its output folder.
    assert main(["reconstruct", str(shot / "idx"), "--bundles", str(shot / "s" / "bundles.csv"), "--out",
                 str(shot / "rec_bl"), "--usd", "--dcc", "blender", "-q"]) == 0
    again = _blender(shot / "rec_bl" / "shot.blender.py", frames, shot / "shot_rec.json")
    assert again["frames"] == got["frames"] and again["fps"] == 30.0


def test_the_solved_rig_in_blender(shot: Path) -> None:
    """The rig and its solved animation imported through the script: the played face within 1e-3 mm of lgi's own
    playback of the curves, every control's shape-key value the curve's, the jaw bone turned as the jaw curves
    say, and each corrective driven by the product of its controls: set by hand, a control takes its correctives
    with it."""
    from lgi.export.convention import Convention
    from lgi.export.formats import usd_name
    from lgi.jobs.rig_solve import JAW_CURVES, load_rig, playback, read_curves
    from lgi.solve.jaw import jaw_matrix

    assert main(["rig-generate", "--template", str(shot / "template"), "--index", str(shot / "idx"), "--out",
                 str(shot / "rig"), "--correctives", "auto", "--usd", str(shot / "rig.usdc"), "--dcc", "blender",
                 "-q"]) == 0
    assert (shot / "rig.blender.py").is_file()
    assert main(["rig-solve", str(shot / "rec"), "--rig", str(shot / "rig"), "--out", str(shot / "rs"), "--usd",
                 str(shot / "anim" / "shot.usda"), "--rig-usd", str(shot / "rig.usdc"), "-q"]) == 0
    rig = load_rig(shot / "rig")[0]
    assert rig.jaw is not None and len(rig.combinations) >= 2
    curves = read_curves(shot / "rs", rig.controls)
    jaw = read_curves(shot / "rs", list(JAW_CURVES))
    weights = rig.all_weights(curves)
    frames = [0, 4, FRAMES - 1]
    got = _blender(shot / "anim" / "shot.blender.py", frames, shot / "rig.json", control=usd_name(rig.controls[0]))
    assert got["fps"] == 30.0 and got["range"] == [0, FRAMES - 1]
    assert got["bone_curves"] == ["jaw"]  # the static root is not keyed
    blender = Convention.of("blender")
    played = blender.points(playback(rig, np.c_[curves, jaw]), np.float64)
    names = [usd_name(n) for n in rig.names]
    worst_v = worst_w = worst_r = 0.0
    for f in frames:
        row = got["frames"][str(f)]
        worst_v = max(worst_v, np.abs(np.asarray(row["vertices"]) - played[f]).max() * 1000)
        worst_w = max(worst_w, max(abs(row["keys"][n] - w) for n, w in zip(names, weights[f], strict=True)))
        turn = blender.rotation @ jaw_matrix(jaw[f], rig.jaw.pivot)[:3, :3] @ blender.rotation.T
        worst_r = max(worst_r, np.abs(np.asarray(row["jaw_rotation"]) - turn).max())
    print(f"Blender: the rig's played face within {worst_v:.2e} mm of lgi's playback; shape-key values within "
          f"{worst_w:.1e}; jaw bone rotation within {worst_r:.1e}")
    assert worst_v < 1e-3 and worst_w < 1e-5 and worst_r < 1e-5
    control = usd_name(rig.controls[0])
    followed = 0
    for step in got["follow"]:
        keys = step["keys"]
        assert keys[control] == step["value"]
        for name, combo in zip(rig.corrective_names, rig.combinations, strict=True):
            parts = [usd_name(rig.controls[c]) for c in combo]
            assert abs(keys[usd_name(name)] - np.prod([keys[p] for p in parts])) < 1e-6, name
            followed += control in parts
    assert followed >= 2  # the control has correctives, and they moved with it
