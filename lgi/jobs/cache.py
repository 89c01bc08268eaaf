"""``lgi cache``: list and trim the stage cache of the dataset rebuild (:class:`lgi.io.cache.StageCache`)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lgi.errors import InputError
from lgi.options import declared, option


def cache_root(path: str | Path) -> Path:
    """The cache folder: ``path`` itself, or ``path/.cache`` for a rebuild's OUT (where the flow keeps it)."""
    p = Path(path)
    if (p / ".cache").is_dir():
        return p / ".cache"
    if not p.is_dir():
        raise InputError("no such cache folder (give the rebuild's OUT or its cache folder)", path=p)
    return p


@declared
@dataclass(frozen=True)
class PruneOptions:
    """``lgi cache prune``: keep the ``keep`` most recently used results of each stage, and/or remove those not
    used for ``older_than`` days. One of the two is needed."""

    keep: int | None = option(None, "keep the N most recently used results of each stage", group="prune",
                              metavar="N")
    older_than: float | None = option(None, "remove results unused for DAYS days", group="prune", metavar="DAYS",
                                      units="days")

    def __post_init__(self) -> None:
        if self.keep is None and self.older_than is None:
            raise InputError("say what to prune: --keep N and/or --older-than DAYS")
        if self.keep is not None and (isinstance(self.keep, bool) or not isinstance(self.keep, int) or self.keep < 0):
            raise InputError(f"--keep must be a whole number >= 0, not {self.keep!r}")
        if self.older_than is not None and (not math.isfinite(self.older_than) or self.older_than < 0):
            raise InputError(f"--older-than must be a number of days >= 0, not {self.older_than!r}")


def list_cache(path: str | Path) -> list[dict[str, Any]]:
    """Every complete stage result (stage, key, bytes, created, used, path), most recently used first."""
    from lgi.io.cache import StageCache

    return StageCache(cache_root(path)).entries()


def prune_cache(path: str | Path, options: PruneOptions) -> list[dict[str, Any]]:
    """Remove stage results as ``options`` say; returns the removed ones."""
    from lgi.io.cache import StageCache

    return StageCache(cache_root(path)).prune(options.keep, options.older_than)


def cache_report(entries: list[dict[str, Any]], removed: bool = False) -> list[str]:
    total = sum(e["bytes"] for e in entries)
    now = time.time()
    lines = [f"{'stage':<10} {'key':<14} {'MB':>8} {'last used':>12}"]
    for e in entries:
        age = (now - e["used"]) / 86400
        lines.append(f"{e['stage']:<10} {e['key'][:12]:<14} {e['bytes'] / 1e6:8.2f} {age:9.1f} d ago")
    lines.append(f"{'removed' if removed else 'total'}: {len(entries)} results, {total / 1e6:.1f} MB")
    return lines
