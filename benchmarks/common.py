"""What the benchmarks share: where their data is, the datasets, indexes and shots they build, and how they run
and time whole ``lgi`` processes.

Every script in ``benchmarks/`` runs as ``python benchmarks/SCRIPT.py`` and imports this module beside it
(``from common import ...``). The benchmark sets themselves (the frames and truth each accuracy figure is
measured on) are :mod:`lgi.evaluation.benchsets`, which ``lgi bench`` and the tests use too; what the scripts
take from it comes through here (ICT as the sets import it: ``ict_dataset``, ``ict_layout``).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from lgi.evaluation.benchsets import (
    ICT_FACE_VERTICES,
    ICT_NOT_PERFORMED,
    ict_dir_or_none,
    load_sets,
    needs_ict,
    synthetic_set,
    tracking_noise,
)
from lgi.evaluation.benchsets.ict import _ict as ict_dataset
from lgi.evaluation.benchsets.ict import _ict_layout as ict_layout
from lgi.paths import REPO_ROOT, shared_data, shipped

__all__ = ["ICT_DIR", "ICT_FACE_VERTICES", "ICT_JAW_VERTICES", "ICT_MARKERS", "ICT_NOT_PERFORMED", "Run", "add_noise",
           "combos", "dir_mib", "eased_shot", "escape", "first_frames", "has_ict", "ict_dataset", "ict_dir_or_none",
           "ict_layout", "lgi", "lgi_timed", "load_sets", "log", "manifest", "needs_ict", "run_process",
           "synthetic_actor", "synthetic_set", "tracking_noise"]

# ------------------------------------------------------------------------------------------------ data
#: ICT FaceKit's folder as the benchmarks find it by default (``$LGI_SHARED_DATA/ict-facekit``, else
#: ``../shared/data/ict-facekit`` beside the repository); each script's ``--ict`` may name another.
ICT_DIR = shared_data("ict-facekit")
#: The shipped 108-marker layout on ICT's mesh.
ICT_MARKERS = shipped("markers_ict.csv")
#: ICT's vertices that move rigidly with the jaw (``lgi rig --jaw-vertices``).
ICT_JAW_VERTICES = "19247:21450"


def has_ict(folder: Path) -> bool:
    """Whether ``folder`` holds ICT FaceKit (its generic neutral mesh)."""
    return (Path(folder) / "generic_neutral_mesh.obj").is_file()


# ------------------------------------------------------------------------------------- datasets and shots
def synthetic_actor(n_vertices: int | None = None):
    """The synthetic actor, its 47-shape dataset and its shipped marker layout: ``(actor, dataset, layout)``
    (``n_vertices``: at least this many vertices; default the actor's own)."""
    from lgi.synthetic import actor as synth

    actor = synth.make_actor() if n_vertices is None else synth.make_actor(n_vertices)
    ds = synth.make_dataset(actor)
    layout, _ = synth.default_layout(actor)
    return actor, ds, layout


def manifest(directory: Path) -> dict:
    """A dataset's or index's ``manifest.json``."""
    return json.loads((directory / "manifest.json").read_text())


def combos(directory: Path) -> list[tuple[str, frozenset]]:
    """``(name, sources)`` of a dataset's in-betweens, read from its manifest (no arrays loaded)."""
    out = []
    for s in manifest(directory)["shapes"]:
        src = (s.get("extra") or {}).get("sources")
        if src:
            out.append((s["name"], frozenset((k, float(v)) for k, v in src.items())))
    return out


def dir_mib(path: Path) -> float:
    """Size on disk of a directory's files, MiB."""
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 2**20


def add_noise(src: Path, dst: Path, sigma: float | np.ndarray, seed: int) -> None:
    """Copy of a bundles CSV with Gaussian noise ``sigma`` (file units; a number, or (3,) per axis) on every
    coordinate, written in the format ``lgi bundles`` writes (``frame, marker, x, y, z``, ``%.9g``)."""
    df = pd.read_csv(src)
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, 1.0, (len(df), 3)) * np.broadcast_to(np.asarray(sigma, np.float64), (3,))
    df[["x", "y", "z"]] = df[["x", "y", "z"]].to_numpy(np.float64) + noise
    df.to_csv(dst, index=False, float_format="%.9g")


def first_frames(src: Path, dst: Path, n: int) -> None:
    """The first ``n`` frames of a bundles CSV, rows unchanged."""
    df = pd.read_csv(src, dtype={"marker": str, "frame": str, "x": str, "y": str, "z": str}, keep_default_na=False)
    frames = pd.to_numeric(df["frame"])
    keep = np.sort(frames.unique())[:n]
    df[frames.isin(keep).to_numpy()].to_csv(dst, index=False)


def eased_shot(keys: Path, dst: Path, step: int) -> int:
    """A continuous shot from key poses (a bundles CSV, one frame per pose): ``step`` frames from each pose to
    the next, eased in time (smoothstep), the last pose not repeated. Returns the number of frames."""
    df = pd.read_csv(keys)
    names = df.loc[df["frame"] == df["frame"].iloc[0], "marker"].tolist()
    pos = df[["x", "y", "z"]].to_numpy().reshape(-1, len(names), 3)
    t = np.arange(step) / step
    ease = t * t * (3 - 2 * t)
    shot = ((1 - ease)[None, :, None, None] * pos[:-1, None] + ease[None, :, None, None] * pos[1:, None])
    shot = shot.reshape(-1, len(names), 3)
    n_f = len(shot)
    pd.DataFrame({"frame": np.repeat(np.arange(n_f), len(names)), "marker": np.tile(names, n_f),
                  "x": shot[..., 0].ravel(), "y": shot[..., 1].ravel(), "z": shot[..., 2].ravel()}
                 ).to_csv(dst, index=False, float_format="%.7g")
    return n_f


def escape(name: str) -> str:
    """A shape name as a shell pattern matching only itself (``*`` in in-between names is literal)."""
    return "".join(f"[{c}]" if c in "*?[" else c for c in name)


# ------------------------------------------------------------------------------- processes and timing
def lgi(*args: str) -> str:
    """``python -m lgi ARGS`` in a child process; its standard output, or exit with its output if it fails."""
    r = subprocess.run([sys.executable, "-m", "lgi", *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"lgi {' '.join(args)} failed:\n{r.stdout}\n{r.stderr}")
    return r.stdout


@dataclass
class Run:
    """One finished child process."""

    wall_s: float
    peak_mib: float
    returncode: int
    stdout: str
    stderr: str


# Linux starts an exec'd child's peak memory (ru_maxrss) at the peak of the process it was forked from (the
# old address space's high-water mark is kept across exec), so a child started straight from a benchmark that
# has held large arrays reports the benchmark's peak. A small launcher between them starts the command afresh and
# passes on the command's own figures.
_LAUNCHER = """
import json, os, subprocess, sys, time
t = time.perf_counter()
p = subprocess.Popen(sys.argv[2:])
_, status, usage = os.wait4(p.pid, 0)
with open(sys.argv[1], "w") as f:
    json.dump({"wall_s": time.perf_counter() - t, "maxrss_kib": usage.ru_maxrss,
               "returncode": os.waitstatus_to_exitcode(status)}, f)
"""


def run_process(argv: list[str], env: dict[str, str] | None = None) -> Run:
    """Run ``argv`` to completion; wall time and the peak resident set size of that process.

    Parameters
    ----------
    argv
        Command line.
    env
        Environment of the child (default: this process's).

    Returns
    -------
    Run
        ``peak_mib``: the command's own ``ru_maxrss`` (``os.wait4``, through a small launcher so that this
        process's peak does not count), which is the largest of the command's process and of the processes it
        started and waited for (Dask's local workers), not their sum.
    """
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err, \
            tempfile.TemporaryDirectory() as tmp:
        figures = Path(tmp) / "figures.json"
        p = subprocess.run([sys.executable, "-c", _LAUNCHER, str(figures), *argv], stdout=out, stderr=err, env=env,
                           cwd=REPO_ROOT)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read().decode(errors="replace"), err.read().decode(errors="replace")
        if not figures.is_file():
            raise SystemExit(f"the launcher of {' '.join(argv)} failed (status {p.returncode}):\n{stderr}")
        f = json.loads(figures.read_text())
        return Run(f["wall_s"], f["maxrss_kib"] / 1024, f["returncode"], stdout, stderr)


def lgi_timed(*args: str, env: dict[str, str] | None = None) -> Run:
    """``python -m lgi ARGS`` as a timed process; exits with its output if it fails."""
    r = run_process([sys.executable, "-m", "lgi", *args], env)
    if r.returncode != 0:
        raise SystemExit(f"lgi {' '.join(args)} failed (status {r.returncode}):\n{r.stdout}\n{r.stderr}")
    return r


def log(msg: str) -> None:
    """Progress line on stderr (the tables go to stdout)."""
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def write_marked(doc: Path, name: str, body: str) -> bool:
    """Replace the text between ``<!-- table:NAME -->`` and ``<!-- /table -->`` in ``doc`` with ``body``, so
    that a table in the docs is the script's own output. False (and a log line) when ``doc`` has no such
    markers."""
    text = doc.read_text()
    new, n = re.subn(rf"<!-- table:{re.escape(name)} -->\n.*?<!-- /table -->",
                     lambda _: f"<!-- table:{name} -->\n{body}\n<!-- /table -->", text, flags=re.S)
    if not n:
        log(f"{doc} has no <!-- table:{name} --> marker; nothing written")
        return False
    doc.write_text(new)
    log(f"wrote the {name} table into {doc}")
    return True
