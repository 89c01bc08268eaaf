"""The review page's rig map (lgi review --rig-solve): where the actor's rig, played with lgi rig-solve's curves,
falls short of the reconstruction, per vertex and frame."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from test_review import _payload, _pixels, browser  # noqa: F401 - the browser fixture, shared

from lgi.cli import main
from lgi.review.pack import NOT_MEASURED, TOP_WITH_GAPS, unblob
from lgi.synthetic import actor as A

N_VERTICES = 2000
FRAMES = 12


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    """Actor 1's 12-frame shot reconstructed, its rig generated from the default actor's controls, the shot
    solved onto it, and the review page with the rig map."""
    t = tmp_path_factory.mktemp("review_rig")
    A.make_dataset(A.make_actor(N_VERTICES), list(A.CONTROLS), np.eye(len(A.CONTROLS))).save(t / "template")
    assert main(["synth", "--out", str(t / "actor"), "--vertices", str(N_VERTICES), "--frames", str(FRAMES),
                 "--actor", "1", "-q"]) == 0
    assert main(["build", str(t / "actor" / "dataset"), "--markers", str(t / "actor" / "markers.csv"), "--jaw-rig",
                 str(t / "actor" / "jaw_rig.npz"), "--out", str(t / "index"), "-q"]) == 0
    assert main(["reconstruct", str(t / "index"), "--bundles", str(t / "actor" / "bundles.csv"), "--out",
                 str(t / "rec"), "-q"]) == 0
    assert main(["rig-generate", "--template", str(t / "template"), "--index", str(t / "index"), "--out",
                 str(t / "rig"), "-q"]) == 0
    assert main(["rig-solve", str(t / "rec"), "--rig", str(t / "rig"), "--out", str(t / "solve"), "-q"]) == 0
    assert main(["review", str(t / "rec"), "--index", str(t / "index"), "--rig-solve", str(t / "solve"), "--out",
                 str(t / "page")]) == 0
    return t


def _rig_map(t) -> tuple[dict, np.ndarray]:
    m = next(mp for mp in _payload(t / "page" / "review_frames.js")["maps"] if mp["key"] == "rig")
    blocks = sorted((t / "page" / "frames").glob("block_*.html"))
    return m, np.concatenate([unblob(_payload(b)["maps"]["rig"]) for b in blocks])


def test_rig_map_is_the_solve_residual(solved):
    """Per frame, the map's largest value is rig-solve's own max residual (to a code step), its RMS curve is
    rig-solve's RMS, and the vertices outside the rig's face region are "not measured", never 0 mm."""
    from lgi.io.npz import load_npz

    t = solved
    m, codes = _rig_map(t)
    # Over more than one block: each block's frames are played from their own frames' curves.
    assert len(list((t / "page" / "frames").glob("block_*.html"))) > 1
    region = load_npz(t / "solve" / "vertex_error.npz")["region"].astype(bool)
    assert codes.shape == (FRAMES, region.size)
    assert 0 < region.sum() < region.size
    assert np.all(codes[:, ~region] == NOT_MEASURED)
    assert np.all(codes[:, region] <= TOP_WITH_GAPS)
    res = pd.read_csv(t / "solve" / "residuals.csv")
    step = m["vmax_mm"] / TOP_WITH_GAPS
    top = codes[:, region].max(axis=1) * step
    capped = res.max_mm.to_numpy() >= m["vmax_mm"]
    assert np.all(np.abs(top - np.minimum(res.max_mm.to_numpy(), m["vmax_mm"]))[~capped] <= step / 2 + 1e-4)
    meta = _payload(t / "page" / "review_meta.js")
    curve = unblob(next(c for c in meta["curves"] if c["key"] == "rig_rms")["values"])
    assert np.allclose(curve, res.rms_mm.to_numpy(), atol=2e-5)
    rows = dict((label, text) for label, text in meta["summary"] if label != "report")
    assert "RMS" in rows["rig playback"] and str(t / "rig") in rows["rig solve"]


def test_rig_map_bad_input(solved, tmp_path, capsys):
    t = solved
    base = ["review", str(t / "rec"), "--index", str(t / "index")]
    # --rig alone
    assert main([*base, "--rig", str(t / "rig"), "--out", str(tmp_path / "a")]) == 2
    assert "--rig goes with --rig-solve" in capsys.readouterr().err
    # not rig-solve's folder
    assert main([*base, "--rig-solve", str(t / "rec"), "--out", str(tmp_path / "b")]) == 2
    assert "solve.json" in capsys.readouterr().err
    # curves of another shot (its frames shifted)
    other = tmp_path / "other"
    other.mkdir()
    (other / "solve.json").write_text((t / "solve" / "solve.json").read_text())
    c = pd.read_csv(t / "solve" / "curves.csv")
    c.assign(frame=c.frame + 100).to_csv(other / "curves.csv", index=False)
    assert main([*base, "--rig-solve", str(other), "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "curves.csv" in err and "another shot" in err
    assert not any((tmp_path / n).exists() for n in ("a", "b", "c"))


def test_rig_map_in_the_browser(browser, solved, tmp_path):  # noqa: F811
    pg = browser.new_page(viewport={"width": 1000, "height": 700}, device_scale_factor=1, bypass_csp=True)
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto((solved / "page" / "index.html").resolve().as_uri())
    pg.wait_for_function("window.lgiReview && (window.lgiReview.idle || window.lgiReview.error)",
                         timeout=60_000)
    assert pg.evaluate("window.lgiReview.error") is None and errors == []
    pg.uncheck("#showMarkers")
    pg.evaluate(f"window.lgiReview.setFrame({FRAMES - 1})")
    shaded = _pixels(pg.locator("#gl").screenshot())
    pg.select_option("#map", "rig")
    coloured = _pixels(pg.locator("#gl").screenshot(path=str(tmp_path / "rig_map.png")))
    assert np.any(np.abs(coloured - shaded) > 20, axis=2).mean() > 0.05
    assert "outside the rig's face region" in pg.evaluate("window.lgiReview.mapNote()")
    pg.close()
