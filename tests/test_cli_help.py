"""The command-line help a user can act on: every argument explained with its default and unit, every command with
an example that parses, and docs/cli.md generated from the same parser."""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from lgi.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
#: A metavar naming a unit promises that unit in the help text.
UNITS = {"MM": "mm", "PX": "px", "DEG": "deg", "DAYS": "days", "SECONDS": "second"}


def _parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ("lgi",)
             ) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, (*path, name))


def _arguments() -> list[tuple[str, argparse.ArgumentParser, argparse.Action]]:
    return [(f"{' '.join(path)} {'/'.join(a.option_strings) or a.dest}", parser, a)
            for path, parser in _parsers(build_parser()) for a in parser._actions
            if not isinstance(a, argparse._HelpAction)]


def test_the_walk_reaches_every_command() -> None:
    """The walk sees every subcommand (layout's two actions included) and their arguments, so the checks below
    cannot pass by looking at nothing."""
    paths = {" ".join(p) for p, _ in _parsers(build_parser())}
    assert {"lgi reconstruct", "lgi rig-generate", "lgi layout design", "lgi layout evaluate", "lgi demo"} <= paths
    assert len(paths) >= 19  # one per command, and more as commands are added
    assert len(_arguments()) > 150


@pytest.mark.parametrize("name,parser,action", _arguments(), ids=[n for n, _, _ in _arguments()])
def test_every_argument_is_explained(name: str, parser: argparse.ArgumentParser, action: argparse.Action) -> None:
    assert action.help and action.help != argparse.SUPPRESS and len(action.help.split()) >= 2, \
        f"{name}: no help text"
    text = parser._get_formatter()._expand_help(action)
    default = action.default
    if default not in (None, False, argparse.SUPPRESS):
        assert "default" in text and str(default) in text, f"{name}: the help does not show its default {default!r}"
    metavar = action.metavar if isinstance(action.metavar, str) else ""
    for word, unit in UNITS.items():
        if word in metavar.split("|"):
            assert unit in text, f"{name}: takes {metavar} but its help does not say {unit}"


@pytest.mark.parametrize("path,parser", list(_parsers(build_parser()))[1:],
                         ids=[" ".join(p) for p, _ in list(_parsers(build_parser()))[1:]])
def test_every_command_has_an_example_that_parses(path: tuple[str, ...], parser: argparse.ArgumentParser) -> None:
    epilog = parser.epilog or ""
    assert "example:\n" in epilog, f"{' '.join(path)}: no example in the epilog"
    examples = [line.strip() for line in epilog.split("example:\n", 1)[1].splitlines() if line.strip()]
    assert examples and all(e.startswith(" ".join(path)) for e in examples), examples
    for example in examples:
        args = build_parser().parse_args(shlex.split(example)[1:])  # argparse exits (SystemExit 2) if it is wrong
        assert callable(args.func)
    assert "example:\n  " in parser.format_help(), "the formatter lost the example's layout"


def test_top_level_help_for_a_newcomer() -> None:
    text = build_parser().format_help()
    after_usage = text.split("\n\n", 1)[1]
    assert after_usage.startswith("Start with `lgi demo`")
    for term in ("bundles", "HMC", "head-mounted stereo camera", "LGI index", "lgi build"):
        assert term in text, term
    for code, meaning in (("0", "success"), ("1", "a check failed"), ("2", "bad input"), ("3", "internal error"),
                          ("130", "interrupted"), ("143", "SIGTERM")):
        assert any(line.split()[:1] == [code] and meaning in line for line in text.splitlines()), (code, meaning)


def test_examples_keep_their_lines_in_a_narrow_terminal() -> None:
    r = subprocess.run([sys.executable, "-m", "lgi", "reconstruct", "--help"], capture_output=True, text=True,
                       env={**__import__("os").environ, "COLUMNS": "60"}, timeout=120)
    assert r.returncode == 0
    example = r.stdout.split("example:\n", 1)[1].splitlines()[0]
    assert example.startswith("  lgi reconstruct ") and example.rstrip().endswith("--smooth 3")


def test_docs_cli_md_is_the_parser() -> None:
    """docs/cli.md is generated from the parser (scripts/make_cli_doc.py): a help text changed without
    regenerating it fails here."""
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "make_cli_doc.py"), "--check"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    doc = (ROOT / "docs" / "cli.md").read_text()
    for path, _ in list(_parsers(build_parser()))[1:]:
        assert f"\n## {' '.join(path)}\n" in doc, path


def test_readme_links_to_existing_sections() -> None:
    """Every docs/cli.md#anchor the README links to is a heading there, and every command has one."""
    import re

    from scripts.make_cli_doc import anchor

    readme = (ROOT / "README.md").read_text()
    doc = (ROOT / "docs" / "cli.md").read_text()
    anchors = {anchor(tuple(h.split())) for h in re.findall(r"^## (lgi .*)$", doc, re.M)}
    linked = set(re.findall(r"docs/cli\.md#([a-z0-9_-]+)", readme))
    assert linked and linked <= anchors, linked - anchors
    leaves = {anchor(p) for p, parser in list(_parsers(build_parser()))[1:] if len(p) == 2}
    assert leaves <= linked, leaves - linked
