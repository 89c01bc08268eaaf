"""The package tree in README.md ("Layout of the repository") against the code: every file and folder it names
exists, and every subpackage of lgi/ is named in it."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Where a line's description starts; a line indented this far continues the description above it.
DESCRIPTION_COLUMN = 25
# A module named inside a description (``solver.py``), taken in the folder of the line's entry.
MODULE_IN_TEXT = re.compile(r"(?<![\w/*.-])([A-Za-z_]\w*\.py)\b")


def readme_tree() -> list[str]:
    """The lines of the fenced block under README.md's "## Layout of the repository"."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Layout of the repository", 1)[1]
    block = section.split("```", 2)[1]
    return [ln for ln in block.splitlines() if ln.strip()]


def named_paths(lines: list[str]) -> list[str]:
    """Repository-relative paths the tree names: its entries (the text before a line's description; several
    may stand there, comma-separated) placed under the folder above them by indentation (two spaces a level),
    and the modules its descriptions name, in the folder of their line's entry. Folders end with "/"."""
    parents: dict[int, str] = {}  # indentation level -> folder (with "/") of the last folder entry there
    out: list[str] = []
    here = ""  # the folder that the current entry's description speaks of
    for ln in lines:
        indent = len(ln) - len(ln.lstrip(" "))
        if indent < DESCRIPTION_COLUMN:
            level = indent // 2
            base = parents.get(level - 1, "") if level else ""
            entry, _, description = ln.strip().partition("  ")
            names = [n.strip() for n in entry.split(",") if n.strip()]
            for name in names:
                out.append(base + name)
                if name.endswith("/"):
                    parents[level] = base + name
            parents = {k: v for k, v in parents.items() if k <= level}
            here = base + names[-1] if names[-1].endswith("/") else base
        else:
            description = ln
        out += [here + m for m in MODULE_IN_TEXT.findall(description)]
    return out


def test_readme_tree_parses_as_expected() -> None:
    paths = named_paths(readme_tree())
    # Entries, nested entries, comma-separated entries and modules named in descriptions.
    assert {"lgi/", "lgi/cli.py", "lgi/jobs/reconstruct/", "lgi/units.py", "flows/", "tasks/",
            "lgi/solve/solver.py"} <= set(paths)


def test_every_path_in_the_readme_tree_exists() -> None:
    missing = [p for p in named_paths(readme_tree()) if not (ROOT / p.rstrip("/")).exists()
               or p.endswith("/") != (ROOT / p.rstrip("/")).is_dir()]
    assert not missing, f"README.md's layout names what is not in the tree: {missing}"


def test_every_subpackage_of_lgi_is_in_the_readme_tree() -> None:
    named = {p.rstrip("/") for p in named_paths(readme_tree())}
    packages = sorted(str(p.parent.relative_to(ROOT)) for p in (ROOT / "lgi").rglob("__init__.py")
                      if "__pycache__" not in p.parts)
    absent = [p for p in packages if p not in named]
    assert not absent, f"subpackages of lgi/ missing from README.md's layout: {absent}"


def test_benchmark_index_is_the_scripts() -> None:
    """docs/benchmarks.md's index of the benchmark scripts is generated from them (scripts/make_bench_index.py):
    a script added, or a docstring changed, without regenerating it fails here; and every row names a
    script that exists, every script has a row."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "make_bench_index.py"), "--check"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    doc = (ROOT / "docs" / "benchmarks.md").read_text()
    block = doc.split("<!-- table:scripts -->", 1)[1].split("<!-- /table -->", 1)[0]
    named = set(re.findall(r"^\| `([\w.]+\.py)` \|", block, flags=re.M))
    scripts = {p.name for p in (ROOT / "benchmarks").glob("*.py")} - {"common.py", "__init__.py"}
    assert named == scripts
    for target in re.findall(r"\]\(([^)#]+)\)", block):
        assert (ROOT / "docs" / target).resolve().is_file(), target
