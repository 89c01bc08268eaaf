"""lgi rig-generate (paper 7.7): actor rigs from a template, their USD, bad inputs; lgi synth --actor."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lgi.cli import main
from lgi.dataset.shapes import ShapeDataset
from lgi.synthetic import actor as A

N_VERTICES = 2500


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lgi.cli", *args], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> dict:
    """A template (the default actor's 13 controls and two of its combinations) and actor 1's index."""
    d = tmp_path_factory.mktemp("rig")
    eye = np.eye(len(A.CONTROLS))
    pairs = [("jaw_open", "pucker"), ("smile_L", "cheek_puff")]
    acts = np.vstack([eye, *[[eye[A.C[a]] + eye[A.C[b]]] for a, b in pairs]])
    template = A.make_dataset(A.make_actor(N_VERTICES), [*A.CONTROLS, *("+".join(p) for p in pairs)], acts)
    template.save(d / "template")
    assert main(["synth", "--out", str(d / "actor"), "--vertices", str(N_VERTICES), "--frames", "2", "--actor", "1",
                 "-q"]) == 0
    assert main(["build", str(d / "actor" / "dataset"), "--markers", str(d / "actor" / "markers.csv"), "--jaw-rig",
                 str(d / "actor" / "jaw_rig.npz"), "--out", str(d / "index"), "-q"]) == 0
    return {"dir": d, "pairs": pairs, "actor": A.make_actor(N_VERTICES, A.ActorVariant.draw(1))}


def test_actor_variant_is_another_face_and_the_default_is_unchanged() -> None:
    assert A.ActorVariant.draw(0).is_default
    base, other = A.make_actor(1000), A.make_actor(1000, A.ActorVariant.draw(1))
    assert np.array_equal(base.neutral, A.make_actor(1000, A.ActorVariant()).neutral)
    # Not just a rescaling: after the best affine map between the neutrals, the smile still differs.
    from lgi.retarget.template import fit_affine

    m, _ = fit_affine(base.neutral, other.neutral)
    k = A.C["smile_L"]
    d0, d1 = base.extreme_deltas()[k], other.extreme_deltas()[k]
    assert np.sqrt(np.mean(np.sum((d1 - d0 @ m.T) ** 2, axis=1))) > 0.003  # cm
    # Its true jaw rig is a rig of its shapes: the skinned jaw opening is the shape.
    rig = A.jaw_rig(other)
    a = np.eye(len(A.CONTROLS))[A.C["jaw_open"]]
    np.testing.assert_allclose(other.evaluate(a), rig.skin(other.unskinned(a), other.jaw_parameters(a)), atol=1e-9)


def test_generated_controls_beat_the_naive_transfer(setup) -> None:
    """On another actor, the generated controls are at most half the naive transfer's error and better than
    the same transfer without LGI; interpolating (fit 0) passes every shape through its transferred bundles."""
    from lgi.index.build import LGIIndex
    from lgi.retarget.template import TemplateTransfer
    from lgi.solve.solver import LGISolver

    d, actor = setup["dir"], setup["actor"]
    template, solver = ShapeDataset.load(d / "template"), LGISolver(LGIIndex.load(d / "index"))
    tt = TemplateTransfer(template, solver, "scale")
    rig = tt.generate(list(A.CONTROLS), setup["pairs"])
    eye = np.eye(len(A.CONTROLS))
    truth = [actor.evaluate(eye[k]) for k in range(len(A.CONTROLS))]

    def pooled(shapes) -> float:
        return float(np.sqrt(np.mean([np.mean(np.sum((s - t) ** 2, axis=1)) for s, t in zip(shapes, truth,
                                                                                              strict=True)])))

    ours = pooled(rig.shapes)
    assert ours <= 0.5 * pooled([tt.naive((c,)) for c in A.CONTROLS])
    assert ours < pooled([tt.transferred((c,)) for c in A.CONTROLS])
    exact = TemplateTransfer(template, solver, "scale", fit_mm=0.0).generate(list(A.CONTROLS))
    assert exact.residual_mm.max() < 1e-3
    # The rig at both controls of a corrective reproduces the reconstructed combination.
    for i, (a, b) in enumerate(setup["pairs"]):
        np.testing.assert_allclose(rig.evaluate({a: 1.0, b: 1.0}), rig.combinations[i], atol=1e-4)
    # The jaw opening's corrective (a pucker with the jaw open) is the actor's: closer to its true corrective
    # than to none at all.
    a, b = setup["pairs"][0]
    x0 = actor.neutral
    true = actor.evaluate(eye[A.C[a]] + eye[A.C[b]]) - actor.evaluate(eye[A.C[a]]) - actor.evaluate(eye[A.C[b]]) + x0
    assert np.linalg.norm(rig.corrective_deltas[0] - true) < 0.5 * np.linalg.norm(true)
    # The jaw as the rig's joint: unskinned, each control skinned with its own jaw pose is its generated shape,
    # and a combination skinned with its pose is the combination; the opening's rotation leaves its blend shape.
    u, e = rig.unskinned(tt.rig)
    for k in range(len(A.CONTROLS)):
        np.testing.assert_allclose(tt.rig.skin(x0 + u[k], rig.jaw[k]), rig.shapes[k], atol=1e-4)
    for i, (a, b) in enumerate(setup["pairs"]):
        whole = x0 + u[A.C[a]] + u[A.C[b]] + e[i]
        np.testing.assert_allclose(tt.rig.skin(whole, rig.jaw[len(A.CONTROLS) + i]), rig.combinations[i], atol=1e-4)
    k = A.C["jaw_open"]
    assert rig.jaw[k, 0] > 15.0 and np.abs(rig.jaw[A.C["smile_L"]]).max() < 0.5
    assert np.linalg.norm(u[k], axis=1).max() < 0.3 * np.linalg.norm(rig.shapes[k] - x0, axis=1).max()


def test_a_template_from_the_command_line(setup, tmp_path: Path) -> None:
    """``lgi synth --template`` writes the default actor's 13 named controls and 24 combination shapes on the mesh;
    rig-generate takes them (auto: the template's combinations) with no --controls. Given the actor's own
    47-shape dataset as the template, the default controls leave out its in-betweens (``_50``) and its tagged
    combinations (``smile_LR``): the 13 extremes."""
    from lgi.synthetic.actor import TEMPLATE_PAIRS

    d = setup["dir"]
    assert main(["synth", "--out", str(tmp_path / "s"), "--vertices", str(N_VERTICES), "--frames", "2",
                 "--template", "-q"]) == 0
    template = ShapeDataset.load(tmp_path / "s" / "template", verify=True)
    assert template.names[:13] == list(A.CONTROLS) and len(template.names) == 13 + TEMPLATE_PAIRS
    assert all(n.count("+") == 1 for n in template.names[13:])
    r = run("rig-generate", "--template", str(tmp_path / "s" / "template"), "--index", str(d / "index"), "--out",
            str(tmp_path / "rig"), "--correctives", "auto", "-q")
    assert r.returncode == 0, r.stderr
    rig = ShapeDataset.load(tmp_path / "rig")
    assert rig.names[:13] == list(A.CONTROLS) and set(rig.names[13:]) <= set(template.names[13:])
    assert len(rig.names) > 13 + TEMPLATE_PAIRS // 2  # the template's combinations, less any that move nothing
    r = run("rig-generate", "--template", str(d / "actor" / "dataset"), "--index", str(d / "index"), "--out",
            str(tmp_path / "rig47"), "-q")
    assert r.returncode == 0, r.stderr
    assert ShapeDataset.load(tmp_path / "rig47").names == list(A.CONTROLS)


def test_correctives_that_move_nothing_are_left_out(setup, tmp_path: Path) -> None:
    """Brow and jaw move apart on the synthetic face: their correctives are zero, so they are left out of the rig
    dataset and its USD, and the run says which; the jaw-and-pucker corrective stays."""
    pytest.importorskip("pxr")
    from pxr import Usd, UsdSkel

    d = setup["dir"]
    r = run("rig-generate", "--template", str(d / "template"), "--index", str(d / "index"), "--out",
            str(tmp_path / "rig"), "--correctives", "jaw_open+brow_raise_L,jaw_open+brow_raise_R,jaw_open+pucker",
            "--usd", str(tmp_path / "rig.usdc"))
    assert r.returncode == 0, r.stderr
    assert "2 correctives left out: jaw_open+brow_raise_L, jaw_open+brow_raise_R" in r.stderr
    assert "13 controls, 1 correctives" in r.stdout
    ds = ShapeDataset.load(tmp_path / "rig", verify=True)
    assert ds.names[13:] == ["jaw_open+pucker"]
    stage = Usd.Stage.Open(str(tmp_path / "rig.usdc"))
    mesh = stage.GetPrimAtPath("/Rig/Face")
    assert len(UsdSkel.BindingAPI(mesh).GetBlendShapesAttr().Get()) == 14


def test_a_combination_outside_the_actors_dataset_takes_the_templates_corrective(setup, caplog) -> None:
    """smile_L+cheek_puff deepens the nasolabial fold beyond any shape of the actor's dataset: its bundles lie
    outside their clouds, so its corrective is the template's (transferred), and a warning says so; the jaw
    opening with a pucker is in the dataset and is reconstructed."""
    from lgi.index.build import LGIIndex
    from lgi.retarget.template import TemplateTransfer
    from lgi.solve.solver import LGISolver

    d = setup["dir"]
    template, solver = ShapeDataset.load(d / "template"), LGISolver(LGIIndex.load(d / "index"))
    with caplog.at_level("WARNING"):
        rig = TemplateTransfer(template, solver, "scale").generate(list(A.CONTROLS), setup["pairs"])
    assert rig.corrective_source == ["actor", "template"]
    assert rig.projection_mm[-1] > 2.0 >= rig.projection_mm[-2]
    assert any("smile_L+cheek_puff" in r.getMessage() and "template's" in r.getMessage() for r in caplog.records)
    tt = TemplateTransfer(template, solver, "scale")
    expected = tt.transferred(setup["pairs"][1]) - sum(tt.transferred((c,)) for c in setup["pairs"][1]) + \
        tt.neutral
    np.testing.assert_allclose(rig.corrective_deltas[1], expected, atol=1e-5)
    always = TemplateTransfer(template, solver, "scale", coverage_mm=np.inf).generate(list(A.CONTROLS), setup["pairs"])
    assert always.corrective_source == ["actor", "actor"]


def test_cli_writes_a_tagged_dataset_and_a_usd_that_reads_back(setup, tmp_path: Path) -> None:
    pytest.importorskip("pxr")
    d = setup["dir"]
    out, usd = tmp_path / "rig", tmp_path / "rig.usda"
    r = run("rig-generate", "--template", str(d / "template"), "--index", str(d / "index"), "--out", str(out),
            "--correctives", "pucker+jaw_open,smile_L+cheek_puff+pucker", "--usd", str(usd), "-q")
    assert r.returncode == 0, r.stderr
    assert "13 controls, 2 correctives" in r.stdout
    ds = ShapeDataset.load(out, verify=True)
    assert ds.names[:13] == list(A.CONTROLS) and ds.names[13:] == ["pucker+jaw_open", "smile_L+cheek_puff+pucker"]
    assert [m.tags for m in ds.shape_meta][12:] == [["control"], ["corrective", "combination"]] + \
        [["corrective", "combination"]]
    # The template's combination shape is found whatever the order of the parts.
    assert ds.shape_meta[13].extra["template"] == "combination shape jaw_open+pucker"
    assert ds.shape_meta[14].extra["template"] == "sum of parts"
    assert ds.shape_meta[13].extra["corrective_from"] == "actor"
    from pxr import Usd, UsdGeom, UsdSkel

    stage = Usd.Stage.Open(str(usd))
    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath("/Rig/Face"))
    tokens = list(binding.GetBlendShapesAttr().Get())
    assert tokens == [*A.CONTROLS, "pucker__jaw_open", "smile_L__cheek_puff__pucker"]
    query = UsdSkel.BlendShapeQuery(binding)
    assert query.GetNumBlendShapes() == len(ds.names)
    for k, target in enumerate(binding.GetBlendShapeTargetsRel().GetTargets()):
        prim = stage.GetPrimAtPath(target)
        offsets = np.asarray(UsdSkel.BlendShape(prim).GetOffsetsAttr().Get())
        np.testing.assert_allclose(offsets, ds.deltas[k], atol=1e-6)
        assert prim.GetAttribute("lgi:name").Get() == ds.names[k]
    combo = stage.GetPrimAtPath("/Rig/Face/pucker__jaw_open").GetAttribute("lgi:combination").Get()
    assert list(combo) == ["pucker", "jaw_open"]
    points = np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath("/Rig/Face")).GetPointsAttr().Get())
    np.testing.assert_allclose(points, ds.neutral, atol=1e-5)
    # The index has a jaw rig: the dataset carries it (its shapes unskinned, each control's jaw pose in its
    # metadata) and the USD's skeleton has the jaw joint at its hinge, the mesh bound with weights [1 - w, w].
    from lgi.solve.jaw import JawRig

    index_rig = JawRig.load(d / "actor" / "jaw_rig.npz")
    np.testing.assert_allclose(ds.jaw_pivot, index_rig.pivot)
    np.testing.assert_allclose(ds.jaw_weights, index_rig.weights)
    assert ds.shape_meta[A.C["jaw_open"]].extra["jaw"][0] > 15.0
    skel = UsdSkel.Skeleton(stage.GetPrimAtPath("/Rig/Skel"))
    assert list(skel.GetJointsAttr().Get()) == ["root", "root/jaw"]
    np.testing.assert_allclose(skel.GetBindTransformsAttr().Get()[1].ExtractTranslation(), index_rig.pivot, atol=1e-6)
    assert binding.GetJointWeightsPrimvar().GetElementSize() == 2
    w = np.asarray(binding.GetJointWeightsPrimvar().Get()).reshape(-1, 2)
    np.testing.assert_allclose(w[:, 1], index_rig.weights, atol=1e-7)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-6)
    jaw = stage.GetPrimAtPath("/Rig/Face/jaw_open").GetAttribute("lgi:jaw").Get()
    np.testing.assert_allclose(list(jaw), ds.shape_meta[A.C["jaw_open"]].extra["jaw"], atol=1e-5)


@pytest.mark.parametrize("case, words", [
    ("vertex_count", ["vertices", "topology"]),
    ("unknown_control", ["'frown'", "not among the controls"]),
    ("one_part", ["two or three"]),
    ("usd_inside", ["inside the rig's dataset directory"]),
    ("usd_suffix", [".usda"]),
    ("controls_typo", ["'smle_R'", "matches no template shape"]),
    ("usd_names_clash", ["'smile.L'", "'smile_L'", "same USD name"]),
    ("template_in_mm", ["scales by", "other units"]),
])
def test_bad_input_is_refused_cleanly(setup, tmp_path: Path, case: str, words: list[str]) -> None:
    d = setup["dir"]
    template = d / "template"
    out = tmp_path / "rig"
    extra: list[str] = []
    if case == "vertex_count":
        small = A.make_dataset(A.make_actor(1000), ["smile_L"], np.eye(len(A.CONTROLS))[[A.C["smile_L"]]])
        template = tmp_path / "small"
        small.save(template)
    elif case == "unknown_control":
        extra = ["--correctives", "smile_L+frown"]
    elif case == "one_part":
        extra = ["--correctives", "smile_L"]
    elif case == "controls_typo":
        extra = ["--controls", "smile_L,smle_R"]
    elif case in ("usd_names_clash", "template_in_mm"):
        eye = np.eye(len(A.CONTROLS))
        ds = A.make_dataset(A.make_actor(N_VERTICES), ["smile.L", "smile_L"], eye[[A.C["smile_L"], A.C["smile_R"]]])
        if case == "template_in_mm":  # the numbers of a mm template labelled cm
            ds.neutral = ds.neutral * 10
            ds.deltas = ds.deltas * 10
        template = tmp_path / "tpl"
        ds.save(template)
        extra = ["--usd", str(tmp_path / "rig.usda")]
    elif case == "usd_inside":
        extra = ["--usd", str(out / "rig.usda")]
    else:
        extra = ["--usd", str(tmp_path / "rig.obj")]
    r = run("rig-generate", "--template", str(template), "--index", str(d / "index"), "--out", str(out), *extra)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    for w in words:
        assert w in r.stderr, r.stderr
    assert not out.exists() and not list(tmp_path.glob("rig*")) and not list(tmp_path.glob(".rig*"))
