"""Arrays packed for the review page: quantised, optionally gzip-compressed, base64 in ``.js`` files.

A page opened from ``file://`` cannot ``fetch`` files beside it in Chromium, but it can run scripts beside it,
also those it adds later as ``<script>`` tags: each data file is a script that assigns a JSON object (a block of
frames adds itself to a registry, :func:`write_script`) whose blobs are base64 text. The page decodes a blob into
a typed array (gzip through the browser's own ``DecompressionStream``), so a shot of 1000 frames of a 27k-vertex
mesh is tens of megabytes of script instead of hundreds of megabytes of JSON numbers.

A long take is packed a block of frames at a time: what must be the shot's is found first, in a pass over the
blocks (:class:`DisplacementRange` for the quantisation step, :class:`ColourTop` for a colour bar's top), so that
a frame's codes do not depend on the block it is in.
"""

from __future__ import annotations

import base64
import gzip
import hashlib
import json
import math
import re
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: Largest magnitude an int16 code takes (symmetric, so that 0 is exact).
INT16_MAX = 32767
#: Frames converted at a time in float64 (whole-shot float64 temporaries of a 1000-frame ICT shot were the slowest
#: part of lgi review).
QUANTISE_CHUNK = 50


@dataclass(frozen=True)
class QuantisedFrames:
    """A shot's vertices as int16 displacements from a rest mesh, only for the vertices that move: codes in a
    :class:`FrameLayout` (its ``rest``, ``moving`` vertices and ``scale`` are the shot's).

    Attributes
    ----------
    layout : FrameLayout
    codes : (F, K, 3) int16
        Displacement of each moving vertex, in units of ``layout.scale``.
    """

    layout: FrameLayout
    codes: np.ndarray

    rest = property(lambda self: self.layout.rest)
    moving = property(lambda self: self.layout.moving)
    scale = property(lambda self: self.layout.scale)
    error_bound_cm = property(lambda self: self.layout.error_bound_cm)


class DisplacementRange:
    """The largest displacement of each vertex from a rest mesh over a shot seen a block of frames at a time: the
    first pass that fixes the shot's quantisation (:meth:`layout`) before any frame is encoded, so that the codes
    of a frame do not depend on the blocks it was read in.

    Parameters
    ----------
    rest : (V, 3) float, cm
        The mesh the displacements are from (the index's neutral).
    """

    def __init__(self, rest: np.ndarray) -> None:
        self.rest = np.asarray(rest, np.float32)
        if self.rest.ndim != 2 or self.rest.shape[1] != 3:
            raise ValueError(f"rest mesh {self.rest.shape} is not (V, 3)")
        #: (V, 3) float64, cm: per vertex and axis, the largest |vertex - rest| seen so far.
        self.peak = np.zeros(self.rest.shape, np.float64)

    def add(self, vertices: np.ndarray) -> None:
        """Take in a block of frames, ``vertices`` (B, V, 3) cm."""
        v = np.asarray(vertices)
        if v.ndim != 3 or v.shape[1:] != self.rest.shape:
            raise ValueError(f"vertices {v.shape} and rest mesh {self.rest.shape} differ in shape")
        if len(v):
            # float64, as the codes are computed: the same rounding decides what moves.
            np.maximum(self.peak, np.abs(v.astype(np.float64) - self.rest).max(axis=0), out=self.peak)

    def layout(self, step: float = 0.0) -> FrameLayout:
        """The shot's quantisation: one scale, ``step`` cm or the largest displacement over the largest code when
        that is coarser, and the vertices whose code is not 0 in some frame."""
        big = float(self.peak.max()) if self.peak.size else 0.0
        scale = max(big / INT16_MAX, float(step)) if big > 0 else max(float(step), 1e-6)
        # rint(d / scale) != 0 exactly when |d| / scale > 0.5 (a tie rounds to the even 0).
        moving = np.flatnonzero(np.any(self.peak / scale > 0.5, axis=1)).astype(np.int32)
        return FrameLayout(self.rest, moving, scale)


@dataclass(frozen=True)
class FrameLayout:
    """How a shot's frames become int16 codes: displacements from ``rest`` in steps of ``scale``, of the
    ``moving`` vertices only.

    Attributes
    ----------
    rest : (V, 3) float32, cm
    moving : (K,) int32
        Vertices whose code is not 0 in some frame of the shot (the others stay at ``rest``).
    scale : float, cm
        Size of one code step; a position comes back within ``scale / 2`` per coordinate.
    """

    rest: np.ndarray
    moving: np.ndarray
    scale: float

    @property
    def error_bound_cm(self) -> float:
        """Largest per-coordinate error of a position coded and decoded (cm)."""
        return self.scale / 2

    def codes(self, vertices: np.ndarray) -> np.ndarray:
        """(B, K, 3) int16: the codes of a block of frames ``vertices`` (B, V, 3) cm (the same codes whatever the
        block, as the scale is the shot's)."""
        v = np.asarray(vertices)
        return np.rint((v[:, self.moving].astype(np.float64) - self.rest[self.moving]) / self.scale).astype(np.int16)


def quantise_frames(vertices: np.ndarray, rest: np.ndarray, step: float = 0.0) -> QuantisedFrames:
    """Quantise ``vertices`` (F, V, 3) cm as int16 displacements from ``rest`` (V, 3) cm (a shot in memory; ``lgi
    review`` goes through :class:`DisplacementRange` and :class:`FrameLayout` a block of frames at a time, which
    give the same codes).

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
    span = DisplacementRange(r)
    for lo in range(0, len(v), QUANTISE_CHUNK):
        span.add(v[lo:lo + QUANTISE_CHUNK])
    layout = span.layout(step)
    codes = np.empty((len(v), len(layout.moving), 3), np.int16)
    for lo in range(0, len(v), QUANTISE_CHUNK):
        codes[lo:lo + QUANTISE_CHUNK] = layout.codes(v[lo:lo + QUANTISE_CHUNK])
    return QuantisedFrames(layout, codes)


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


def codes_blob(codes: Any, chunk: int = 16) -> dict[str, Any]:
    """``blob(encode_codes(codes))`` for (N, K, 3) int16 ``codes`` read ``chunk`` frames at a time (an array or a
    :class:`~lgi.io.stored.StoredArray`) and compressed as a stream: the memory of a chunk, not of the codes (a
    long take's overview is 256 frames, 32 MB of ICT codes, which :func:`encode_codes` and gzip held three
    times over). The inflated bytes are :func:`encode_codes`'s."""
    n = len(codes)
    comp = zlib.compressobj(6, zlib.DEFLATED, 31)  # 31: a gzip stream, as DecompressionStream("gzip") reads
    parts = []
    for plane in (0, 1):  # all the low bytes, then all the high bytes
        prev = None
        for lo in range(0, n, chunk):
            c = np.ascontiguousarray(codes[lo:lo + chunk], np.int16)
            d = np.empty_like(c)
            np.subtract(c[1:], c[:-1], out=d[1:])  # int16 arithmetic wraps, as the page's running sum undoes
            d[0] = c[0] if prev is None else c[0] - prev
            prev = c[-1].copy()
            planes = d.astype("<i2", copy=False).view(np.uint8).reshape(-1, 2)
            parts.append(comp.compress(np.ascontiguousarray(planes[:, plane])))
    parts.append(comp.flush())
    return {"dtype": "u1", "shape": [2 * n * int(np.prod(codes.shape[1:], dtype=np.int64))], "gzip": True,
            "b64": base64.b64encode(b"".join(parts)).decode("ascii")}


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


#: Float32 bits a :class:`ColourTop` bin leaves out: 12 mantissa bits stay, so a bin spans 2**-12 of its values.
TOP_BIN_SHIFT = 11


class ColourTop:
    """The top of a colour map's bar over a shot's values seen a block at a time, in fixed memory.

    The top is the values' 99.9th percentile, so that one wild vertex does not wash the whole shot into one colour
    (the largest value when that is 0; 1e-3 with none). A histogram of the values' float32 bit patterns, 2**12
    bins per power of two (8 MB), finds it from the tops of the bins of the two values it lies between: at most
    2**-12 (0.025 %) above np.percentile's, whatever the blocks (the page's codes are 1/255 of the bar).
    """

    def __init__(self, q: float = 99.9) -> None:
        self.q = float(q)
        self.counts = np.zeros(1 << (31 - TOP_BIN_SHIFT), np.int64)
        #: Largest finite value seen (mm), 0 with none.
        self.largest = 0.0

    def add(self, values: np.ndarray) -> None:
        """Take in values (any shape, mm, >= 0; NaN and infinities are left out)."""
        v = np.asarray(values, np.float32)
        v = v[np.isfinite(v)]
        if not v.size:
            return
        self.largest = max(self.largest, float(v.max()))
        # Non-negative float32 order as their bit patterns do.
        self.counts += np.bincount(np.maximum(v, 0).view(np.int32) >> TOP_BIN_SHIFT, minlength=len(self.counts))

    def top(self) -> float:
        """The bar's top, mm."""
        n = int(self.counts.sum())
        if n == 0:
            return 1e-3
        # np.percentile's position in the sorted values, between two of them: each is taken as its bin's top.
        pos = self.q / 100 * (n - 1)
        cum = np.cumsum(self.counts)
        lo_bin, hi_bin = (int(np.searchsorted(cum, k + 1)) for k in (math.floor(pos), math.ceil(pos)))
        edges = np.array([(lo_bin + 1) << TOP_BIN_SHIFT, (hi_bin + 1) << TOP_BIN_SHIFT], np.int32).view(np.float32)
        edge = float(edges[0]) + (pos - math.floor(pos)) * float(edges[1] - edges[0])
        top = min(edge, self.largest)
        return top if top > 0 else max(self.largest, 1e-3)


def colour_top(values: np.ndarray) -> float:
    """Top of a colour map's bar (mm) for ``values`` (any shape, mm): their 99.9th percentile (:class:`ColourTop`)."""
    t = ColourTop()
    t.add(values)
    return t.top()


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


def json_blob(value: Any) -> dict[str, Any]:
    """``value`` as JSON text in a gzip-compressed blob (the page parses it after inflating): text that repeats,
    such as the diagnostics' shape lists, packs many times smaller than as JSON strings."""
    return blob(np.frombuffer(json.dumps(_finite(value), separators=(",", ":")).encode("utf-8"), np.uint8))


def unjson_blob(b: dict[str, Any]) -> Any:
    """The value of :func:`json_blob`."""
    return json.loads(unblob(b).tobytes().decode("utf-8"))


def unblob(b: dict[str, Any]) -> np.ndarray:
    """The array of :func:`blob` (for tests and the benchmark)."""
    raw = base64.b64decode(b["b64"])
    if b["gzip"]:
        raw = gzip.decompress(raw)
    return np.frombuffer(raw, np.dtype("<" + b["dtype"])).reshape(b["shape"])


#: The review page's Content-Security-Policy (its inline scripts' hashes are added): scripts from the page's folder
#: and the inline ones lgi wrote, nothing from elsewhere, no inline handlers (an ``onerror=`` that a name in the
#: data smuggled into the page does not run), no network.
PAGE_POLICY = ("default-src 'none'; script-src 'self' {hashes}; style-src 'self' 'unsafe-inline'; "
               "img-src 'self' data:; frame-src 'self'; connect-src 'none'; base-uri 'none'; form-action 'none'")
#: A block page's: its own script only.
BLOCK_POLICY = "default-src 'none'; script-src {hashes}; base-uri 'none'; form-action 'none'"


def with_policy(html: str, policy: str) -> str:
    """``html`` with a ``<meta http-equiv="Content-Security-Policy">`` of ``policy`` (``{hashes}``: the sha256 of
    each inline ``<script>`` of ``html``) right after its ``<meta charset>``."""
    scripts = re.findall(r"<script>(.*?)</script>", html, re.S)
    hashes = " ".join(f"'sha256-{base64.b64encode(hashlib.sha256(t.encode('utf-8')).digest()).decode()}'"
                      for t in scripts)
    meta = f'<meta http-equiv="Content-Security-Policy" content="{policy.format(hashes=hashes)}">'
    charset = '<meta charset="utf-8">'
    if charset not in html:
        raise ValueError("a review page without <meta charset=\"utf-8\">")
    return html.replace(charset, f"{charset}\n{meta}", 1)


def write_script(path: str | Path, name: str, payload: dict[str, Any]) -> int:
    """Write ``payload`` as a script assigning ``window[name]``; returns its size in bytes. Non-finite numbers
    become null (JSON has none)."""
    text = f"window.{name} = " + json.dumps(_finite(payload), separators=(",", ":"), allow_nan=False) + ";\n"
    data = text.encode("utf-8")
    Path(path).write_bytes(data)
    return len(data)


def block_page_script(registry: str) -> str:
    """The script of every block page (the same text in each, so a browser compiles it once): it hands the block's
    JSON text to the review page that framed it, or, opened on its own, puts the block in
    ``window[registry][k]``."""
    return ('(function () { var text = document.getElementById("lgi-block").textContent;'
            ' if (window.parent !== window) { window.parent.postMessage({ lgiReviewBlock: text }, "*"); return; }'
            f" var block = JSON.parse(text); (window.{registry} = window.{registry} || {{}})[block.block] = block;"
            " })();")


def write_block_page(path: str | Path, payload: dict[str, Any], registry: str) -> int:
    """Write a block of frames as a small HTML page: ``payload`` (with its index as ``block``) as JSON in a
    ``<script type="application/json">`` element, which the browser does not compile, and
    :func:`block_page_script`; returns its size in bytes.

    Not a script of its own: Chromium's compilation cache keeps the source of every script a page has run for
    the page's life (measured: 7.6 MB of heap kept per 4 MB script, gc or not), so a long take scrubbed through
    in block scripts grew by the blocks' size. A page the review page frames, hands over and drops is freed
    whole."""
    text = json.dumps(_finite(payload), separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")
    script = block_page_script(registry)
    html = with_policy(f'<!DOCTYPE html>\n<meta charset="utf-8">\n<title>lgi review block {payload["block"]}</title>\n'
                       f'<script type="application/json" id="lgi-block">{text}</script>\n<script>{script}</script>\n',
                       BLOCK_POLICY)
    data = html.encode("utf-8")
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
