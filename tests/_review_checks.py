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
