"""Flow parameters described once: the descriptions Prefect shows for a flow's parameters (its UI, the
deployment's schema) come from the job options' docstrings, so the flow and the command line document the same
options in the same words."""

from __future__ import annotations

import inspect
import re
from collections.abc import Callable
from typing import Any, TypeVar

from lgi.options import Subset, option_help

F = TypeVar("F", bound=Callable[..., Any])

_ENTRY = re.compile(r"^    (?P<names>[A-Za-z_][\w, ]*?)\s*:\s*(?P<type>.*)$")


def option_docs(cls: type) -> dict[str, str]:
    """Field name -> description: the options declared with :func:`lgi.options.option` (their help), and the
    rest from a numpy-style ``Parameters``/``Attributes`` section of ``cls``'s docstring (an entry ``a, b : type``
    describes both)."""
    if isinstance(cls, Subset):
        return {k: v.strip(" .") + "." for k, v in option_help(cls).items()}
    docs: dict[str, str] = {}
    current: list[str] = []
    for line in (cls.__doc__ or "").splitlines():
        m = _ENTRY.match(line)
        if m and not line.startswith("     "):
            current = [n.strip() for n in m["names"].split(",")]
            for n in current:
                docs[n] = m["type"].strip()
        elif line.startswith("        ") and current:
            for n in current:
                docs[n] = (docs[n] + ". " if docs[n] and not docs[n].endswith(".") else docs[n] + " ") + line.strip()
        elif not line.strip():
            continue
        else:
            current = []
    docs.update(option_help(cls))
    return {k: v.strip(" .") + "." for k, v in docs.items()}


def described(*sources: type, **extra: str) -> Callable[[F], F]:
    """Append a Google-style ``Args:`` section (what Prefect reads) to a flow function's docstring: each
    parameter's description from ``extra`` or from the first of the option classes ``sources`` that documents
    it. A parameter without one, or two sharing one, is an error (a new parameter cannot go undocumented, nor
    borrow another's words)."""
    def wrap(fn: F) -> F:
        docs: dict[str, str] = {}
        for cls in reversed(sources):
            docs.update(option_docs(cls))
        docs.update(extra)
        missing = [p for p in inspect.signature(fn).parameters if p not in docs]
        if missing:
            raise TypeError(f"{fn.__name__}: parameters without a description: {missing}")
        # One docstring entry for several options ("a, b : bool") would show the same words under each of them.
        shared: dict[str, list[str]] = {}
        for p in inspect.signature(fn).parameters:
            shared.setdefault(docs[p], []).append(p)
        if clash := [names for names in shared.values() if len(names) > 1]:
            raise TypeError(f"{fn.__name__}: parameters sharing one description: {clash}")
        lines = [f"    {p}: {docs[p]}" for p in inspect.signature(fn).parameters]
        fn.__doc__ = inspect.cleandoc(fn.__doc__ or "") + "\n\nArgs:\n" + "\n".join(lines) + "\n"
        return fn
    return wrap
