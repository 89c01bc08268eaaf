"""Numba kernels of the synthetic camera renderer (:mod:`lgi.synthetic.hmc`): z-buffer, shading, painted dots."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def rasterize(uv: np.ndarray, z: np.ndarray, tris: np.ndarray, height: int, width: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Z-buffer triangles projected to ``uv`` (V, 2) px with camera depth ``z`` (V,).

    Returns the depth (H, W) float32 (inf where empty), the triangle id (H, W) int32 (-1 where empty) and
    the screen-space barycentric weights (H, W, 3) float32 of each pixel centre.
    """
    zbuf = np.full((height, width), np.inf, np.float32)
    tid = np.full((height, width), -1, np.int32)
    bary = np.zeros((height, width, 3), np.float32)
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        if not (z[a] > 0 and z[b] > 0 and z[c] > 0):
            continue
        ax, ay, bx, by, cx, cy = uv[a, 0], uv[a, 1], uv[b, 0], uv[b, 1], uv[c, 0], uv[c, 1]
        if not (np.isfinite(ax) and np.isfinite(bx) and np.isfinite(cx)):
            continue
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if abs(area) < 1e-12:
            continue
        x0 = max(int(np.ceil(min(ax, bx, cx))), 0)
        x1 = min(int(np.floor(max(ax, bx, cx))), width - 1)
        y0 = max(int(np.ceil(min(ay, by, cy))), 0)
        y1 = min(int(np.floor(max(ay, by, cy))), height - 1)
        inv = 1.0 / area
        for py in range(y0, y1 + 1):
            for px in range(x0, x1 + 1):
                w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) * inv
                w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) * inv
                w2 = 1.0 - w0 - w1
                if w0 < -1e-9 or w1 < -1e-9 or w2 < -1e-9:
                    continue
                d = w0 * z[a] + w1 * z[b] + w2 * z[c]
                if d < zbuf[py, px]:
                    zbuf[py, px] = d
                    tid[py, px] = t
                    bary[py, px, 0] = w0
                    bary[py, px, 1] = w1
                    bary[py, px, 2] = w2
    return zbuf, tid, bary


@njit(cache=True)
def shade(tid: np.ndarray, bary: np.ndarray, tris: np.ndarray, vertex_value: np.ndarray, vertex_pos: np.ndarray,
          background: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interpolate a per-vertex intensity (V,) and position (V, 3) over the covered pixels.

    Returns the image (H, W) float32 (``background`` where empty) and the surface point (H, W, 3) float32.
    """
    h, w = tid.shape
    img = background.copy()
    pos = np.full((h, w, 3), np.nan, np.float32)
    for y in range(h):
        for x in range(w):
            t = tid[y, x]
            if t < 0:
                continue
            a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
            w0, w1, w2 = bary[y, x, 0], bary[y, x, 1], bary[y, x, 2]
            img[y, x] = w0 * vertex_value[a] + w1 * vertex_value[b] + w2 * vertex_value[c]
            for k in range(3):
                pos[y, x, k] = w0 * vertex_pos[a, k] + w1 * vertex_pos[b, k] + w2 * vertex_pos[c, k]
    return img, pos


@njit(cache=True)
def paint_dots(img: np.ndarray, pos: np.ndarray, centers: np.ndarray, centers_px: np.ndarray, radius: float,
               radius_px: np.ndarray, edge: np.ndarray, albedo: float) -> None:
    """Darken ``img`` in place where the visible surface lies within ``radius`` of a dot centre.

    ``centers`` (D, 3) are the dots in the same frame as ``pos``; ``centers_px`` (D, 2) their projections
    (to bound the work); ``radius_px`` (D,) the projected radius; ``edge`` (D,) the width of the soft edge
    (world units, about one pixel's footprint) so dots are anti-aliased.
    """
    h, w = img.shape
    for d in range(centers.shape[0]):
        cx, cy = centers_px[d, 0], centers_px[d, 1]
        if not (np.isfinite(cx) and np.isfinite(cy)):
            continue
        r = 1.5 * radius_px[d] + 2
        x0, x1 = max(int(cx - r), 0), min(int(cx + r) + 1, w - 1)
        y0, y1 = max(int(cy - r), 0), min(int(cy + r) + 1, h - 1)
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                if not np.isfinite(pos[y, x, 0]):
                    continue
                dx = pos[y, x, 0] - centers[d, 0]
                dy = pos[y, x, 1] - centers[d, 1]
                dz = pos[y, x, 2] - centers[d, 2]
                dist = np.sqrt(dx * dx + dy * dy + dz * dz)
                cover = min(max((radius - dist) / edge[d] + 0.5, 0.0), 1.0)
                if cover > 0:
                    img[y, x] = img[y, x] * (1 - cover) + albedo * img[y, x] * cover
