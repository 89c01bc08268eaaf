"""Write the index of the benchmark scripts in docs/benchmarks.md from the scripts themselves.

One row per ``benchmarks/*.py`` (``common.py`` excepted): what it measures, from the first paragraph of its
docstring, and the documents that hold its tables, from the ``docs/*.md`` and ``README.md`` paths its source
names. The figures stay in those documents, written by the scripts; the index carries none, so it cannot
disagree with them. ``tests/test_docs.py`` fails when the index is out of date.

    python scripts/make_bench_index.py            # rewrite the table between <!-- table:scripts --> markers
    python scripts/make_bench_index.py --check    # exit 1 if it differs from what the scripts give
"""

from __future__ import annotations

import argparse
import ast
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
MARKED = re.compile(r"<!-- table:scripts -->\n.*?<!-- /table -->", re.S)


def _summary(path: Path) -> str:
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    first = doc.strip().split("\n\n")[0]
    return " ".join(first.split()).replace("|", "\\|")


def _documents(path: Path, texts: dict[str, str]) -> list[str]:
    """The documents that hold or read a script's tables: those its source names (where it writes them) and
    those that name the script, in a stable order."""
    names = set(re.findall(r"\b(docs/[\w.-]+\.md|README\.md)\b", path.read_text()))
    names |= {name for name, text in texts.items() if path.name in text}
    names = {n for n in names if (ROOT / n).is_file()}
    return sorted(names, key=lambda n: (n != "README.md", n))


def _link(name: str) -> str:
    # docs/benchmarks.md lives in docs/: links to its siblings are bare, the README is one level up.
    return f"[{name}](../README.md)" if name == "README.md" else f"[{name}]({Path(name).name})"


def table(doc_text: str) -> str:
    """The index as Markdown; ``doc_text`` is docs/benchmarks.md, whose own index is not a mention."""
    texts = {f"docs/{p.name}": p.read_text() for p in sorted((ROOT / "docs").glob("*.md")) if p != DOC}
    texts["README.md"] = (ROOT / "README.md").read_text()
    texts["docs/benchmarks.md"] = MARKED.sub("", doc_text)
    rows = ["| script | measures | figures in |", "|---|---|---|"]
    for path in sorted((ROOT / "benchmarks").glob("*.py")):
        if path.name in ("common.py", "__init__.py"):
            continue
        docs = ", ".join(_link(n) for n in _documents(path, texts)) or "printed only"
        rows.append(f"| `{path.name}` | {_summary(path)} | {docs} |")
    return "\n".join(rows)


def render(text: str) -> str:
    """``text`` with its scripts table replaced; SystemExit when the markers are missing."""
    if not MARKED.search(text):
        raise SystemExit(f"{DOC}: no <!-- table:scripts --> ... <!-- /table --> markers")
    return MARKED.sub(lambda _: f"<!-- table:scripts -->\n{table(text)}\n<!-- /table -->", text)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="exit 1 if the index is out of date; write nothing")
    args = ap.parse_args()
    text = DOC.read_text()
    new = render(text)
    if args.check:
        if new != text:
            print(f"{DOC} is out of date: run python scripts/make_bench_index.py")
            return 1
        return 0
    DOC.write_text(new)
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
