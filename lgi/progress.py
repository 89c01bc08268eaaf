"""Progress bars for long loops (standard error, hidden when not wanted)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import TypeVar

from tqdm import tqdm

T = TypeVar("T")


def progress(items: Iterable[T], desc: str, disable: bool = False, total: int | None = None) -> Iterator[T]:
    """Iterate ``items`` with a progress bar on standard error.

    The bar is skipped when ``disable`` is set; it also stays quiet for loops that finish within
    about a second (``mininterval``/``delay``), so short runs print nothing.
    """
    # disable=None lets tqdm hide the bar when standard error is not a terminal (CI logs).
    yield from tqdm(items, desc=desc, disable=True if disable else None, total=total, delay=1.0, leave=False, unit="it")
