"""Thread budgets: the per-frame solve runs its own parallel loops (numba) and small dense products; a
multithreaded BLAS on top of them fights for the same cores (on this 2-core machine a global fit went from
14 to about 60 ms per frame), so the solver's entry points run with one BLAS thread."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

# The compiled kernels' dense products (numba's np.dot) call SciPy's own OpenBLAS, a second copy beside
# NumPy's that loads only when SciPy's BLAS is first used. threadpoolctl limits the copies loaded when
# the limit is entered: loaded later, in the first frame, SciPy's kept its threads, and the exact path's
# global fit took 27 instead of 1.4 ms of CPU per frame (500 shapes; its idle threads spin). Loading it
# here puts it under every limit.
import scipy.linalg.cython_blas  # noqa: F401
from threadpoolctl import threadpool_limits

F = TypeVar("F", bound=Callable)


def one_blas_thread(fn: F) -> F:
    """Run ``fn`` with BLAS limited to one thread (restored afterwards; nesting is harmless)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
