"""Arrays packed for the review page: quantised, optionally gzip-compressed, base64 in ``.js`` files.

A page opened from ``file://`` cannot ``fetch`` files beside it in Chromium, but it can run scripts beside it:
each data file is a script that assigns a JSON object whose blobs are base64 text. The page decodes a blob into
a typed array (gzip through the browser's own ``DecompressionStream``), so a shot of 1000 frames of a 27k-vertex
mesh is tens of megabytes of script instead of hundreds of megabytes of JSON numbers.
"""

from __future__ import annotations

import base64
import gzip
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: Largest magnitude an int16 code takes (symmetric, so that 0 is exact).
INT16_MAX = 32767


@dataclass(frozen=True)
class QuantisedFrames:
    """A shot's vertices as int16 displacements from a rest mesh, only for the vertices that move.

    Attributes
    ----------
    rest : (V, 3) float32, cm
        The mesh the displacements are from (the index's neutral).
    moving : (K,) int32
        Vertices whose quantised displacement is non-zero in some frame (the others stay at ``rest``).
    codes : (F, K, 3) int16
        Displacement of each moving vertex, in units of ``scale``.
    scale : float, cm
        Size of one code step; the round trip error is at most ``scale / 2`` per coordinate.
    """

    rest: np.ndarray
    moving: np.ndarray
    codes: np.ndarray
    scale: float

    @property
    def error_bound_cm(self) -> float:
        """Largest per-coordinate error of :func:`dequantise_frames` against the input (cm)."""
        return self.scale / 2


def quantise_frames(vertices: np.ndarray, rest: np.ndarray, step: float = 0.0) -> QuantisedFrames:
    """Quantise ``vertices`` (F, V, 3) cm as int16 displacements from ``rest`` (V, 3) cm.

    One scale for the shot: ``step`` cm, or the shot's largest displacement over the largest code when that is
    coarser (a face moving by 3 cm fits steps of 1 um). The page's size is mostly these codes, and the bits
    below a few um are the solve's own jitter, which does not compress: 10 um steps take a 1000-frame ICT shot
    from about 55 to 29 MB (measured). Vertices that never move by half a step are left out (the back of the
    head, the neck).
    """
    v = np.asarray(vertices)
    r = np.asarray(rest, np.float32)
    if v.ndim != 3 or v.shape[1:] != r.shape or r.shape[-1:] != (3,):
        raise ValueError(f"vertices {v.shape} and rest mesh {r.shape} differ in shape")
    # In float64 and in chunks of frames: a 1000-frame ICT shot is 320 MB of float32, and whole-shot
    # temporaries of it in float64 made this the slowest part of lgi review.
    chunks = [slice(lo, lo + 50) for lo in range(0, len(v), 50)]
    big = max((float(np.abs(v[c].astype(np.float64) - r).max()) for c in chunks), default=0.0) if v.size else 0.0
    scale = max(big / INT16_MAX, float(step)) if big > 0 else max(float(step), 1e-6)
    codes = np.empty(v.shape, np.int16)
    for c in chunks:
        codes[c] = np.rint((v[c].astype(np.float64) - r) / scale)
    moving = np.flatnonzero(np.any(codes != 0, axis=(0, 2))).astype(np.int32)
    return QuantisedFrames(r, moving, np.ascontiguousarray(codes[:, moving]), scale)


def dequantise_frames(q: QuantisedFrames) -> np.ndarray:
    """(F, V, 3) float32 cm: the vertices :func:`quantise_frames` stored (what the page shows)."""
    out = np.repeat(q.rest[None].astype(np.float32), q.codes.shape[0], axis=0)
    out[:, q.moving] += q.codes.astype(np.float32) * np.float32(q.scale)
    return out


def encode_codes(codes: np.ndarray) -> np.ndarray:
    """(F, K, 3) int16 codes as the bytes the page stores: frame-to-frame differences (wrapping in int16, so the
    page's running sum in an ``Int16Array`` restores them exactly), low bytes then high bytes. Smooth motion makes
    small differences whose high bytes are mostly 0 or 255: gzip then takes the frames to about 60 % of its size
    on the codes themselves (measured on the 300-frame synthetic shot)."""
    c = np.ascontiguousarray(codes, np.int16)
    d = c.astype(np.int32)
    d[1:] -= c[:-1]
    b = d.astype(np.int16).astype("<i2").view(np.uint8).reshape(-1, 2)
    return np.concatenate([b[:, 0], b[:, 1]])


def decode_codes(data: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """The codes of :func:`encode_codes` (what the page computes)."""
    n = data.size // 2
    d = (data[:n].astype(np.uint16) | (data[n:].astype(np.uint16) << 8)).view(np.int16).reshape(shape)
    return np.cumsum(d, axis=0, dtype=np.int16) if d.size else d


def quantise_map(values: np.ndarray, vmax: float, top: int = 255) -> np.ndarray:
    """A colour map's values (any shape, mm) as uint8 codes over [0, vmax] (clamped; NaN becomes 0). The page
    reads code k <= top as k / top * vmax mm; ``top`` below 255 leaves the codes above it for "no value"
    (:data:`NOT_COVERED`, :data:`NOT_MEASURED`)."""
    v = np.nan_to_num(np.asarray(values, np.float64), nan=0.0)
    return np.rint(np.clip(v / max(vmax, 1e-12), 0.0, 1.0) * top).astype(np.uint8)


def colour_top(values: np.ndarray) -> float:
    """Top of a colour map's bar (mm) for ``values`` (any shape, mm): their 99.9th percentile, so that one wild
    vertex does not wash the whole shot into one colour (the largest value when that is 0; 1e-3 with none)."""
    finite = np.asarray(values)[np.isfinite(values)]
    top = float(np.percentile(finite, 99.9)) if finite.size else 0.0
    return top if top > 0 else max(float(finite.max()) if finite.size else 0.0, 1e-3)


#: Codes of a map with missing values (the scan map): values take 0..TOP_WITH_GAPS, and two codes above say why a
#: vertex has none. The page paints them in colours outside its ramp, so a gap never reads as 0 mm.
TOP_WITH_GAPS = 253
NOT_COVERED = 254
NOT_MEASURED = 255


def quantise_gaps(values: np.ndarray, covered: np.ndarray, measured: np.ndarray, vmax: float) -> np.ndarray:
    """Codes of a map with gaps: ``values`` (any shape, mm) over [0, vmax] as 0..:data:`TOP_WITH_GAPS` where
    ``covered``; :data:`NOT_COVERED` where ``measured`` but not covered (the scan has no surface there: a hole,
    its outline); :data:`NOT_MEASURED` where not ``measured`` (outside the compared region)."""
    codes = quantise_map(values, vmax, TOP_WITH_GAPS)
    codes[~covered] = NOT_COVERED
    codes[~measured] = NOT_MEASURED
    return codes


def blob(array: np.ndarray, compress: bool = True) -> dict[str, Any]:
    """A typed array for the page: little-endian bytes, gzip-compressed when ``compress``, base64 text."""
    a = np.ascontiguousarray(array)
    kinds = {np.dtype(t): n for t, n in ((np.uint8, "u1"), (np.int8, "i1"), (np.uint16, "u2"), (np.int16, "i2"),
                                         (np.int32, "i4"), (np.uint32, "u4"), (np.float32, "f4"))}
    if a.dtype not in kinds:
        raise TypeError(f"no page type for {a.dtype}")
    raw = a.astype(a.dtype.newbyteorder("<"), copy=False).tobytes()
    if compress:
        # mtime 0: the same arrays always give the same page bytes.
        raw = gzip.compress(raw, compresslevel=6, mtime=0)
    return {"dtype": kinds[a.dtype], "shape": list(a.shape), "gzip": bool(compress),
            "b64": base64.b64encode(raw).decode("ascii")}


def unblob(b: dict[str, Any]) -> np.ndarray:
    """The array of :func:`blob` (for tests and the benchmark)."""
    raw = base64.b64decode(b["b64"])
    if b["gzip"]:
        raw = gzip.decompress(raw)
    return np.frombuffer(raw, np.dtype("<" + b["dtype"])).reshape(b["shape"])


def write_script(path: str | Path, name: str, payload: dict[str, Any]) -> int:
    """Write ``payload`` as a script assigning ``window[name]``; returns its size in bytes. Non-finite numbers
    become null (JSON has none)."""
    text = f"window.{name} = " + json.dumps(_finite(payload), separators=(",", ":"), allow_nan=False) + ";\n"
    data = text.encode("utf-8")
    Path(path).write_bytes(data)
    return len(data)


def _finite(x: Any) -> Any:
    if isinstance(x, float):
        return x if np.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, np.generic):
        return _finite(x.item())
    return x
