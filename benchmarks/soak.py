"""A long night on one worker: the scheduled dataset rebuild every few minutes and a stream of shots in between,
run through the flows in one long-lived process (as a served deployment runs them), against a Prefect API.

    python benchmarks/soak.py [--minutes 5] [--rebuild-every 1] [--keep 2] [--frames 60] [--shots 4]
                              [--vertices 1500] [--out FOLDER] [--json FILE]

Each rebuild starts from "new scans" (one shape moved by a little, so every stage misses the cache and the cache
grows as a real night's would), then prunes the cache as the schedule does (``lgi cache prune OUT --keep N``).
Between rebuilds, shots (``--shots`` synthetic performances, cycled, each into its own folder, so a shot's
earlier result is replaced) go through ``reconstruct-shot`` with the latest index. A shot reconstructed twice
from the same index must give the same bytes.

Reported: runs completed and failed; the process's resident memory (RSS) sampled every second, as the peak per
window of ``--window`` minutes, and its growth after the warm-up (the first rebuild and first round of shots)
against the 10 % allowed; the cache size after every rebuild and prune (it must stay under the policy's
bound: ``keep`` results per stage); temporary files left under the outputs (staging folders, ``.tmp-`` and
``.old-`` entries, chunk folders) and in the run's own temporary folder (``TMPDIR`` is pointed at a fresh
folder, so only what this run leaves counts). The exit status is 1 when any check fails.

With ``PREFECT_API_URL`` set, the flows report to that server; without it, a temporary API is started
(``prefect_test_harness``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")

# Entries a run leaves only while it is running: any of them after the run is a leak.
LEFTOVER_MARKS = (".tmp-", ".old-", ".lgi-staging-", ".chunks-")


class RssSampler(threading.Thread):
    """The process's RSS every ``every`` seconds, as (seconds since start, bytes)."""

    def __init__(self, every: float = 1.0) -> None:
        super().__init__(daemon=True)
        import psutil

        self.proc = psutil.Process()
        self.every = every
        self.samples: list[tuple[float, int]] = []
        self.t0 = time.time()
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            self.samples.append((time.time() - self.t0, self.proc.memory_info().rss))
            self._halt.wait(self.every)

    def stop(self) -> None:
        self._halt.set()
        self.join()


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _tree_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def _leftovers(folder: Path) -> list[str]:
    return sorted(str(p) for p in folder.rglob("*") if any(m in p.name for m in LEFTOVER_MARKS))


def _make_inputs(root: Path, vertices: int, frames: int, shots: int) -> tuple[Path, Path, list[Path]]:
    """The actor's shapes (OBJ), its marker layout, and ``shots`` performances' bundles."""
    import numpy as np

    from lgi.cli import main as lgi
    from lgi.dataset.markers import write_layout
    from lgi.io.obj import write_obj
    from lgi.synthetic import actor as synth

    a = synth.make_actor(vertices)
    shapes = root / "scans"
    write_obj(shapes / "neutral.obj", a.neutral, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs)
    eye = np.eye(len(synth.CONTROLS))
    for name in ("jaw_open", "smile_L", "pucker"):
        write_obj(shapes / f"{name}.obj", a.evaluate(eye[synth.C[name]]), a.face_vertices, a.face_offsets,
                  a.uvs, a.face_uvs)
    layout, _ = synth.default_layout(a)
    markers = root / "markers.csv"
    write_layout(markers, layout, a.neutral)
    bundles = []
    for k in range(shots):
        s = root / "synth" / f"shot{k:03d}"
        assert lgi(["synth", "--out", str(s), "--vertices", str(vertices), "--frames", str(frames),
                    "--seed", str(k), "-q"]) == 0
        bundles.append(s / "bundles.csv")
    return shapes, markers, bundles


def _new_scan(shapes: Path, night: int) -> None:
    """Move one shape's vertices by a little, differently each night: every stage then misses the cache."""
    import numpy as np

    from lgi.io.obj import read_obj, write_obj

    path = shapes / "pucker.obj"
    mesh = read_obj(path)
    rng = np.random.default_rng(night)
    v = mesh.vertices + rng.normal(0, 1e-4, mesh.vertices.shape)
    write_obj(path, v, mesh.face_vertices, mesh.face_offsets, mesh.uvs, mesh.face_uvs)


def soak(args: argparse.Namespace) -> dict[str, Any]:
    from lgi.jobs.cache import PruneOptions, list_cache, prune_cache
    from lgi.orchestration.rebuild import rebuild_dataset
    from lgi.orchestration.reconstruct import reconstruct_shot

    root = Path(args.out)
    shapes, markers, shot_bundles = _make_inputs(root / "inputs", args.vertices, args.frames, args.shots)
    out = root / "datasets" / "actor"
    rss = RssSampler()
    rss.start()
    log: dict[str, Any] = {"runs": {"rebuild": {"completed": 0, "failed": 0}, "shot": {"completed": 0, "failed": 0}},
                           "cache": [], "errors": [], "mismatches": []}
    t0 = time.time()
    end = t0 + args.minutes * 60
    next_rebuild = t0
    night = shot = 0
    warm_until: float | None = None
    seen: dict[tuple[str, int], str] = {}  # (index manifest digest, shot) -> meshes.npz digest
    index_digest = ""
    while time.time() < end:
        if time.time() >= next_rebuild:
            next_rebuild = time.time() + args.rebuild_every * 60
            if night:
                _new_scan(shapes, night)
            night += 1
            try:
                rebuild_dataset(str(shapes), str(out), markers=str(markers))
                log["runs"]["rebuild"]["completed"] += 1
                index_digest = _digest(out / "index" / "manifest.json")
            except Exception as e:  # a failed run is counted and the night goes on, as the schedule would
                log["runs"]["rebuild"]["failed"] += 1
                log["errors"].append(f"rebuild {night}: {type(e).__name__}: {e}")
            prune_cache(out, PruneOptions(keep=args.keep))
            entries = list_cache(out)
            per_stage: dict[str, int] = {}
            for e in entries:
                per_stage[e["stage"]] = per_stage.get(e["stage"], 0) + 1
            log["cache"].append({"t_min": round((time.time() - t0) / 60, 2), "results": len(entries),
                                 "bytes": _tree_bytes(out / ".cache"), "max_per_stage": max(per_stage.values(),
                                                                                             default=0)})
            _say(t0, f"rebuild {night}: {log['runs']['rebuild']}, cache {log['cache'][-1]}")
            continue
        if not index_digest:
            time.sleep(1)
            continue
        k = shot % len(shot_bundles)
        recon = root / "shots" / f"shot{k:03d}" / "recon"
        try:
            reconstruct_shot(str(out / "index"), str(shot_bundles[k]), str(recon), chunk_size=args.chunk)
            log["runs"]["shot"]["completed"] += 1
            d = _digest(recon / "meshes.npz")
            if seen.setdefault((index_digest, k), d) != d:
                log["mismatches"].append(f"shot{k:03d} differs from its earlier run on the same index")
        except Exception as e:
            log["runs"]["shot"]["failed"] += 1
            log["errors"].append(f"shot {shot}: {type(e).__name__}: {e}")
        shot += 1
        _say(t0, f"shot {shot}: {log['runs']['shot']}, rss {rss.samples[-1][1] / 2**20:.0f} MB")
        if warm_until is None and shot >= len(shot_bundles):
            warm_until = time.time() - rss.t0
    rss.stop()
    log["minutes"] = round((time.time() - t0) / 60, 1)
    log["rss"] = _rss_summary(rss.samples, warm_until or 0.0, args.window * 60)
    log["leftovers"] = _leftovers(root)
    log["tmp_leftovers"] = sorted(str(p) for p in Path(tempfile.gettempdir()).iterdir())
    # A bound of the policy: keep results per stage, each no larger than the largest seen.
    log["cache_bound_held"] = all(c["max_per_stage"] <= args.keep for c in log["cache"])
    return log


def _say(t0: float, text: str) -> None:
    print(f"[{(time.time() - t0) / 60:6.1f} min] {text}", file=sys.stderr, flush=True)


def _rss_summary(samples: list[tuple[float, int]], warm: float, window: float) -> dict[str, Any]:
    windows: dict[int, int] = {}
    for t, b in samples:
        windows[int(t // window)] = max(windows.get(int(t // window), 0), b)
    after = [b for t, b in samples if t >= warm]
    first = [b for t, b in samples if warm <= t < warm + window] or after
    last = [b for t, b in samples if t >= samples[-1][0] - window] if samples else []
    growth = (max(last) / max(first) - 1) if first and last else 0.0
    return {"peak_mb_per_window": [round(windows[k] / 2**20, 1) for k in sorted(windows)],
            "window_min": window / 60, "warm_up_s": round(warm, 1),
            "peak_mb_after_warm_up_first_window": round(max(first) / 2**20, 1) if first else None,
            "peak_mb_last_window": round(max(last) / 2**20, 1) if last else None,
            "median_mb_after_warm_up": round(statistics.median(after) / 2**20, 1) if after else None,
            "growth": round(growth, 4)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=5, help="how long to run (60 for the night)")
    ap.add_argument("--rebuild-every", type=float, default=1, help="minutes between scheduled rebuilds")
    ap.add_argument("--keep", type=int, default=2, help="lgi cache prune --keep after each rebuild")
    ap.add_argument("--frames", type=int, default=60, help="frames per shot")
    ap.add_argument("--shots", type=int, default=4, help="distinct shots, cycled")
    ap.add_argument("--chunk", type=int, default=20, help="reconstruct-shot chunk_size")
    ap.add_argument("--vertices", type=int, default=1500)
    ap.add_argument("--window", type=float, default=5, help="minutes per RSS window")
    ap.add_argument("--out", default=None, help="work folder (default: a new temporary folder)")
    ap.add_argument("--json", default=None, help="write the figures here too")
    args = ap.parse_args()
    # A private temporary folder: what is left in it afterwards is this run's, not another program's.
    tmp = Path(tempfile.mkdtemp(prefix="lgi-soak-tmp-"))
    os.environ["TMPDIR"] = str(tmp)
    tempfile.tempdir = str(tmp)
    args.out = args.out or tempfile.mkdtemp(prefix="work-", dir=tmp.parent)
    if os.environ.get("PREFECT_API_URL"):
        log = soak(args)
    else:
        from prefect.testing.utilities import prefect_test_harness

        with prefect_test_harness(server_startup_timeout=180):
            log = soak(args)
    # The temporary API's own database lives in TMPDIR while it runs and goes with the server process, a moment
    # after the harness returns: only entries still there after that count.
    deadline = time.time() + 30
    while any(tmp.iterdir()) and time.time() < deadline:
        time.sleep(1)
    log["tmp_leftovers"] = sorted(str(p) for p in tmp.rglob("*"))
    ok = (not log["runs"]["rebuild"]["failed"] and not log["runs"]["shot"]["failed"] and not log["mismatches"]
          and log["rss"]["growth"] <= 0.10 and log["cache_bound_held"] and not log["leftovers"]
          and not log["tmp_leftovers"])
    log["ok"] = ok
    text = json.dumps(log, indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
