"""The deliberate faults of scripts/check_mutations.py stay meaningful: each one's target text occurs exactly
once and its tests exist, and a fault whose code or tests changed since the last whole check is run again."""

from __future__ import annotations

import re
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import check_mutations as cm  # noqa: E402 - a script beside the package, not an installed module


def test_every_fault_targets_code_that_is_there() -> None:
    """A fault whose target text is gone (or occurs twice) would stop the whole check before it tries a fault."""
    assert cm.check_targets(cm.FAULTS) == []
    for f in cm.FAULTS:
        for node in f.tests:
            path, _, name = node.partition("::")
            text = (ROOT / path).read_text()
            if name:
                assert re.search(rf"^def {re.escape(name.split('[')[0])}\(", text, re.M), (f.name, node)


def test_a_stale_target_is_reported() -> None:
    f = cm.FAULTS[0]
    stale = cm.Fault(f.name, f.what, f.path, f.old + "# gone\n", f.new, f.tests)
    assert len(cm.check_targets([stale])) == 1


def test_faults_changed_since_the_last_whole_check_are_caught() -> None:
    """The faults whose file or tests changed since ``scripts/check_mutations.py`` last caught them all, run
    again here (none when the record is up to date)."""
    todo = cm.unchecked(cm.FAULTS)
    with tempfile.TemporaryDirectory(prefix="lgi-mutations-") as base:
        missed = []
        for f in todo:
            verdict, _, tail = cm.run_fault(f, Path(base))
            if verdict != "caught":
                missed.append(f"{f.name}: {verdict}: {tail}")
    assert not missed, "\n".join(missed)
