"""Job options declared once.

An options dataclass declares each option in one place, :func:`option`: its default, its help (the words the
command line, the class's docstring, the flows' parameter descriptions and docs/cli.md all show), and how the
command line takes it (metavar, a parsing function, choices, the help group). From that declaration

- :func:`add_flags` adds the flags to an argparse parser, and :func:`from_args` reads them back;
- :func:`declared` (a class decorator) writes the class's numpy ``Attributes`` section;
- :func:`flow_parameters` gives a Prefect flow function the options as its keyword parameters, with their
  defaults and types, so that a deployment's schema lists them;
- :func:`option_help` gives each option's words to the flows' parameter descriptions.

So an option added to the dataclass reaches the parser, docs/cli.md (generated from the parser) and the flow.
"""

from __future__ import annotations

import argparse
import inspect
import typing
from collections.abc import Callable
from dataclasses import MISSING, Field, dataclass, field, fields, is_dataclass
from typing import Any, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class Flag:
    """How the command line takes an option. ``help`` is argparse's help text (``%(default)s`` is the default);
    ``group``: the name of the help section it is listed in; ``parse``: argparse's ``type`` (default: from the
    field's type, ``float`` or ``int``); ``name``: the flag (default ``--`` and the field's name with dashes);
    ``units``: what the value is measured in, for the docstring."""

    help: str
    group: str | None = None
    metavar: str | None = None
    parse: Callable[[str], Any] | None = None
    choices: tuple[str, ...] | None = None
    name: str | None = None
    units: str | None = None


def option(default: Any, help: str, **flag: Any) -> Any:
    """A dataclass field for a job option: its default and its :class:`Flag` (``help`` and the keywords)."""
    return field(default=default, metadata={"flag": Flag(help, **flag)})


def _flag(f: Field) -> Flag | None:
    return f.metadata.get("flag")


def declared_fields(cls: type) -> list[Field]:
    """The fields of ``cls`` declared with :func:`option`, in order."""
    if not is_dataclass(cls):
        return []
    return [f for f in fields(cls) if _flag(f) is not None]


def flag_name(f: Field) -> str:
    """The command line's flag of an option (``--temporal-weight``)."""
    return _flag(f).name or "--" + f.name.replace("_", "-")


def _filled(text: str, default: Any) -> str:
    """Help text with argparse's ``%(default)s`` filled in (and ``%%`` as ``%``)."""
    return text % {"default": default}


def option_help(cls: type) -> dict[str, str]:
    """Field name -> the option's help, its default filled in (the flows' parameter descriptions)."""
    return {f.name: _filled(_flag(f).help, f.default) for f in declared_fields(cls)}


def add_flags(groups: dict[str, argparse._ActionsContainer], cls: type, default_group: str | None = None) -> None:
    """Add the options of ``cls`` as flags, each to ``groups[its group]`` (an argparse parser or argument group;
    ``default_group`` for an option without one)."""
    for f in declared_fields(cls):
        fl = _flag(f)
        target = groups[fl.group or default_group]
        kind = str(f.type)
        kw: dict[str, Any] = {"dest": f.name, "help": fl.help}
        if kind == "bool":
            kw["action"] = "store_false" if f.default else "store_true"
        else:
            kw["default"] = f.default
            kw["metavar"] = fl.metavar
            kw["choices"] = fl.choices
            parse = fl.parse or {"float": float, "int": int}.get(kind)
            if parse is not None:
                kw["type"] = parse
        target.add_argument(flag_name(f), **kw)


def from_args(cls: type[T], args: argparse.Namespace, **given: Any) -> T:
    """The options of ``cls`` from parsed arguments (:func:`add_flags`), and ``given`` for the other fields."""
    return cls(**{f.name: getattr(args, f.name) for f in declared_fields(cls)}, **given)


def declared(cls: type[T]) -> type[T]:
    """Class decorator: append the options' numpy ``Attributes`` section to the class's docstring."""
    lines = ["", "Attributes", "----------"]
    for f in declared_fields(cls):
        fl = _flag(f)
        units = f", {fl.units}" if fl.units else ""
        lines.append(f"{f.name} : {f.type}{units}")
        lines.append(f"    {_filled(fl.help, f.default)}.")
    cls.__doc__ = inspect.cleandoc(cls.__doc__ or "") + "\n" + "\n".join(lines) + "\n"
    return cls


def flow_parameters(*classes: type, after: int) -> Callable[[Callable[..., T]], Callable[..., T]]:
    """Decorator of a flow function taking ``**options``: its signature (what Prefect reads for the flow's and
    a deployment's parameters) gains every option of ``classes`` as a keyword parameter with its default and
    type, after the function's first ``after`` parameters. Prefect passes them in ``**options``."""
    def wrap(fn: Callable[..., T]) -> Callable[..., T]:
        sig = inspect.signature(fn)
        own = [p for p in sig.parameters.values() if p.kind != inspect.Parameter.VAR_KEYWORD]
        added = []
        for cls in classes:
            hints = typing.get_type_hints(cls)
            for f in declared_fields(cls):
                if f.default is MISSING:
                    raise TypeError(f"{cls.__name__}.{f.name}: a flow parameter needs a default")
                added.append(inspect.Parameter(f.name, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=f.default,
                                               annotation=hints[f.name]))
        names = [p.name for p in [*own, *added]]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise TypeError(f"{fn.__name__}: parameters declared twice: {twice}")
        fn.__signature__ = sig.replace(parameters=[*own[:after], *added, *own[after:]])  # type: ignore[attr-defined]
        return fn
    return wrap
