"""Two rebuilds into one OUT at the same moment (the nightly run and a manual one): both succeed, they share the
stage work (each stage computed once, the other run waiting on its lock) instead of deleting each other's
temporaries, and OUT holds exactly the shared results."""

import filecmp
import subprocess
import sys
from pathlib import Path

from lgi.io.record import RECORD_FILE
from tests.test_resume import RUN, _env


# 16 s (two rebuild processes at once): in the default set, as the nightly and a manual run may meet
def test_two_rebuilds_into_one_out_at_once(prefect_api: str, tmp_path: Path, obj_folder: Path,
                                          small_actor, layout_csv: Path) -> None:
    root = Path(__file__).resolve().parents[1]
    markers = layout_csv
    out, cache = tmp_path / "shared", tmp_path / "shared" / ".cache"
    procs = []
    for k in range(2):  # two processes (a worker's run and a manual one) on one Prefect API
        (tmp_path / f"run{k}").mkdir()
        env = _env(tmp_path / f"run{k}", prefect_api)
        procs.append(subprocess.Popen([sys.executable, "-c", RUN, str(obj_folder), str(out), str(markers), str(cache)],
                                      cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    results = [p.communicate(timeout=900) for p in procs]
    for p, (_, err) in zip(procs, results, strict=True):
        assert p.returncode == 0, err[-3000:]
    import ast

    stages = [ast.literal_eval(o.split("STAGES", 1)[1].strip()) for o, _ in results]
    # Each stage computed once: where one run computed it, the other waited on its lock and then hit.
    for name in stages[0]:
        assert not (stages[0][name] is False and stages[1][name] is False), (name, stages)
    # One result per stage in the shared cache (computed once), and OUT holds exactly those results.
    entries = {d.name: [e for e in d.iterdir() if not e.name.startswith(".")] for d in cache.iterdir() if d.is_dir()}
    assert all(len(v) == 1 for v in entries.values()), entries
    for name, src in (("dataset", entries["stabilise"][0] / "dataset"), ("index", entries["index"][0] / "index"),
                      ("verification", entries["verify"][0])):
        mine = sorted(p.relative_to(src) for p in src.rglob("*") if p.is_file() and not p.name.startswith("."))
        theirs = sorted(p.relative_to(out / name) for p in (out / name).rglob("*") if p.is_file()
                        and p.name not in ("worst.png", RECORD_FILE))  # the picture is drawn after publishing
        assert mine == theirs, (name, mine, theirs)
        assert all(filecmp.cmp(src / f, out / name / f, shallow=False) for f in mine), name
    leftovers = [p for p in out.rglob("*") if ".tmp-" in p.name or ".old-" in p.name]
    assert not leftovers, leftovers
