"""Run a fixed set of jobs on a small synthetic actor and print a sha256 per output file.

A code move (modules renamed, split or merged, kernels carried to other files) must leave every output
byte for byte as it was. Run this before the move and keep its JSON, run it after, and compare::

    python scripts/check_identity.py --json before.json
    ... move ...
    python scripts/check_identity.py --compare before.json

``--compare`` exits 1 when a file's hash differs, or a file is written by one run only.

The jobs go through the ``lgi`` command line, each in a child process, so what runs is what a user runs:
``synth``; ``build`` without and with ``--jaw-rig``; ``reconstruct`` on exact bundles (``--method local``
and ``--method simplex``), on noisy bundles with ``--smooth`` and ``--noise auto``, and with the jaw rig;
``--obj``; ``verify`` (its table, kept as ``verify.txt``); ``bundles``; ``export`` (USD and OpenEXR).

What is not hashed whole, and why: a JSON output's members that hold wall-clock figures or the run's
own paths (``timings_s``, ``seconds``, ``elapsed``, ``created``, ..., see VOLATILE_KEYS, and any string
naming the temporary folder) change from run to run with the code unchanged, so each JSON file is hashed
as canonical JSON with those members dropped. ``build.json`` of an index holds nothing but the build's
timings (``timings_s``), so it hashes as an empty object. The other jobs' standard output is not kept
(it prints timings and frame rates).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from lgi.io.record import RECORD_FILE

#: JSON members whose values are wall-clock figures or stamps: they change between two runs of one tree.
VOLATILE_KEYS = frozenset({"seconds", "elapsed", "timings", "timings_s", "created", "time", "started", "finished"})


def _lgi(*args: str | Path, stdout: Path | None = None) -> None:
    """Run ``lgi ARGS`` in a child process (same interpreter, same ``PYTHONPATH``); fail loudly. With
    ``stdout``, keep what it printed there (for a job whose table is its output)."""
    cmd = [sys.executable, "-m", "lgi", *map(str, args)]
    r = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
    if r.returncode != 0:
        raise SystemExit(f"failed ({r.returncode}): {' '.join(cmd)}\n{r.stdout}\n{r.stderr}")
    if stdout is not None:
        stdout.write_text(r.stdout)


def _noisy_bundles(src: Path, dst: Path, sigma: float, seed: int) -> None:
    """Copy a bundles CSV with Gaussian noise of ``sigma`` (dataset units, cm) added to x, y, z.

    Written with a fixed seed and fixed formatting, so the input is the same bytes on every run."""
    lines = src.read_text().splitlines()
    rng = np.random.default_rng(seed)
    out = [lines[0]]
    for ln in lines[1:]:
        f, m, x, y, z = ln.split(",")
        d = rng.normal(0.0, sigma, 3)
        out.append(f"{f},{m},{float(x) + d[0]:.9g},{float(y) + d[1]:.9g},{float(z) + d[2]:.9g}")
    dst.write_text("\n".join(out) + "\n")


def run_jobs(work: Path) -> None:
    """The fixed set of jobs, writing under ``work``."""
    s = work / "synth"
    _lgi("synth", "--out", s, "--vertices", "2500", "--frames", "24", "--seed", "3", "-q")
    _lgi("bundles", s / "dataset", "--markers", s / "markers.csv", "--out", work / "shape_bundles.csv")
    _lgi("build", s / "dataset", "--markers", s / "markers.csv", "--out", work / "index", "-q")
    _lgi("build", s / "dataset", "--markers", s / "markers.csv", "--out", work / "index_jaw",
         "--jaw-rig", s / "jaw_rig.npz", "-q")
    _lgi("verify", work / "index", "-q", stdout=work / "verify.txt")
    _noisy_bundles(s / "bundles.csv", work / "noisy.csv", sigma=0.03, seed=7)
    _lgi("reconstruct", work / "index", "--bundles", s / "bundles.csv", "--out", work / "rec_exact",
         "--obj", "--noise", "0", "--jaw", "none", "-q")
    _lgi("reconstruct", work / "index", "--bundles", s / "bundles.csv", "--out", work / "rec_simplex",
         "--method", "simplex", "--noise", "0", "--jaw", "none", "-q")
    _lgi("reconstruct", work / "index", "--bundles", work / "noisy.csv", "--out", work / "rec_noisy",
         "--smooth", "5", "--jaw", "none", "-q")
    _lgi("reconstruct", work / "index_jaw", "--bundles", work / "noisy.csv", "--out", work / "rec_rig",
         "--smooth", "5", "-q")
    _lgi("export", work / "rec_noisy", "--index", work / "index", "--usd", work / "export" / "shot.usda",
         "--exr", work / "export" / "exr", "--exr-size", "32", "-q")


def _drop_volatile(v: Any, work: str) -> Any:
    """``v`` without the members named in VOLATILE_KEYS, and with ``work`` (the run's folder) in strings
    replaced by a fixed name."""
    if isinstance(v, dict):
        return {k: _drop_volatile(x, work) for k, x in v.items() if k not in VOLATILE_KEYS}
    if isinstance(v, list):
        return [_drop_volatile(x, work) for x in v]
    if isinstance(v, str):
        return v.replace(work, "WORK")
    return v


def digest(path: Path, work: Path) -> str:
    """sha256 of a file: canonical JSON without volatile members for ``.json``, the raw bytes otherwise."""
    if path.suffix == ".json":
        doc = _drop_volatile(json.loads(path.read_text()), str(work.resolve()))
        if path.name == RECORD_FILE:
            # Each file's [size, mtime_ns, sha256]: the modification time is the run's, not its output; a JSON
            # file's size and bytes hold its timings (the file itself is compared without them, above).
            doc = {**doc, "files": {k: None if k.endswith(".json") else [v[0], v[2]] for k, v in doc["files"].items()}}
        doc = _drop_volatile(doc, str(work))
        data = json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()
    else:
        data = path.read_bytes()
    return hashlib.sha256(data).hexdigest()


def hashes(work: Path) -> dict[str, str]:
    """Relative path -> sha256 for every file under ``work``, sorted by path."""
    return {p.relative_to(work).as_posix(): digest(p, work)
            for p in sorted(work.rglob("*")) if p.is_file()}


def compare(a: dict[str, str], b: dict[str, str]) -> list[str]:
    """Lines naming every path whose hash differs or that only one side has (empty when equal)."""
    out = []
    for k in sorted(set(a) | set(b)):
        if k not in a:
            out.append(f"only in this run: {k}")
        elif k not in b:
            out.append(f"only in the reference: {k}")
        elif a[k] != b[k]:
            out.append(f"differs: {k}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", metavar="FILE", help="also write the hashes to FILE")
    ap.add_argument("--compare", metavar="FILE", help="a reference JSON: exit 1 on any difference")
    ap.add_argument("--keep", metavar="DIR", help="run in DIR (kept) instead of a temporary folder")
    a = ap.parse_args(argv)
    if a.keep:
        work = Path(a.keep)
        work.mkdir(parents=True, exist_ok=False)
        run_jobs(work)
        h = hashes(work)
    else:
        with tempfile.TemporaryDirectory(prefix="lgi-identity-") as d:
            run_jobs(Path(d))
            h = hashes(Path(d))
    for k, v in h.items():
        print(f"{v}  {k}")
    print(f"{len(h)} files")
    if a.json:
        Path(a.json).write_text(json.dumps(h, indent=1, sort_keys=True) + "\n")
    if a.compare:
        diff = compare(h, json.loads(Path(a.compare).read_text()))
        for ln in diff:
            print(ln)
        print("identical" if not diff else f"{len(diff)} differences")
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
