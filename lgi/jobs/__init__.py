"""The job layer: one function and one typed options object per job.

The ``lgi`` command line parses its arguments into a job's options, calls the job and prints the job's
report; the Prefect tasks and flows call the same functions (or the same stages of them) with the same
options, so choosing ``--flow`` changes how the work is scheduled and nothing else.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any, TypeVar

T = TypeVar("T")


def options_from_dict(cls: type[T], d: dict[str, Any] | None, what: str) -> T:
    """An options dataclass from a dict (a flow's parameters, a JSON file); unknown keys are refused by name, so
    a typo is an error, not an option silently left at its default."""
    from lgi.errors import InputError

    d = dict(d or {})
    known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(d) - known)
    if unknown:
        raise InputError(f"unknown {what} options {unknown}; known: {sorted(known)}")
    return cls(**d)
