"""Deliberate faults, to show that the tests notice them.

Each fault is a small, named change to the code (a string replaced, the target asserted to occur exactly once so
that a fault whose code has changed is reported as stale instead of silently skipped). For each one the script
copies the repository to a temporary folder, applies the change there, runs the tests meant to notice it and
reports whether any failed ("caught") or all passed ("MISSED"). The repository itself is never modified; the
temporary copies are removed afterwards.

    python scripts/check_mutations.py            # every fault
    python scripts/check_mutations.py --list     # their names
    python scripts/check_mutations.py sigint-ignored mesh-before-correction

Exit status: 0 when every fault was caught, 1 when one was missed or a test run could not be judged (the tests
failed to start), 2 when a fault's target text is gone (update the fault).

A run whose faults are all caught records each one's digest (its definition, the file it changes and the test
files it runs) in ``scripts/mutations-checked.json``. The default test suite (tests/test_mutations.py) checks
every target, and runs again, in CI, each fault whose digest is not recorded: its code or tests changed since it
was last caught.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BAD = "tests/test_bad_input.py"
#: The digests of the faults at the last run of them all that caught every one.
RECORD = ROOT / "scripts" / "mutations-checked.json"


@dataclass(frozen=True)
class Fault:
    name: str
    what: str  # the fault in words
    path: str  # the file changed, relative to the repository
    old: str  # text that must occur exactly once
    new: str
    tests: tuple[str, ...]  # pytest node ids or files, relative to the repository


FAULTS = [
    # --- signals, pipes and exit statuses ---------------------------------------------------------------------
    Fault("sigint-ignored", "Ctrl-C ignored by the command's handler",
          "lgi/_entry.py", "        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()\n",
          "        if signum == signal.SIGTERM:\n            raise Terminated()\n",
          (f"{BAD}::test_signal_at_a_stage_leaves_nothing[sigint-solve]",)),
    Fault("sigterm-ignored", "SIGTERM ignored while the command works",
          "lgi/cli.py", "def _raise_terminated(signum: int, frame: object) -> None:\n    raise Terminated()\n",
          "def _raise_terminated(signum: int, frame: object) -> None:\n    return None\n",
          (f"{BAD}::test_signal_at_a_stage_leaves_nothing[sigterm-solve]",)),
    Fault("signal-at-shutdown-kills", "a signal after the command returned still raises (death by SIGINT: -2)",
          "lgi/_entry.py", "        if done:\n", "        if False:\n",
          (f"{BAD}::test_signal_during_shutdown_keeps_the_outputs",)),
    Fault("sigterm-status-130", "SIGTERM reported as an interrupt (130, not 143)",
          "lgi/cli.py", "            return 143 if isinstance(stop, Terminated) else 130\n",
          "            return 130\n",
          (f"{BAD}::test_signal_at_a_stage_leaves_nothing[sigterm-write]",)),
    Fault("exit-handlers-skipped", "an interrupted command leaves without its exit handlers (the Prefect server "
          "that --flow started keeps running)",
          "lgi/_entry.py", "            atexit._run_exitfuncs()\n", "            pass\n",
          (f"{BAD}::test_signal_inside_a_flow_task_stops_the_local_server",)),
    Fault("broken-pipe-handler-deleted", "a closed pipe handled as any other OS error (exit 2, 'Broken pipe')",
          "lgi/cli.py", "    except BrokenPipeError:\n", "    except NotImplementedError:\n",
          (f"{BAD}::test_closed_pipe_is_quiet",)),
    Fault("internal-error-status-2", "a bug reported as bad input (exit 2 instead of 3)",
          "lgi/cli.py", "\"traceback and report it)\", file=sys.stderr)\n        return 3\n",
          "\"traceback and report it)\", file=sys.stderr)\n        return 2\n",
          (f"{BAD}::test_internal_error_is_status_3_and_debug_prints_the_traceback",)),
    Fault("debug-ignored", "--debug prints no traceback",
          "lgi/cli.py", "        if debug:\n            import traceback\n",
          "        if False:\n            import traceback\n",
          (f"{BAD}::test_internal_error_is_status_3_and_debug_prints_the_traceback",)),
    Fault("bad-input-status-1", "bad input reported as a failed check (exit 1 instead of 2)",
          "lgi/cli.py", "            print(f\"{name}: error: {err}\", file=sys.stderr)\n            return 2\n",
          "            print(f\"{name}: error: {err}\", file=sys.stderr)\n            return 1\n",
          (f"{BAD}::test_bad_input[bundles-inf]",)),
    # --- outputs on disk --------------------------------------------------------------------------------------
    Fault("staging-kept-on-error", "an interrupted or failed run leaves its staging folder in OUT",
          "lgi/io/atomic.py", "                shutil.rmtree(stage, ignore_errors=True)\n", "                pass\n",
          (f"{BAD}::test_signal_at_a_stage_leaves_nothing[sigint-write]",)),
    Fault("killed-run-temporaries-kept", "a killed run's temporaries are never swept by the next run",
          "lgi/io/atomic.py",
          "    return name.startswith(prefix) and pid.isdigit() and not _alive(int(pid))\n", "    return False\n",
          (f"{BAD}::test_sigkill_then_rerun_cleans_up",)),
    Fault("stage-cache-unlocked", "concurrent rebuilds compute the same stage without taking turns",
          "lgi/io/cache.py", "        with locked(self.root / stage / f\".{key}.lock\"):\n",
          "        with contextlib.nullcontext():\n",
          ("tests/test_concurrent_rebuild.py",)),
    Fault("cache-never-hits", "a resumed rebuild recomputes the stages that finished",
          "lgi/io/cache.py", "            if (out / \".complete\").is_file():\n", "            if False:\n",
          ("tests/test_resume.py",)),
    # --- the reconstruction -----------------------------------------------------------------------------------
    Fault("mesh-before-correction", "the mesh is kept from before the correction through the bundles, while the "
          "residuals are those after it (the correction works on a copy)",
          "lgi/solve/surface.py",
          "        a = self._a\n        resid_vec = np.where(seen[:, None], p - self.layout.evaluate(x), 0.0)\n",
          "        a = self._a\n        x = x.copy()\n"
          "        resid_vec = np.where(seen[:, None], p - self.layout.evaluate(x), 0.0)\n",
          ("tests/test_cli.py::test_build_reconstruct_verify",
           "tests/test_lgi.py::test_heldout_performance_passes_through_bundles")),
    Fault("marker-weights-rotated", "markers evaluated with their barycentric weights on the wrong corners",
          "lgi/dataset/markers.py", "        return np.einsum(\"...mkd,mk->...md\", corners, self.weights)\n",
          "        return np.einsum(\"...mkd,mk->...md\", corners, self.weights[:, [1, 2, 0]])\n",
          ("tests/test_cli.py::test_build_reconstruct_verify",)),
    Fault("natural-weights-nearest-bundle", "the natural-neighbour blend replaced by the nearest bundle's weights",
          "lgi/index/natural.py", "    w_region /= w_region.sum(1, keepdims=True)\n",
          "    w_region /= w_region.sum(1, keepdims=True)\n    w_region[:] = 0.0\n"
          "    w_region[np.arange(len(w_region)), owner[queries]] = 1.0\n",
          ("tests/test_natural.py", "tests/test_lgi.py::test_heldout_performance_passes_through_bundles")),
    Fault("jaw-file-held-at-rest", "a jaw file given with --jaw read as the jaw at rest",
          "lgi/jobs/reconstruct/options.py",
          "        raise InputError(\"non-finite jaw parameter\", path=p, frame=int(frames[r]))\n    return vals\n",
          "        raise InputError(\"non-finite jaw parameter\", path=p, frame=int(frames[r]))\n"
          "    return np.zeros_like(vals)\n",
          ("tests/test_jaw_temporal.py",)),
    Fault("chunk-boundary-off-by-one", "the reconstruct-shot flow's chunks end one frame early",
          "lgi/orchestration/reconstruct.py",
          "    return [(lo, min(lo + chunk_size, n_frames)) for lo in range(0, n_frames, chunk_size)]\n",
          "    return [(lo, min(lo + chunk_size - 1, n_frames)) for lo in range(0, n_frames, chunk_size)]\n",
          ("tests/test_reconstruct_job.py::test_plain_and_flow_agree_with_non_default_options",)),
    Fault("noise-always-exact", "noisy bundles always judged exact (never smoothed and fitted)",
          "lgi/solve/temporal.py",
          "        return bool(np.isfinite(self.noise_mm) and self.coherence < NOISE_MAX_COHERENCE)\n",
          "        return False\n",
          ("tests/test_local_fit.py::test_noise_is_estimated_and_handled",)),
    Fault("default-verify-tolerance-1mm", "the default verification tolerance 0.01 mm became 1 mm",
          "lgi/jobs/verify.py", "    tolerance: float = option(0.01,", "    tolerance: float = option(1.0,",
          (f"{BAD}::test_default_verification_tolerance",)),
    Fault("obj-uv-indices-zero-based", "OBJ files written with 0-based texture-coordinate indices",
          "lgi/io/obj.py", "    fuv = None if face_uvs is None else np.asarray(face_uvs) + 1\n",
          "    fuv = None if face_uvs is None else np.asarray(face_uvs)\n",
          ("tests/test_obj.py",)),
    Fault("augment-count-drops-one", "the augmentation report counts one point fewer than the in-betweens kept",
          "lgi/augment/combinations.py", "\"kept\": pts[\"augmented\"] - pts[\"original\"]}",
          "\"kept\": pts[\"augmented\"] - pts[\"original\"] - 1}",
          ("tests/test_cli.py::test_augment_linear",)),
    Fault("layout-pooled-row-first-shape", "the held-out table's pooled row (ALL) is the first shape's",
          "lgi/jobs/layout.py",
          "        rows.append({\"method\": method, \"shape\": \"ALL\", **_stats(err.ravel())})\n",
          "        rows.append({\"method\": method, \"shape\": \"ALL\", **_stats(err[0])})\n",
          ("tests/test_layout_design.py::test_evaluate_reports_numbers",)),
]


def _copy(dst: Path) -> None:
    """The working tree (with others' uncommitted edits, as the tests would see them), without caches that the
    tests do not need; the numba cache (__pycache__ next to the kernels) is kept so nothing recompiles."""
    shutil.copytree(ROOT, dst, symlinks=True, ignore=shutil.ignore_patterns(
        ".git", ".pytest_cache", ".ruff_cache", ".benchmarks", "*.egg-info"))


def check_targets(faults: list[Fault]) -> list[str]:
    """The faults whose target text does not occur exactly once (stale: the code changed)."""
    stale = []
    for f in faults:
        n = (ROOT / f.path).read_text().count(f.old) if f.old else 0
        if n != 1:
            stale.append(f"{f.name}: {f.path} holds the target {n} times (expected once): {f.old[:80]!r}")
    return stale


def digest(f: Fault) -> str:
    """SHA-256 of the fault's definition, the file it changes and the test files it runs: what its verdict
    depends on."""
    h = hashlib.sha256(repr(f).encode())
    for rel in (f.path, *sorted({t.split("::")[0] for t in f.tests})):
        h.update(rel.encode() + b"\0" + (ROOT / rel).read_bytes())
    return h.hexdigest()


def unchecked(faults: list[Fault]) -> list[Fault]:
    """The faults whose digest differs from the record of the last whole check (or that it lacks)."""
    record = json.loads(RECORD.read_text()) if RECORD.is_file() else {}
    return [f for f in faults if record.get(f.name) != digest(f)]


def run_fault(f: Fault, base: Path, keep: bool = False) -> tuple[str, float, str]:
    """("caught" | "MISSED" | "ERROR" | "STALE", seconds, the tail of pytest's output) for one fault, on a copy
    at ``base/repo`` (the same path for every fault, so that the compiled kernels cached in ``base/numba-cache``,
    which numba keys by the source's path, are compiled once per run of this script, not once per fault)."""
    t0 = time.perf_counter()
    repo = base / "repo"
    shutil.rmtree(repo, ignore_errors=True)
    try:
        _copy(repo)
        target = repo / f.path
        text = target.read_text()
        if text.count(f.old) != 1:  # changed since the check at the start (someone is editing that file)
            return "STALE", time.perf_counter() - t0, f"{f.path} holds the target {text.count(f.old)} times"
        target.write_text(text.replace(f.old, f.new))
        # The copy's lgi first, for pytest and for every command the tests start (they import lgi through
        # PYTHONPATH, ahead of the editable install that points at the repository).
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(repo), os.environ.get("PYTHONPATH", "")]).rstrip(
            os.pathsep), "PYTHONDONTWRITEBYTECODE": "1", "NUMBA_CACHE_DIR": str(base / "numba-cache"),
            # The shared data the repository finds beside itself (../shared/data), which the copy would not.
            "LGI_SHARED_DATA": os.environ.get("LGI_SHARED_DATA", str(ROOT.parent / "shared" / "data"))}
        r = subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
                            f"--basetemp={base / 'pytest'}", *f.tests],
                           cwd=repo, env=env, capture_output=True, text=True, timeout=1800)
        lines = (r.stdout + r.stderr).strip().splitlines()
        failed = [ln for ln in lines if ln.startswith(("FAILED ", "ERROR "))]
        tail = "\n".join(failed[:1] if r.returncode == 1 and failed else lines[-3:])
        # pytest: 1 = tests failed (the fault was noticed); 0 = all passed; anything else = could not run them.
        verdict = {1: "caught", 0: "MISSED"}.get(r.returncode, "ERROR")
        if verdict == "caught" and not any(ln.startswith("FAILED ") for ln in failed):
            verdict = "ERROR"  # a fixture or the collection broke: the tests did not get to judge the fault
        if verdict == "caught":
            check = subprocess.run([sys.executable, "-c", "import lgi, sys; print(lgi.__file__)"], cwd=base, env=env,
                                   capture_output=True, text=True)
            if not check.stdout.strip().startswith(str(repo)):  # the tests must have run the changed copy
                verdict, tail = "ERROR", f"lgi imported from {check.stdout.strip()}, not the copy"
        return verdict, time.perf_counter() - t0, tail
    finally:
        if keep:
            os.replace(repo, base / f.name)
        else:
            shutil.rmtree(repo, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("names", nargs="*", help="faults to run (default: all)")
    p.add_argument("--list", action="store_true", help="list the faults and exit")
    p.add_argument("--keep", action="store_true", help="keep the changed copies (for a look at a missed fault)")
    args = p.parse_args(argv)
    faults = [f for f in FAULTS if not args.names or f.name in args.names]
    unknown = set(args.names) - {f.name for f in FAULTS}
    if unknown:
        p.error(f"unknown faults: {sorted(unknown)}")
    if args.list:
        for f in faults:
            print(f"{f.name:32s} {f.path}: {f.what}")
        return 0
    stale = check_targets(faults)
    if stale:
        print("stale faults (their code changed; update them):", *stale, sep="\n  ", file=sys.stderr)
        return 2
    results = []
    base = Path(tempfile.mkdtemp(prefix="lgi-mutations-"))
    try:
        for i, f in enumerate(faults, 1):
            verdict, seconds, tail = run_fault(f, base, args.keep)
            results.append(verdict)
            print(f"[{i:2d}/{len(faults)}] {verdict:6s} {f.name:32s} {seconds:6.1f} s  {f.what}", flush=True)
            print("        " + tail.replace("\n", "\n        "), flush=True)  # the test that noticed, or why not
    finally:
        if args.keep:
            print(f"copies kept in {base}")
        else:
            shutil.rmtree(base, ignore_errors=True)
    caught = results.count("caught")
    if caught == len(faults):
        record = json.loads(RECORD.read_text()) if RECORD.is_file() else {}
        record = {f.name: record[f.name] for f in FAULTS if f.name in record}  # a fault no longer defined goes
        record.update({f.name: digest(f) for f in faults})
        RECORD.write_text(json.dumps(record, indent=1) + "\n")
        print(f"digests of the faults caught written to {RECORD.relative_to(ROOT)}")
    print(f"{caught} of {len(faults)} faults caught" + ("" if caught == len(faults) else
                                                       f"; missed or not run: {len(faults) - caught}"))
    return 0 if caught == len(faults) else 1


if __name__ == "__main__":
    sys.exit(main())
