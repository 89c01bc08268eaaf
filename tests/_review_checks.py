"""Checks of the review page shared by its Chromium and Firefox tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pandas as pd


def check_marker_colours(img: np.ndarray, screen: np.ndarray, rows: pd.DataFrame, markers: list[str],
                         status_colour: Callable[[str], list[float]]) -> tuple[set[str], np.ndarray]:
    """Assert that every marker with room around it is drawn in its status colour.

    Parameters
    ----------
    img : (H, W, 3) int16
        The canvas, 0-255.
    screen : (M, 2) float
        Each marker's position on the canvas, CSS pixels.
    rows : DataFrame
        The frame's rows of ``diagnostics.csv``, indexed by marker.
    markers : list of M str
        The page's marker names.
    status_colour : callable
        The page's colour (3 floats in [0, 1]) of a status.

    Returns
    -------
    The statuses checked, and the markers with room around them (indices).
    """
    checked: set[str] = set()
    gaps = np.linalg.norm(screen[:, None] - screen[None], axis=2) + np.eye(len(markers)) * 1e9
    roomy = np.flatnonzero(gaps.min(axis=1) > 14)
    for m in roomy:
        status = rows.loc[markers[m], "status"]
        if rows.loc[markers[m]].get("constraint", "") == "ray":
            status = "ray"
        want = np.round(np.array(status_colour(status)) * 255)
        x, y = np.round(screen[m]).astype(int)
        if not (2 <= x < img.shape[1] - 2 and 2 <= y < img.shape[0] - 2):
            continue
        got = img[y - 1:y + 2, x - 1:x + 2].reshape(-1, 3)
        assert np.abs(got - want).max(axis=1).min() <= 3, (markers[m], status, got, want)
        checked.add(status)
    return checked, roomy


#: Names a received file could carry into the page, each of which would run script if it reached the DOM as markup
#: (an inline handler; the end of a script element) and sets ``window.__pwned`` if it runs.
HOSTILE = ("<img src=x onerror=window.__pwned=1>", "</script><script>window.__pwned=2</script>")


def hostile_page(folder) -> dict:
    """A small synthetic shot whose marker names, diagnostics column names, shape names (a text column's values),
    reconstruction folder's name and ``--jaw`` option's file name are :data:`HOSTILE` (file names: the first, a
    slash being no part of one), reconstructed and its review page written; returns the paths."""
    from pathlib import Path

    from lgi.cli import main

    w = Path(folder)
    assert main(["synth", "--out", str(w / "s"), "--vertices", "1500", "--frames", "4", "-q"]) == 0
    layout = pd.read_csv(w / "s" / "markers.csv", dtype=str, keep_default_na=False)
    rename = {layout.loc[i, "name"]: name for i, name in enumerate(HOSTILE)}
    layout["name"] = layout["name"].replace(rename)
    layout.to_csv(w / "s" / "markers.csv", index=False)
    bundles = pd.read_csv(w / "s" / "bundles.csv", dtype=str, keep_default_na=False)
    bundles["marker"] = bundles["marker"].replace(rename)
    bundles.to_csv(w / "bundles.csv", index=False)
    jaw = w / f"{HOSTILE[0]}.csv"  # an option's value
    jaw.write_text("frame,open_deg,yaw_deg,roll_deg,forward_cm\n" + "".join(f"{f},2,0,0,0\n" for f in range(4)))
    rec = w / HOSTILE[0]  # a folder's name
    assert main(["build", str(w / "s" / "dataset"), "--markers", str(w / "s" / "markers.csv"), "--jaw-rig",
                 str(w / "s" / "jaw_rig.npz"), "--out", str(w / "idx"), "-q"]) == 0
    assert main(["reconstruct", str(w / "idx"), "--bundles", str(w / "bundles.csv"), "--jaw", str(jaw), "--out",
                 str(rec), "-q"]) == 0
    d = pd.read_csv(rec / "diagnostics.csv", dtype=str, keep_default_na=False)
    for name in HOSTILE:
        d[name] = "1.5"  # a column name
    d["shapes"] = HOSTILE[1] + ";" + HOSTILE[0]  # shape names
    d.to_csv(rec / "diagnostics.csv", index=False)
    assert main(["review", str(rec), "--index", str(w / "idx"), "--out", str(w / "page")]) == 0
    return {"page": w / "page" / "index.html", "jaw": jaw, "rec": rec}


#: The page's script that shows every hostile name: each marker pinned on every frame, under every colour map;
#: returns what ran (``window.__pwned``) and the text the panels show.
SHOW_HOSTILE = """(async () => {
  const api = window.lgiReview, shown = [];
  for (const map of ["none", ...api.maps]) {
    api.setMap(map);
    for (let f = 0; f < api.nFrames; f++) {
      await api.setFrame(f);
      for (const m of [0, 1]) { api.pinMarker(m); shown.push(document.getElementById("marker").textContent); }
    }
  }
  return {pwned: window.__pwned === undefined ? null : window.__pwned, marker: shown.join("\\n"),
          summary: document.getElementById("summary").textContent};
})()"""


def check_nothing_ran(result: dict, made: dict) -> None:
    """What :data:`SHOW_HOSTILE` returned for :func:`hostile_page`'s page: no script ran, and each name is shown
    as the text it is."""
    assert result["pwned"] is None, result["pwned"]
    for name in HOSTILE:
        assert name in result["marker"]  # the marker's name, the column's name, the shapes' names: as text
    assert str(made["rec"]) in result["summary"] and f"jaw={made['jaw']}" in result["summary"]
