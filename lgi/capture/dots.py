"""Painted-dot detection in grey images: blobs with sub-pixel centres.

Dots are dark paint on lit skin. A morphological black-hat (closing minus image) with a kernel larger
than a dot keeps dark features smaller than the kernel and removes the shading, large dark regions
(eyes, mouth) and bright highlights; it is thresholded and split into connected components. A component
is kept as a dot if its area, elongation, fill and contrast are those of a dot and it does not touch a
saturated (specular) pixel; its centre is the black-hat-weighted centroid, to a fraction of a pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit


@dataclass
class DotOptions:
    """Detection parameters (pixels, grey levels 0-255).

    ``kernel`` must exceed the largest dot's diameter; ``threshold`` is the black-hat level that makes a
    pixel part of a blob; ``min_contrast`` the level its darkest pixel must reach.
    """

    kernel: int = 17
    threshold: int = 14
    min_contrast: int = 30
    min_area: int = 6
    max_area: int = 260
    max_aspect: float = 2.5
    min_fill: float = 0.4
    saturation: int = 250

    @classmethod
    def for_size(cls, diameter_px: float) -> DotOptions:
        """Options for dots of about ``diameter_px`` pixels (the defaults are for
        :data:`~lgi.capture.settings.DOT_SIZE_PX`)."""
        k = int(round(1.9 * diameter_px)) | 1
        return cls(kernel=max(k, 5), min_area=max(int(round(0.075 * diameter_px**2)), 3),
                   max_area=int(np.ceil(3.2 * diameter_px**2)))


@dataclass
class Dots:
    """Detected dots of one image.

    Attributes
    ----------
    xy : (N, 2) float64, pixels (sub-pixel centres)
    area : (N,) int32, pixels
    contrast : (N,) float32, grey levels
    rejected : dict reason -> count of blobs rejected for it
    """

    xy: np.ndarray
    area: np.ndarray
    contrast: np.ndarray
    rejected: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.xy)


@njit(cache=True)
def _centroids(resp: np.ndarray, labels: np.ndarray, stats: np.ndarray, keep: np.ndarray, floor: float
               ) -> tuple[np.ndarray, np.ndarray]:
    h, w = resp.shape
    out = np.full((keep.shape[0], 2), np.nan)
    peak = np.zeros(keep.shape[0], np.float32)
    for k in range(keep.shape[0]):
        lab = keep[k]
        x0, y0, bw, bh = stats[lab, 0], stats[lab, 1], stats[lab, 2], stats[lab, 3]
        sx = 0.0
        sy = 0.0
        sw = 0.0
        pk = 0.0
        for y in range(max(y0 - 1, 0), min(y0 + bh + 1, h)):
            for x in range(max(x0 - 1, 0), min(x0 + bw + 1, w)):
                lb = labels[y, x]
                if lb != lab and lb != 0:
                    continue
                v = resp[y, x] - floor
                if v <= 0:
                    continue
                sx += v * x
                sy += v * y
                sw += v
                if resp[y, x] > pk:
                    pk = resp[y, x]
        if sw > 0:
            out[k, 0] = sx / sw
            out[k, 1] = sy / sw
        peak[k] = pk
    return out, peak


def detect_dots(image: np.ndarray, options: DotOptions | None = None) -> Dots:
    """Detect dark dots.

    Parameters
    ----------
    image : (H, W) uint8 grey image

    Returns
    -------
    Dots
    """
    import cv2

    o = options or DotOptions()
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"expected an (H, W) uint8 grey image, got {image.shape} {image.dtype}")
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (o.kernel, o.kernel))
    resp = cv2.morphologyEx(image, cv2.MORPH_BLACKHAT, kernel)
    mask = (resp > o.threshold).view(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=cv2.CV_32S)
    xy, area_k, peak, rejected = _validate(resp, labels, stats, image, o)
    # Blobs too large or misshapen may be a dot touching a darker feature (brow, lip line, eye): split them
    # at a level relative to their own peak and validate the pieces again.
    extra = [np.zeros((0, 2))], [np.zeros(0, np.int32)], [np.zeros(0, np.float32)]
    for lab in np.flatnonzero(~_shape_ok(stats[1:], o) & (stats[1:, cv2.CC_STAT_AREA] >= o.min_area)) + 1:
        x0, y0, bw, bh = (int(v) for v in stats[lab, :4])
        sub = resp[y0:y0 + bh, x0:x0 + bw] * (labels[y0:y0 + bh, x0:x0 + bw] == lab)
        level = 0.6 * float(sub.max())
        if level <= o.threshold:
            continue
        m2 = (sub > level).view(np.uint8)
        _, lab2, st2, _ = cv2.connectedComponentsWithStats(m2, connectivity=8, ltype=cv2.CV_32S)
        xy2, a2, p2, _ = _validate(np.where(sub > level * 0.5, sub, 0).astype(np.uint8), lab2, st2,
                                   image[y0:y0 + bh, x0:x0 + bw], o)
        if len(xy2):
            extra[0].append(xy2 + [x0, y0])
            extra[1].append(a2)
            extra[2].append(p2)
            rejected["split"] = rejected.get("split", 0) + 1
    return Dots(np.vstack([xy, *extra[0]]), np.concatenate([area_k, *extra[1]]),
                np.concatenate([peak, *extra[2]]), rejected)


def _shape_ok(st: np.ndarray, o: DotOptions) -> np.ndarray:
    import cv2

    area = st[:, cv2.CC_STAT_AREA]
    bw, bh = st[:, cv2.CC_STAT_WIDTH], st[:, cv2.CC_STAT_HEIGHT]
    return ((area <= o.max_area) & (np.maximum(bw, bh) <= o.max_aspect * np.minimum(bw, bh))
            & (area >= o.min_fill * bw * bh))


def _validate(resp: np.ndarray, labels: np.ndarray, stats: np.ndarray, image: np.ndarray, o: DotOptions):
    """Centres, areas and contrasts of the components that look like dots, and rejection counts."""
    import cv2

    st = stats[1:]
    area = st[:, cv2.CC_STAT_AREA]
    bw, bh = st[:, cv2.CC_STAT_WIDTH], st[:, cv2.CC_STAT_HEIGHT]
    rejected: dict[str, int] = {}
    ok = np.ones(len(st), bool)

    def reject(cond: np.ndarray, reason: str) -> None:
        nonlocal ok
        hit = ok & cond
        if hit.any():
            rejected[reason] = int(hit.sum())
        ok &= ~cond

    reject(area < o.min_area, "too small")
    reject(area > o.max_area, "too large")
    reject(np.maximum(bw, bh) > o.max_aspect * np.minimum(bw, bh), "elongated")
    reject(area < o.min_fill * bw * bh, "not filled")
    keep = np.flatnonzero(ok) + 1
    xy, peak = _centroids(resp, labels, stats, keep.astype(np.int64), float(o.threshold) * 0.5)
    low = peak < o.min_contrast
    if low.any():
        rejected["low contrast"] = int(low.sum())
    # Specular: a blob touching saturated pixels is the dark rim of a highlight, not paint.
    sat = np.zeros(len(keep), bool)
    if (image >= o.saturation).any():
        bright = cv2.dilate((image >= o.saturation).view(np.uint8), np.ones((3, 3), np.uint8))
        touching = np.unique(labels[bright.astype(bool) & (labels > 0)])
        sat = np.isin(keep, touching) & ~low
        if sat.any():
            rejected["specular"] = int(sat.sum())
    good = ~low & ~sat & np.all(np.isfinite(xy), axis=1)
    return xy[good], area[keep[good] - 1].astype(np.int32), peak[good], rejected
