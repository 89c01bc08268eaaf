"""Each job option is declared once (lgi/options.py): an option added to its options class, in that one place,
reaches the command line's parser, docs/cli.md and the flow's parameters (with its words, default and type)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PROBE = ('    probe_weight: float = option(0.5, "a probe of the declarations, mm (default %(default)s)", '
         'group="method", metavar="MM")\n')

CHECK = """
import json
from lgi.cli import _reconstruct_options, build_parser
from prefect.utilities.callables import parameter_schema
from lgi.orchestration.reconstruct import reconstruct_shot

args = build_parser().parse_args(["reconstruct", "idx", "--bundles", "b.csv", "--out", "o", "--probe-weight", "0.25"])
default = build_parser().parse_args(["reconstruct", "idx", "--bundles", "b.csv", "--out", "o"])
prop = parameter_schema(reconstruct_shot.fn).model_dump()["properties"]["probe_weight"]
given, default = _reconstruct_options(args), _reconstruct_options(default)
print(json.dumps({"given": given.probe_weight, "default": default.probe_weight, "flow": prop}))
"""


def test_an_option_added_in_one_place_reaches_the_parser_the_docs_and_the_flow(tmp_path: Path) -> None:
    for name in ("lgi", "scripts"):
        shutil.copytree(ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "docs").mkdir()
    options = tmp_path / "lgi" / "jobs" / "reconstruct" / "options.py"
    text = options.read_text()
    anchor = "\n    def __post_init__(self) -> None:\n"
    assert text.count(anchor) == 1
    options.write_text(text.replace(anchor, "\n" + PROBE + anchor))
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    r = subprocess.run([sys.executable, "-c", CHECK], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["given"] == 0.25 and got["default"] == 0.5
    assert got["flow"]["default"] == 0.5 and got["flow"]["type"] == "number"
    assert got["flow"]["description"].startswith("a probe of the declarations, mm (default 0.5)")
    r = subprocess.run([sys.executable, "scripts/make_cli_doc.py"], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    doc = (tmp_path / "docs" / "cli.md").read_text()
    assert "--probe-weight MM" in doc and "a probe of the declarations, mm (default 0.5)" in doc
