"""Job options declared once.

An options dataclass declares each option in one place, :func:`option`: its default, its help (the words the
command line, the class's docstring, the flows' parameter descriptions and docs/cli.md all show), and how the
command line takes it (metavar, a parsing function, choices, the help group). From that declaration

- :func:`add_flags` adds the flags to an argparse parser, and :func:`from_args` reads them back;
- :func:`declared` (a class decorator) writes the class's numpy ``Attributes`` section;
- :func:`flow_parameters` gives a Prefect flow function the options as its keyword parameters, with their
  defaults and types, so that a deployment's schema lists them, and :func:`take` reads them back;
- :func:`option_help` gives each option's words to the flows' parameter descriptions.

A job that takes some of another job's options under other names (``lgi reconstruct --scan-gate`` for
``lgi compare --gate``) names them with a :class:`Subset`, wherever a class is taken.

So an option added to the dataclass reaches the parser, docs/cli.md (generated from the parser) and the flow.
"""

from __future__ import annotations

import argparse
import inspect
import typing
from collections.abc import Callable
from dataclasses import MISSING, Field, dataclass, field, fields, is_dataclass, replace
from typing import Any, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class Flag:
    """How the command line takes an option. ``help`` is argparse's help text (``%(default)s`` is the default);
    ``group``: the name of the help section it is listed in; ``parse``: argparse's ``type`` (default: from the
    field's type, ``float`` or ``int``); ``name``: the flag (default ``--`` and the field's name with dashes);
    ``append``: the flag is repeated, one value each; ``units``: what the value is measured in, for the
    docstring."""

    help: str
    group: str | None = None
    metavar: str | None = None
    parse: Callable[[str], Any] | None = None
    choices: tuple[str, ...] | None = None
    name: str | None = None
    append: bool = False
    units: str | None = None


#: The default of an option that must be given (a required flag).
REQUIRED = MISSING


def option(default: Any, help: str, **flag: Any) -> Any:
    """A dataclass field for a job option: its default (:data:`REQUIRED`: none, the flag must be given) and its
    :class:`Flag` (``help`` and the keywords)."""
    return field(default=default, metadata={"flag": Flag(help, **flag)})


def same_as(cls: type, name: str, **flag: Any) -> Any:
    """The option ``name`` of ``cls`` declared again for another job: the same default and words (``flag``: what
    differs in how its command line lists it, e.g. its ``group``)."""
    f = next(f for f in declared_fields(cls) if f.name == name)
    return field(default=f.default, metadata={"flag": replace(_flag(f), **flag)})


@dataclass(frozen=True)
class Subset:
    """The options ``only`` (field names) of ``cls``, each named ``prefix`` and its own flag's name (``scan_``
    and ``--gate``: ``--scan-gate``, the parameter ``scan_gate``), its help after ``help_prefix``."""

    cls: type
    prefix: str = ""
    only: tuple[str, ...] | None = None
    help_prefix: str = ""


def _subset(spec: type | Subset) -> Subset:
    return spec if isinstance(spec, Subset) else Subset(spec)


def _flag(f: Field) -> Flag:
    return f.metadata["flag"]


def declared_fields(spec: type | Subset) -> list[Field]:
    """The fields declared with :func:`option` of a class (or those of a :class:`Subset`), in order."""
    s = _subset(spec)
    if not is_dataclass(s.cls):
        return []
    return [f for f in fields(s.cls) if "flag" in f.metadata and (s.only is None or f.name in s.only)]


def param_name(f: Field, prefix: str = "") -> str:
    """An option's name as a flow parameter and argparse destination: ``prefix`` and its flag without dashes."""
    return prefix + (_flag(f).name or "--" + f.name).lstrip("-").replace("-", "_")


def flag_name(f: Field, prefix: str = "") -> str:
    """The command line's flag of an option (``--temporal-weight``)."""
    return "--" + param_name(f, prefix).replace("_", "-")


def _shown(default: Any) -> Any:
    """A default as the command line writes it (a tuple as comma-separated values)."""
    return ",".join(map(str, default)) if isinstance(default, tuple) else default


def _filled(text: str, default: Any) -> str:
    """Help text with argparse's ``%(default)s`` filled in (and ``%%`` as ``%``)."""
    return text % {"default": _shown(default)}


def option_help(spec: type | Subset) -> dict[str, str]:
    """Parameter name -> the option's help, its default filled in (the flows' parameter descriptions)."""
    s = _subset(spec)
    return {param_name(f, s.prefix): s.help_prefix + _filled(_flag(f).help, f.default) for f in declared_fields(s)}


def add_flags(groups: dict[str, argparse._ActionsContainer], spec: type | Subset,
              default_group: str | None = None) -> None:
    """Add the options of a class (or a :class:`Subset`) as flags, each to ``groups[its group]`` (an argparse
    parser or argument group; ``default_group`` for an option without one, or for every option of a subset)."""
    s = _subset(spec)
    for f in declared_fields(s):
        fl = _flag(f)
        target = groups[(default_group if s.prefix else None) or fl.group or default_group]
        kind = str(f.type).removesuffix(" | None")
        kw: dict[str, Any] = {"dest": param_name(f, s.prefix), "help": s.help_prefix + fl.help}
        if kind == "bool":
            kw["action"] = "store_false" if f.default else "store_true"
        else:
            if f.default is MISSING:
                kw["required"] = True
            else:
                # A string default goes through ``parse`` as a given value would (argparse does so).
                kw["default"] = None if fl.append else _shown(f.default)
            kw["metavar"] = fl.metavar
            kw["choices"] = fl.choices
            if fl.append:
                kw["action"] = "append"
            parse = fl.parse or {"float": float, "int": int}.get(kind)
            if parse is not None:
                kw["type"] = parse
        target.add_argument(flag_name(f, s.prefix), **kw)


def take(spec: type | Subset, values: dict[str, Any] | argparse.Namespace) -> dict[str, Any]:
    """Field name -> value of the options of a class (or a :class:`Subset`) among ``values`` (parsed
    arguments, or a flow's keyword parameters: those found are removed from the dict)."""
    s = _subset(spec)
    out = {}
    for f in declared_fields(s):
        name = param_name(f, s.prefix)
        if isinstance(values, dict):
            if name in values:
                out[f.name] = values.pop(name)
        else:
            out[f.name] = getattr(values, name)
    return out


def params(spec: type | Subset, values: dict[str, Any]) -> dict[str, Any]:
    """Parameter name -> value, from field name -> value (:func:`take`'s inverse)."""
    s = _subset(spec)
    return {param_name(f, s.prefix): values[f.name] for f in declared_fields(s) if f.name in values}


def from_args(cls: type[T], args: argparse.Namespace, **given: Any) -> T:
    """The options of ``cls`` from parsed arguments (:func:`add_flags`), and ``given`` for the other fields."""
    return cls(**take(cls, args), **given)


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


def flow_parameters(*specs: type | Subset, after: int) -> Callable[[Callable[..., T]], Callable[..., T]]:
    """Decorator of a flow function taking ``**options``: its signature (what Prefect reads for the flow's and
    a deployment's parameters) gains every option of ``specs`` (classes or :class:`Subset`) as a keyword
    parameter with its default and type, after the function's first ``after`` parameters. Prefect passes them
    in ``**options``; :func:`take` reads them back."""
    def wrap(fn: Callable[..., T]) -> Callable[..., T]:
        sig = inspect.signature(fn)
        own = [p for p in sig.parameters.values() if p.kind != inspect.Parameter.VAR_KEYWORD]
        added = []
        for spec in specs:
            s = _subset(spec)
            hints = typing.get_type_hints(s.cls)
            for f in declared_fields(s):
                if f.default is MISSING:
                    raise TypeError(f"{s.cls.__name__}.{f.name}: a flow parameter needs a default")
                added.append(inspect.Parameter(param_name(f, s.prefix), inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                               default=f.default, annotation=hints[f.name]))
        names = [p.name for p in [*own, *added]]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise TypeError(f"{fn.__name__}: parameters declared twice: {twice}")
        fn.__signature__ = sig.replace(parameters=[*own[:after], *added, *own[after:]])  # type: ignore[attr-defined]
        return fn
    return wrap
