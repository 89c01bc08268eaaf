"""The shot review page in Firefox: the checks of the Chromium tests (tests/test_review.py), in Debian's
firefox-esr driven over WebDriver BiDi (tests/_firefox.py), with WebGL on Mesa's llvmpipe in a private Xvfb.

They skip with the reason when Firefox, Xvfb or the ``websockets`` package is missing (``.ci/run`` installs
firefox-esr and xvfb)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from _firefox import FIREFOX, BiDiError, Firefox
from _review_checks import SHOW_HOSTILE, check_marker_colours, check_nothing_ran
from test_review import INJECTED, SCANNED, _pixels, hostile, scanned, shot  # noqa: F401 - fixtures shared with the Chromium tests

READY = "window.lgiReview && (window.lgiReview.idle || window.lgiReview.error)"


@pytest.fixture(scope="module")
def firefox():
    pytest.importorskip("websockets.sync.client", reason="the websockets package is not installed (it comes "
                                                         "with prefect)")
    if not Path(FIREFOX).is_file():
        pytest.skip(f"no firefox at {FIREFOX} (apt-get install -y firefox-esr)")
    try:
        ff = Firefox(width=1100, height=760)
    except BiDiError as exc:
        pytest.skip(f"firefox cannot run here: {exc}")
    yield ff
    ff.close()


@pytest.fixture()
def page(firefox, shot):  # noqa: F811 - pytest's fixture, imported above
    firefox.errors.clear()
    firefox.goto((shot / "page" / "index.html").resolve().as_uri())
    firefox.wait_for(READY)
    return firefox


def _canvas(ff: Firefox, path: Path | None = None) -> np.ndarray:
    # Firefox composites WebGL after the script's task: a screenshot right after a redraw can show the frame
    # before it. Two animation frames later the new one is on screen.
    ff.evaluate("new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
    png = ff.screenshot("#gl")
    if path is not None:
        path.write_bytes(png)
    return _pixels(png)


def _set(ff: Firefox, selector: str, value: str, event: str) -> None:
    """Set a control's value as a user does: the value, then the event the page listens to."""
    ff.evaluate(f"(() => {{ const e = document.querySelector({json.dumps(selector)}); e.value = {json.dumps(value)}; "
                f"e.dispatchEvent(new Event({json.dumps(event)}, {{bubbles: true}})); }})()")


def _uncheck_markers(ff: Firefox) -> None:
    ff.evaluate("(() => { const e = document.querySelector('#showMarkers'); if (e.checked) e.click(); })()")


def test_page_loads_from_file_without_errors(page):
    assert page.evaluate("window.lgiReview.error") is None
    assert page.errors == []
    assert page.evaluate("window.lgiReview.nFrames") == 20
    assert "Firefox" in page.evaluate("navigator.userAgent")


def test_canvas_is_not_blank_and_screenshot_kept(page, tmp_path):
    px = _canvas(page, tmp_path / "review_firefox.png")
    differs = np.any(np.abs(px - px[2, 2]) > 12, axis=2)
    assert differs.mean() > 0.1
    assert len(np.unique(px[differs].reshape(-1, 3), axis=0)) > 50  # shaded, not flat
    assert (tmp_path / "review_firefox.png").stat().st_size > 10_000


def test_slider_changes_the_picture(page, tmp_path):
    _uncheck_markers(page)
    before = _canvas(page)
    _set(page, "#slider", "15", "input")
    assert page.evaluate("window.lgiReview.frame()") == 15
    assert "16/20" in page.evaluate("document.querySelector('#frameLabel').textContent")
    after = _canvas(page, tmp_path / "frame15.png")
    assert np.any(np.abs(after - before) > 12, axis=2).sum() > 200


def test_colour_map_changes_the_colours(page, tmp_path):
    _uncheck_markers(page)
    shaded = _canvas(page)
    for key in ("truth", "correction"):
        _set(page, "#map", key, "change")
        coloured = _canvas(page, tmp_path / f"map_{key}.png")
        assert np.any(np.abs(coloured - shaded) > 20, axis=2).mean() > 0.05
        face = np.any(np.abs(coloured - coloured[2, 2]) > 12, axis=2)
        assert (coloured[face][:, 2] - coloured[face][:, 0]).mean() > 20


def test_marker_status_colour_matches_the_diagnostics(page, shot, tmp_path):  # noqa: F811
    diag = pd.read_csv(shot / "rec" / "diagnostics.csv", keep_default_na=False)
    frames = sorted(diag.frame.unique())
    markers = page.evaluate("window.LGI_REVIEW_META.markers")
    checked = set()
    for frame_pos in (0, 10, 19):
        page.evaluate(f"window.lgiReview.setFrame({frame_pos})")
        rows = diag[diag.frame == frames[frame_pos]].set_index("marker")
        screen = np.array(page.evaluate(f"[...Array({len(markers)}).keys()].map((m) => "
                                        "window.lgiReview.markerScreen(m))"))
        img = _canvas(page, tmp_path / f"markers_{frame_pos}.png")
        checked |= check_marker_colours(img, screen, rows, markers,
                                        lambda s: page.evaluate(f"window.lgiReview.statusColour('{s}')"))[0]
    assert len(checked) >= 2, checked


def test_clicking_a_curve_jumps_to_its_frame(page):
    box = page.evaluate("(() => { const r = document.querySelector('#curves').getBoundingClientRect(); "
                        "return [r.x, r.y, r.width, r.height]; })()")
    x, y = int(box[0] + box[2] - 8), int(box[1] + box[3] / 2)
    page.send("input.performActions", {"context": page.context, "actions": [{
        "type": "pointer", "id": "mouse", "parameters": {"pointerType": "mouse"},
        "actions": [{"type": "pointerMove", "x": x, "y": y}, {"type": "pointerDown", "button": 0},
                    {"type": "pointerUp", "button": 0}]}]})
    assert page.evaluate("window.lgiReview.frame()") == 19
    page.evaluate("document.querySelector('#back').click()")
    assert page.evaluate("window.lgiReview.frame()") == 18


def test_scan_map(firefox, scanned, tmp_path):  # noqa: F811
    """The scan map (lgi review --scans) paints a scanned frame and says that a frame without a scan has none."""
    ff = firefox
    ff.errors.clear()
    ff.goto((scanned / "page_scans" / "index.html").resolve().as_uri())
    ff.wait_for(READY)
    assert ff.evaluate("window.lgiReview.error") is None and ff.errors == []
    _uncheck_markers(ff)
    ff.evaluate(f"window.lgiReview.setFrame({SCANNED[0]})")
    shaded = _canvas(ff)
    _set(ff, "#map", "scan", "change")
    coloured = _canvas(ff, tmp_path / "scan_map.png")
    assert np.any(np.abs(coloured - shaded) > 20, axis=2).mean() > 0.05
    ff.evaluate("window.lgiReview.setFrame(0)")
    assert "no scan for frame" in ff.evaluate("window.lgiReview.mapNote()")


def test_a_far_frame_loads_its_block(firefox, shot, tmp_path, monkeypatch):  # noqa: F811
    """Firefox too loads a block file from the frames folder on demand (file://): a jump to a frame whose block is
    not loaded draws the overview's nearest frame, then the frame itself when its block arrives."""
    import lgi.jobs.review as job

    monkeypatch.setattr(job, "BLOCK", 2)  # 10 blocks of 2 frames
    job.review(shot / "rec", shot / "idx", tmp_path / "page", job.ReviewOptions())
    ff = firefox
    ff.errors.clear()
    ff.goto((tmp_path / "page" / "index.html").resolve().as_uri())
    ff.wait_for(READY)
    assert ff.evaluate("window.lgiReview.error") is None and ff.errors == []
    assert ff.evaluate("window.lgiReview.blocksHeld()") == [0, 1, 2, 3, 4]
    got = ff.evaluate("(async () => { const p = window.lgiReview.setFrame(15); const at = window.lgiReview.shown(); "
                      "await p; return [at, window.lgiReview.shown()]; })()")
    assert got == [{"frame": 15, "at": 16, "exact": False}, {"frame": 15, "at": 15, "exact": True}]
    assert 7 in ff.evaluate("window.lgiReview.blocksHeld()")


def test_names_in_the_data_run_no_script(firefox, hostile):  # noqa: F811 - pytest's fixture, imported above
    firefox.errors.clear()
    firefox.goto(hostile["page"].resolve().as_uri())
    firefox.wait_for(READY)
    assert firefox.evaluate("window.lgiReview.error") is None
    check_nothing_ran(firefox.evaluate(SHOW_HOSTILE), hostile)
    assert firefox.evaluate(INJECTED) is None
