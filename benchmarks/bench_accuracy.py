"""LGI against the baselines on realistic input, every method on the same frames in one run.

    python benchmarks/bench_accuracy.py [--sets synthetic,ict_jaw,ict_heldout,ict_combination,session_0,session_150,
                                                session_400,ict_session] [--frames F] [--out DIR]

Sets (lgi/evaluation/benchsets/), each with clean bundles and with tracking noise (0.3 mm per coordinate, 5 % of
marker-frames missing in runs of 1-6 frames): (a) the synthetic actor's 300-frame held-out performance;
(b) an ICT actor whose jaw rotates about a fitted hinge (200 frames of 1-4 expressions, linear blends);
(c) held-out ICT shapes and mixes involving them (66 independent poses, dataset built without them);
(d) the jaw actor with combination shapes whose correctives grow with the product of their weights
(120 frames); (e) a capture session: the synthetic actor's 47 shapes plus 0, 150 or 400 captured poses (its true
nonlinear face at frames of another performance), tested on a 160-frame held-out performance (``session_N``), and
the frames of (d) against the ICT jaw actor's 57 shapes plus 150 captured frames of another performance of the
same actor, correctives and jaw included (``ict_session``). On the session sets the plain blendshape fit gets the
best of four ridge weights chosen on the truth (which favours it). The ICT sets are skipped, with the reason, when
../shared/data/ict-facekit is absent.

Prints one table per set and bundles kind, then LGI's figures on the session sets per number of scans, and writes
``accuracy.csv`` (long form) into ``--out``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small bounded fits: threaded BLAS is 40x slower here

DEFAULT_SETS = ("synthetic,ict_jaw,ict_heldout,ict_combination,session_0,session_150,session_400,session_0_norig,"
                "session_150_norig,session_400_norig,ict_session")
RIG_FIT = "blendshape fit + rig"
RIG_FIT_SMOOTHED = "blendshape fit + rig, smoothed bundles"


def session_summary(table, sets: dict) -> str:
    """LGI (default) on the session sets as a Markdown table: RMS / p95 / max (mm) per set and bundles kind, the
    RMS ratio to the best baseline and, on noisy bundles, to the per-frame rigged fit and to the rigged fit of the
    smoothed bundles ("-" where a set has no such row)."""
    from lgi.evaluation.accuracy import SESSION_PREFIXES

    lines = ["| set | scans | bundles | RMS | p95 | max | RMS / best baseline | p95 / best baseline | "
             "max / lowest baseline max | RMS / rig fit | RMS / rig fit, smoothed bundles |", "|" + "---|" * 11]
    for name, bs in sets.items():
        if not name.startswith(SESSION_PREFIXES):
            continue
        for kind in ("clean", "noisy"):
            rows = table[(table.set == name) & (table.bundles == kind)].set_index("method")
            if "LGI (default)" not in rows.index:
                continue
            r = rows.loc["LGI (default)"]
            base_max = rows[rows.baseline.astype(bool)].max_mm.min()
            ratios = [f"{r.rms_vs_best_baseline:.2f}", f"{r.p95_vs_best_baseline:.2f}", f"{r.max_mm / base_max:.2f}"]
            for other in (RIG_FIT, RIG_FIT_SMOOTHED):
                ok = kind == "noisy" and other in rows.index
                ratios.append(f"{r.rms_mm / rows.loc[other, 'rms_mm']:.2f}" if ok else "-")
            lines.append(f"| {name} | {len(bs.info['scan_frames'])} | {kind} | {r.rms_mm:.4f} | {r.p95_mm:.4f} | "
                         f"{r.max_mm:.3f} | " + " | ".join(ratios) + " |")
    return "\n".join(lines) if len(lines) > 2 else ""


def doc_table(table, name: str) -> str:
    """One set's rows, clean then noisy, as the Markdown table of ``docs/accuracy.md`` (a bundles column first)."""
    from lgi.evaluation.accuracy import format_table

    sub = table[table.set == name].drop(columns=[c for c in ("jitter_mm2",) if c in table]).copy()
    if "note" in sub and not sub.note.fillna("").astype(bool).any():
        sub = sub.drop(columns="note")
    sub["method"] = sub.method.where(sub.method != "LGI (default)", "**LGI (default)**")
    lines = format_table(sub).splitlines()
    return "\n".join(["| bundles " + lines[0], "|---" + lines[1]]
                     + [f"| {b} " + line for b, line in zip(sub.bundles, lines[2:], strict=True)])


def doc_summary(table) -> str:
    """LGI (default) against the best baseline on every set and bundles kind, as a Markdown table."""
    rows = ["| set | bundles | LGI RMS / p95 / max mm | RMS / best baseline | p95 / best baseline | "
            "max / lowest baseline max | RMS / fit of the smoothed bundles |", "|" + "---|" * 7]
    for (name, kind), g in table.groupby(["set", "bundles"], sort=False):
        lgi = g[g.method == "LGI (default)"].iloc[0]
        base = g[g.baseline.astype(bool)]
        smoothed = g[g.method.str.endswith("smoothed bundles")]
        rows.append(f"| {name} | {kind} | {lgi.rms_mm:.3g} / {lgi.p95_mm:.3g} / {lgi.max_mm:.3g} | "
                    f"{lgi.rms_vs_best_baseline:.2f} | {lgi.p95_vs_best_baseline:.2f} | "
                    f"{lgi.max_mm / base.max_mm.min():.2f} | "
                    + (f"{lgi.rms_mm / smoothed.rms_mm.iloc[0]:.2f}" if len(smoothed) else "-") + " |")
    return "\n".join(rows)


def update_doc(path: Path, table) -> list[str]:
    """Rewrite the tables of a Markdown file between ``<!-- table:NAME -->`` and ``<!-- /table -->`` markers (NAME a
    set of ``table``, or ``summary``); returns the names replaced. Text outside the markers is left alone."""
    import re

    text = path.read_text()
    done = []

    def put(m: re.Match) -> str:
        name = m.group(1)
        if name != "summary" and name not in set(table.set):
            return m.group(0)
        done.append(name)
        body = doc_summary(table) if name == "summary" else doc_table(table, name)
        return f"<!-- table:{name} -->\n{body}\n<!-- /table -->"

    text = re.sub(r"<!-- table:([\w-]+) -->\n.*?<!-- /table -->", put, text, flags=re.S)
    path.write_text(text)
    return done


def main() -> int:
    from common import ict_dir_or_none, load_sets, needs_ict

    from lgi.evaluation.accuracy import accuracy_benchmark

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default=DEFAULT_SETS)
    ap.add_argument("--frames", type=int, default=None, help="first F frames of each set (default: all)")
    ap.add_argument("--out", default="bench-accuracy")
    ap.add_argument("--doc", help="also rewrite the tables of this Markdown file (docs/accuracy.md) between its "
                                  "<!-- table:SET --> markers")
    ap.add_argument("--from-csv", help="no run: take the table from this accuracy.csv (with --doc)")
    args = ap.parse_args()
    if args.from_csv:
        import pandas as pd

        table = pd.read_csv(args.from_csv)
        print("tables written:", ", ".join(update_doc(Path(args.doc), table)) if args.doc else "none (no --doc)")
        return 0
    names = [n for n in args.sets.split(",") if n]
    ict = ict_dir_or_none()
    if ict is None:
        dropped = [n for n in names if needs_ict(n)]
        if dropped:
            print(f"ICT FaceKit not found (../shared/data/ict-facekit or $LGI_SHARED_DATA): {', '.join(dropped)} "
                  "skipped")
        names = [n for n in names if not needs_ict(n)]
    t0 = time.perf_counter()
    sets = load_sets(names, ict)
    table, _ = accuracy_benchmark(sets, args.frames, log=lambda s: print(s, flush=True))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "accuracy.csv", index=False, float_format="%.6g")
    if args.doc:
        print("tables written into", args.doc, ":", ", ".join(update_doc(Path(args.doc), table)))
    summary = session_summary(table, sets)
    if summary:
        print("\nCapture sessions, LGI (default) per number of scans (mm; ratios of RMS, <= 1 means LGI is at least "
              "as accurate):")
        print(summary)
    lgi = table[table.method == "LGI (default)"].set_index(["set", "bundles"])
    print("\nLGI (default) against the best baseline (RMS and p95 ratios; <= 1 means at least as accurate):")
    for (s, b), r in lgi.iterrows():
        print(f"  {s:16s} {b:5s}  RMS x{r.rms_vs_best_baseline:.2f}  p95 x{r.p95_vs_best_baseline:.2f}")
    print(f"({time.perf_counter() - t0:.0f} s; {out.resolve() / 'accuracy.csv'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
