"""Whole-shot statistics taken a block of frames at a time, equal to the bit to numpy's over the whole array, so
that a long take's trajectories can wait on disk (:class:`~lgi.io.stored.ScratchArray`) and a short one's results
do not change."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator

import numpy as np

#: Frames a blocked pass over a shot reads at once: its working arrays are a few times this many frames' (the
#: smoothing's eight candidate windows: 21 MB at ICT's 108 markers), whatever the shot's length.
BLOCK_FRAMES = 1024

# The median's first pass counts values by the top bits of their float64 pattern (sign, exponent and 8 mantissa
# bits: 1/256 of an octave per bin), so the second keeps only the values of a bin or two.
_MEDIAN_BITS = 20
# numpy sums a contiguous array pairwise; leaves of this many elements are summed by numpy itself.
_SUM_LEAF = 1 << 20


def frame_blocks(n_frames: int, block: int | None = None) -> Iterator[tuple[int, int]]:
    """``(lo, hi)`` of consecutive blocks of at most ``block`` (default :data:`BLOCK_FRAMES`) frames covering
    ``0 .. n_frames``."""
    block = block or BLOCK_FRAMES
    for lo in range(0, n_frames, block):
        yield lo, min(lo + block, n_frames)


def streamed_median(values: Callable[[], Iterable[np.ndarray]]) -> float:
    """``np.median`` of the concatenation of the arrays that ``values()`` yields (non-negative and finite; it is
    called twice), holding only a block and the values next to the median.

    Returns
    -------
    float
        NaN for no values (as numpy's, without its warning).
    """
    n, pick = _order_statistics(values, lambda n: np.array([(n - 1) // 2, n // 2]))
    if n == 0:
        return float("nan")
    # numpy's median is the mean of the middle one or two
    return float(pick[0]) if n % 2 else float(np.mean(pick))


def streamed_percentile(values: Callable[[], Iterable[np.ndarray]], q: float, dtype=np.float64) -> float:
    """``np.percentile(x, q)`` (its default, linear interpolation) of ``x``, the concatenation of the arrays of
    ``dtype`` that ``values()`` yields (non-negative and finite; it is called twice), bit for bit, holding only a
    block and the values next to the percentile.

    Returns
    -------
    float
        NaN for no values.
    """
    virtual = np.zeros(1)

    def ranks(n: int) -> np.ndarray:
        # numpy's virtual index of the linear method, and its neighbours
        virtual[0] = (n - 1) * np.true_divide(q, 100)
        lo = int(np.floor(virtual[0]))
        return np.array([lo, min(lo + 1, n - 1)])

    n, pick = _order_statistics(values, ranks)
    if n == 0:
        return float("nan")
    a, b = np.asarray(pick, dtype)
    gamma = float(virtual[0] - np.floor(virtual[0]))
    # numpy's _lerp: from the nearer end
    return float(b - (b - a) * (1 - gamma) if gamma >= 0.5 else a + (b - a) * gamma)


def _order_statistics(values: Callable[[], Iterable[np.ndarray]],
                      ranks: Callable[[int], np.ndarray]) -> tuple[int, np.ndarray]:
    """The count ``n`` of the values that ``values()`` yields (non-negative and finite; called twice) and those of
    ``ranks(n)`` (ascending) in their sorted order, as float64."""
    shift = np.uint64(64 - _MEDIAN_BITS)
    counts = np.zeros(1 << _MEDIAN_BITS, np.int64)
    for v in values():
        # The bit patterns of non-negative floats sort as their values.
        top = np.ascontiguousarray(v, np.float64).ravel().view(np.uint64) >> shift
        counts += np.bincount(top.astype(np.intp), minlength=len(counts))
    n = int(counts.sum())
    if n == 0:
        return 0, np.zeros(0)
    want = ranks(n)
    cum = np.cumsum(counts)
    lo_bin, hi_bin = np.searchsorted(cum, want[[0, -1]], side="right")
    kept = []
    for v in values():
        v = np.ascontiguousarray(v, np.float64).ravel()
        b = v.view(np.uint64) >> shift
        kept.append(v[(b >= lo_bin) & (b <= hi_bin)])
    near = np.sort(np.concatenate(kept))
    below = int(cum[lo_bin - 1]) if lo_bin > 0 else 0
    return n, near[want - below]


def streamed_sum(read: Callable[[int, int], np.ndarray], n: int) -> float:
    """``np.sum`` of a contiguous float64 array of ``n`` elements, bit for bit, from ``read(lo, hi)`` (its elements
    ``lo .. hi`` in order): numpy's pairwise summation, its tree split as numpy splits it down to leaves it sums
    itself."""
    if n <= _SUM_LEAF:
        return float(np.sum(read(0, n))) if n else 0.0
    return _pairwise(read, 0, n)


def _pairwise(read: Callable[[int, int], np.ndarray], lo: int, n: int) -> float:
    if n <= _SUM_LEAF:
        return np.sum(read(lo, lo + n))
    half = n // 2
    half -= half % 8  # numpy's unrolling by 8
    return _pairwise(read, lo, half) + _pairwise(read, lo + half, n - half)


def row_reader(a, transform: Callable[[np.ndarray], np.ndarray] | None = None
               ) -> Callable[[int, int], np.ndarray]:
    """``read(lo, hi)``: elements ``lo .. hi`` of ``a`` (an array or a :class:`~lgi.io.stored.StoredArray`)
    flattened in C order, read a row range at a time, ``transform`` applied to the rows read."""
    per_row = int(np.prod(a.shape[1:], dtype=np.int64))

    def read(lo: int, hi: int) -> np.ndarray:
        r0, r1 = lo // per_row, -(-hi // per_row)
        rows = np.asarray(a[r0:r1], np.float64)
        if transform is not None:
            rows = transform(rows)
        return rows.reshape(-1)[lo - r0 * per_row: hi - r0 * per_row]

    return read


def same_rows(a, b, block: int | None = None) -> bool:
    """Whether two (F, ...) arrays (or :class:`~lgi.io.stored.StoredArray`) hold the same values, NaN equal to NaN,
    read a block of rows at a time."""
    if a is b:
        return True
    if np.shape(a) != np.shape(b):
        return False
    return all(np.array_equal(np.asarray(a[lo:hi]), np.asarray(b[lo:hi]), equal_nan=True)
               for lo, hi in frame_blocks(len(a), block))


def all_rows(a, test: Callable[[np.ndarray], np.ndarray], block: int | None = None) -> np.ndarray:
    """``test`` (a map of (k, ...) rows to (k, ...) results) applied to every block of ``a``'s rows, the results
    joined: for the small per-frame tables of a long take's arrays (``test`` reduces what it reads)."""
    parts = [test(np.asarray(a[lo:hi])) for lo, hi in frame_blocks(len(a), block)]
    return np.concatenate(parts) if parts else test(np.asarray(a[0:0]))
