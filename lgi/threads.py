"""Thread budgets: the per-frame solve runs its own parallel loops (numba) and small dense products; a
multithreaded BLAS on top of them fights for the same cores (on this 2-core machine a global fit went from
14 to about 60 ms per frame), so the solver's entry points run with one BLAS thread."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

from threadpoolctl import threadpool_limits

F = TypeVar("F", bound=Callable)


def one_blas_thread(fn: F) -> F:
    """Run ``fn`` with BLAS limited to one thread (restored afterwards; nesting is harmless)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
