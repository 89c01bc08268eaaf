"""A corpus of bad input, bad options, bad output paths, corrupt stored files, re-runs and interrupts, through
the command line: each case asserts the exit status, that no traceback reaches the user, that the message
names the culprit, and what is left on disk."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgi.cli import main
from lgi.io.npz import save_npz
from lgi.io.obj import write_obj
from lgi.io.record import RECORD_FILE, read_record
from tests.checks import THROUGH_MM, bundle_gaps_mm, peak_memory_run


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own usage errors
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    """A small synthetic actor, its OBJ folder, two indexes (with and without a jaw rig), a reconstruction."""
    w = tmp_path_factory.mktemp("world")
    assert main(["synth", "--out", str(w / "s"), "--vertices", "1500", "--frames", "12", "-q"]) == 0
    for name, extra in (("idx", []), ("idxr", ["--jaw-rig", str(w / "s" / "jaw_rig.npz")])):
        assert main(["build", str(w / "s" / "dataset"), "--markers", str(w / "s" / "markers.csv"), "--out",
                     str(w / name), "-q", *extra]) == 0
    assert main(["reconstruct", str(w / "idx"), "--bundles", str(w / "s" / "bundles.csv"), "--out",
                 str(w / "rec"), "-q"]) == 0
    from lgi.synthetic import actor as synth

    a = synth.make_actor(1500)
    objs = w / "objs"
    write_obj(objs / "neutral.obj", a.neutral, a.face_vertices, a.face_offsets, a.uvs, a.face_uvs)
    eye = np.eye(len(synth.CONTROLS))
    for name in ("jaw_open", "smile_L"):
        write_obj(objs / f"{name}.obj", a.evaluate(eye[synth.C[name]]), a.face_vertices, a.face_offsets, a.uvs,
                  a.face_uvs)
    (w / "jaw.csv").write_text("frame,open_deg,yaw_deg,roll_deg,forward_cm\n" +
                               "".join(f"{f},5,0,0,0\n" for f in range(12)))
    return w


# ------------------------------------------------------------------------------------------- mutations
def text_edit(rel: str, old: str, new: str, count: int = 1):
    def f(w: Path, c: Path) -> None:
        p = c / rel
        s = p.read_text()
        assert old in s, (rel, old)
        p.write_text(s.replace(old, new, count))
    return f


def write(rel: str, text: str | bytes):
    def f(w: Path, c: Path) -> None:
        p = c / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(text if isinstance(text, bytes) else text.encode())
    return f


def copy(src: str, dst: str | None = None):
    def f(w: Path, c: Path) -> None:
        s, d = w / src, c / (dst or src)
        d.parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree if s.is_dir() else shutil.copy)(s, d)
    return f


def truncate(rel: str, keep: int):
    def f(w: Path, c: Path) -> None:
        p = c / rel
        p.write_bytes(p.read_bytes()[:keep])
    return f


def chain(*fs):
    def f(w: Path, c: Path) -> None:
        for g in fs:
            g(w, c)
    return f


def obj_vertex(rel: str, k: int, line: str):
    """Replace the k-th ``v`` line of an OBJ in the case's copy of the OBJ folder."""
    def f(w: Path, c: Path) -> None:
        p = c / rel
        lines = p.read_text().splitlines()
        vs = [i for i, ln in enumerate(lines) if ln.startswith("v ")]
        lines[vs[k]] = line
        p.write_text("\n".join(lines) + "\n")
    return f


def bundles_csv(edit: Callable[[pd.DataFrame], pd.DataFrame]):
    def f(w: Path, c: Path) -> None:
        d = pd.read_csv(w / "s" / "bundles.csv", dtype=str)
        edit(d).to_csv(c / "b.csv", index=False)
    return f


def set_cell(row: int, col: str, value: str):
    def e(d: pd.DataFrame) -> pd.DataFrame:
        d.loc[row, col] = value
        return d
    return e


def npz_edit(rel: str, edit: Callable[[dict], dict]):
    def f(w: Path, c: Path) -> None:
        p = c / rel
        with np.load(p) as z:
            a = {k: z[k] for k in z.files}
        save_npz(p, **edit(a))
    return f


def manifest_edit(rel: str, edit: Callable[[dict], dict | list]):
    def f(w: Path, c: Path) -> None:
        p = c / rel
        p.write_text(json.dumps(edit(json.loads(p.read_text()))))
    return f


def pickled_npz(rel: str):
    def f(w: Path, c: Path) -> None:
        p = c / rel
        with np.load(p) as z:
            a = {k: z[k] for k in z.files}
        a["evil"] = np.array([{"x": 1}], dtype=object)
        np.savez(p.with_suffix(""), **a)  # numpy's writer pickles object arrays
    return f


def drop_key(key: str):
    def e(d: dict) -> dict:
        d.pop(key)
        return d
    return e


def _cam(d: dict, k: int, key: str, value) -> dict:
    cams = [dict(c) for c in d["cameras"]]
    cams[k][key] = value
    return {**d, "cameras": cams}


def calib_json(edit: Callable[[dict], dict]):
    """A valid stereo calibration document (lgi calibrate's format), edited, as ``calib.json``."""
    def f(w: Path, c: Path) -> None:
        cam = {"K": [[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]], "dist": [0.0, 0, 0, 0, 0]}
        doc = {"image_size": [640, 480], "model": "pinhole", "cameras": [cam, dict(cam)],
               "R": [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]], "T": [-60.0, 0, 0]}
        (c / "calib.json").write_text(json.dumps(edit(doc)))  # Python's JSON writes NaN and Infinity as such
    return f


# ------------------------------------------------------------------------------------------------ cases
@dataclass
class Case:
    id: str
    argv: list[str]
    code: int
    says: str
    setup: Callable[[Path, Path], None] | None = None
    absent: tuple[str, ...] = ("out",)  # case-dir entries that must not exist afterwards


W, C = "{w}", "{c}"
S = f"{W}/s"
REC = ["reconstruct", f"{W}/idx", "--bundles", f"{S}/bundles.csv", "--out", f"{C}/out", "-q"]
RECB = ["reconstruct", f"{W}/idx", "--bundles", f"{C}/b.csv", "--out", f"{C}/out", "-q"]
RECI = ["reconstruct", f"{C}/idx", "--bundles", f"{S}/bundles.csv", "--out", f"{C}/out", "-q"]
IMP = ["import", f"{C}/objs", "--out", f"{C}/out", "-q", "--rigid-vertices", "none"]
BUILD = ["build", f"{S}/dataset", "--markers", f"{S}/markers.csv", "--out", f"{C}/out", "-q"]
BUILDM = ["build", f"{S}/dataset", "--markers", f"{C}/m.csv", "--out", f"{C}/out", "-q"]
BUILDD = ["build", f"{C}/ds", "--markers", f"{S}/markers.csv", "--out", f"{C}/out", "-q"]
AUG = ["augment", f"{S}/dataset", "--out", f"{C}/out", "-q"]
RIG = ["rig", f"{S}/dataset", "--shapes", "jaw_*", "--out", f"{C}/out"]
EXP = ["export", f"{C}/rec", "--index", f"{W}/idx", "-q"]
CAL = ["calibrate", f"{C}/imgs", "--out", f"{C}/out"]
TRK = ["track", f"{C}/foot", "--calib", f"{C}/calib.json", "--markers", f"{S}/markers.csv", "--out", f"{C}/out"]
OBJS = copy("objs")
REC_COPY = copy("rec")
IDX = copy("idx")


def null_marker(path: Path, row: int) -> pd.DataFrame:
    d = pd.read_csv(path).astype({"marker": object})
    d.loc[row, "marker"] = None
    return d


def markers_cell(row: int, col: str, value: str):
    def f(w: Path, c: Path) -> None:
        d = pd.read_csv(w / "s" / "markers.csv", dtype=str, keep_default_na=False)
        d.loc[row, col] = value(d) if callable(value) else value
        d.to_csv(c / "m.csv", index=False)
    return f

CASES = [
    # --- import: malformed OBJ files ------------------------------------------------------------------
    Case("obj-nan-in-shape", IMP, 2, "non-finite coordinate",
         chain(OBJS, obj_vertex("objs/smile_L.obj", 3, "v nan nan nan"))),
    Case("obj-inf-in-neutral", IMP, 2, "neutral.obj", chain(OBJS, obj_vertex("objs/neutral.obj", 0, "v inf 0.5 0.5"))),
    Case("obj-1e39", IMP, 2, "beyond", chain(OBJS, obj_vertex("objs/jaw_open.obj", 5, "v 1e39 0 0"))),
    Case("obj-non-numeric", IMP, 2, "non-numeric", chain(OBJS, obj_vertex("objs/smile_L.obj", 2, "v 1 two 3"))),
    Case("obj-two-values", IMP, 2, "expected 3", chain(OBJS, obj_vertex("objs/smile_L.obj", 2, "v 1 2"))),
    Case("obj-vertex-missing", IMP, 2, "vertex count", chain(OBJS, obj_vertex("objs/smile_L.obj", 2, "# gone"))),
    Case("obj-face-out-of-range", IMP, 2, "out of range",
         chain(OBJS, text_edit("objs/neutral.obj", "\nf ", "\nf 99999 ", 1))),
    Case("obj-face-zero", IMP, 2, "index 0", chain(OBJS, text_edit("objs/neutral.obj", "\nf ", "\nf 0 ", 1))),
    Case("obj-face-differs", IMP, 2, "face", chain(OBJS, text_edit("objs/smile_L.obj", "\nf ", "\nf 1 2 3\n#", 1))),
    Case("obj-binary-garbage", IMP, 2, "smile_L.obj", chain(OBJS, write("objs/smile_L.obj", b"\x00\xff\x13garbage\n"))),
    Case("obj-uv-nan", IMP, 2, "non-finite", chain(OBJS, text_edit("objs/neutral.obj", "\nvt ", "\nvt nan 0\n#", 1))),
    Case("import-empty-folder", IMP, 2, "no OBJ files", write("objs/readme.txt", "nothing")),
    Case("import-missing-folder", IMP, 2, "not found", None),
    Case("import-neutral-unknown", [*IMP, "--neutral", "nobody"], 2, "nobody", OBJS),
    Case("import-include-nothing", [*IMP, "--include", "zzz*"], 2, "no shapes selected", OBJS),
    Case("import-units-unknown", [*IMP, "--units", "furlong"], 2, "furlong", OBJS),
    Case("import-rigid-file-missing", ["import", f"{C}/objs", "--out", f"{C}/out", "-q", "--rigid-vertices",
                                       f"{C}/nope.json"], 2, "nope.json", OBJS),
    Case("import-rigid-out-of-range", ["import", f"{C}/objs", "--out", f"{C}/out", "-q", "--rigid-vertices",
                                       f"{C}/r.json"], 2, "r.json", chain(OBJS, write("r.json", "[1, 2, 999999]"))),
    Case("import-rigid-not-json", ["import", f"{C}/objs", "--out", f"{C}/out", "-q", "--rigid-vertices",
                                   f"{C}/r.json"], 2, "r.json", chain(OBJS, write("r.json", "[1, 2,"))),
    Case("import-identity-bad-weight", [*IMP, "--identity", "identity_a=heavy"], 2, "--identity", OBJS),
    Case("import-identity-unknown", [*IMP, "--identity", "identity_a=1"], 2, "identity_a", OBJS),
    Case("import-identity-inf", [*IMP, "--identity", "identity_a=inf"], 2, "finite", OBJS),
    Case("import-out-is-file", IMP, 2, "a file of that name exists", chain(OBJS, write("out", "precious")), ()),
    Case("import-out-under-file", ["import", f"{C}/objs", "--out", f"{C}/f/sub", "-q"], 2, "a file is in its path",
         chain(OBJS, write("f", "x")), ("f/sub",)),
    # --- reconstruct: bundles files -------------------------------------------------------------------
    Case("bundles-missing", RECB, 2, "b.csv", None),
    Case("bundles-empty-file", RECB, 2, "b.csv", write("b.csv", "")),
    Case("bundles-header-only", RECB, 2, "no rows", write("b.csv", "frame,marker,x,y,z\n")),
    Case("bundles-missing-column", RECB, 2, "missing columns", write("b.csv", "frame,marker,x,y\n0,a,1,2\n")),
    Case("bundles-non-numeric-x", RECB, 2, "non-numeric x", bundles_csv(set_cell(5, "x", "abc"))),
    Case("bundles-fractional-frame", RECB, 2, "not an integer", bundles_csv(set_cell(7, "frame", "1.5"))),
    Case("bundles-frame-1e20", RECB, 2, "outside", bundles_csv(set_cell(7, "frame", "1e20"))),
    Case("bundles-coordinate-1e30", RECB, 2, "beyond", bundles_csv(set_cell(9, "y", "1e30"))),
    Case("bundles-inf", RECB, 2, "non-finite", bundles_csv(set_cell(9, "z", "inf"))),
    Case("bundles-partial-coordinates", RECB, 2, "some coordinates missing", bundles_csv(set_cell(3, "y", ""))),
    Case("bundles-unknown-marker", RECB, 2, "unknown marker", bundles_csv(set_cell(4, "marker", "nose_ring"))),
    Case("bundles-duplicate-row", RECB, 2, "b.csv",
         bundles_csv(lambda d: pd.concat([d, d.iloc[[10]]], ignore_index=True))),
    Case("bundles-frame-all-missing", RECB, 2, "frame 3",
         bundles_csv(lambda d: d.assign(**{c: d[c].where(d.frame != "3", "") for c in "xyz"}))),
    Case("bundles-binary-garbage", RECB, 2, "b.csv", write("b.csv", b"\x89PNG\r\n\x1a\n\x00\x00garbage")),
    Case("bundles-parquet-garbage", ["reconstruct", f"{W}/idx", "--bundles", f"{C}/b.parquet", "--out",
                                     f"{C}/out", "-q"], 2, "b.parquet", write("b.parquet", b"not parquet")),
    Case("bundles-parquet-columns", ["reconstruct", f"{W}/idx", "--bundles", f"{C}/b.parquet", "--out",
                                     f"{C}/out", "-q"], 2, "missing columns",
         lambda w, c: pd.DataFrame({"frame": [0], "x": [1.0]}).to_parquet(c / "b.parquet")),
    Case("bundles-marker-empty", RECB, 2, "b.csv", bundles_csv(set_cell(4, "marker", ""))),
    # --- reconstruct: options ------------------------------------------------------------------------
    *[Case(f"reconstruct-{flag.strip('-')}-{val}", [*REC, flag, val], 2, flag) for flag, val in (
        ("--smooth", "1002"), ("--smooth", "2.5"), ("--jaw-smooth", "1002"), ("--chunk-size", "0"),
        ("--max-gap", "1.5"),
        ("--temporal-weight", "nan"), ("--temporal-weight", "-1"), ("--spatial-weight", "inf"), ("--noise", "-1"),
        ("--noise", "abc"), ("--noise", "nan"), ("--fps", "0"), ("--fps", "-5"), ("--bilateral", "1"),
        ("--bilateral", "1:0"), ("--bilateral", "a:b"), ("--bilateral", "1:2:3:4"), ("--far-field", "5"),
        ("--far-field", "15:5"), ("--far-field", "-1:3"), ("--far-field", "a:b"), ("--far-field", "5:inf"))],
    Case("reconstruct-method-unknown", [*REC, "--method", "magic"], 2, "magic"),
    Case("reconstruct-smooth-not-a-number", [*REC, "--smooth", "three"], 2, "--smooth"),
    Case("reconstruct-jaw-none-rigged", ["reconstruct", f"{W}/idxr", "--bundles", f"{S}/bundles.csv", "--out",
                                         f"{C}/out", "-q", "--jaw", "none"], 2, "jaw rig"),
    Case("reconstruct-jaw-file-no-rig", [*REC, "--jaw", f"{W}/jaw.csv"], 2, "--jaw-rig"),
    Case("reconstruct-jaw-file-missing", ["reconstruct", f"{W}/idxr", "--bundles", f"{S}/bundles.csv", "--out",
                                          f"{C}/out", "-q", "--jaw", f"{C}/j.csv"], 2, "j.csv"),
    *[Case(f"reconstruct-jaw-file-{name}", ["reconstruct", f"{W}/idxr", "--bundles", f"{S}/bundles.csv", "--out",
                                            f"{C}/out", "-q", "--jaw", f"{C}/j.csv"], 2, says,
           write("j.csv", text)) for name, text, says in (
        ("no-column", "frame,open_deg\n0,1\n", "missing columns"),
        ("duplicate-frame", "frame,open_deg,yaw_deg,roll_deg,forward_cm\n0,1,0,0,0\n0,2,0,0,0\n", "twice"),
        ("missing-frame", "frame,open_deg,yaw_deg,roll_deg,forward_cm\n0,1,0,0,0\n", "no jaw parameters"),
        ("nan", "frame,open_deg,yaw_deg,roll_deg,forward_cm\n" + "".join(f"{f},nan,0,0,0\n" for f in range(12)),
         "non-finite"),
        ("garbage", "\x00\x01\x02", "j.csv"))],
    Case("reconstruct-out-is-file", REC, 2, "a file of that name exists", write("out", "precious"), ()),
    Case("reconstruct-out-under-file", ["reconstruct", f"{W}/idx", "--bundles", f"{S}/bundles.csv", "--out",
                                        f"{C}/f/sub", "-q"], 2, "a file is in its path", write("f", "x"), ("f/sub",)),
    Case("reconstruct-flow-bad-bundles", [*RECB, "--flow"], 2, "non-numeric x", bundles_csv(set_cell(5, "x", "abc"))),
    # --- corrupt stored index ----------------------------------------------------------------------------
    Case("index-missing", ["reconstruct", f"{C}/nothing", "--bundles", f"{S}/bundles.csv", "--out", f"{C}/out",
                           "-q"], 2, "not an LGI index"),
    Case("index-manifest-not-json", RECI, 2, "manifest.json", chain(IDX, write("idx/manifest.json", "{broken"))),
    Case("index-manifest-a-list", RECI, 2, "manifest", chain(IDX, write("idx/manifest.json", "[1, 2]"))),
    Case("index-manifest-missing-key", RECI, 2, "manifest lacks",
         chain(IDX, manifest_edit("idx/manifest.json", drop_key("markers")))),
    Case("index-npz-missing", RECI, 2, "index.npz", chain(IDX, lambda w, c: (c / "idx" / "index.npz").unlink())),
    Case("index-npz-truncated", RECI, 2, "index.npz", chain(IDX, truncate("idx/index.npz", 4000))),
    Case("index-npz-pickled", RECI, 2, "index.npz", chain(IDX, pickled_npz("idx/index.npz"))),
    Case("index-npz-missing-array", RECI, 2, "missing arrays",
         chain(IDX, npz_edit("idx/index.npz", drop_key("ptab")))),
    Case("index-deltas-truncated", RECI, 2, "deltas.npy", chain(IDX, truncate("idx/deltas.npy", 200))),
    Case("index-deltas-wrong-shape", RECI, 2, "deltas.npy",
         chain(IDX, lambda w, c: np.save(c / "idx" / "deltas.npy", np.zeros((3, 4, 3), np.float32)))),
    Case("index-neutral-nan", RECI, 2, "non-finite",
         chain(IDX, npz_edit("idx/index.npz", lambda a: {**a, "neutral": a["neutral"] * np.nan}))),
    # --- build ---------------------------------------------------------------------------------------
    Case("build-dataset-missing", ["build", f"{C}/nope", "--markers", f"{S}/markers.csv", "--out", f"{C}/out",
                                   "-q"], 2, "nope"),
    Case("build-markers-missing", ["build", f"{S}/dataset", "--markers", f"{C}/m.csv", "--out", f"{C}/out", "-q"],
         2, "m.csv"),
    Case("markers-missing-column", BUILDM, 2, "missing columns", write("m.csv", "name,triangle\na,1\n")),
    Case("markers-fractional-triangle", BUILDM, 2, "whole number",
         markers_cell(0, "triangle", lambda d: d.triangle[0] + ".5")),
    Case("markers-negative-vertex", BUILDM, 2, "whole number", markers_cell(0, "v0", lambda d: "-" + d.v0[0])),
    Case("markers-weights-not-convex", BUILDM, 2, "not convex", markers_cell(0, "w0", "1.5")),
    Case("markers-duplicate-name", BUILDM, 2, "duplicate marker name",
         markers_cell(1, "name", lambda d: d.name[0])),
    Case("markers-triangle-out-of-range", BUILDM, 2, "out of range", markers_cell(0, "triangle", "999999")),
    Case("markers-triangle-mismatch", BUILDM, 2, "forehead_L_01",
         markers_cell(0, "triangle", lambda d: str(int(d.triangle[0]) + 1))),
    Case("markers-no-name", BUILDM, 2, "without a name", markers_cell(0, "name", "")),
    Case("markers-non-numeric", BUILDM, 2, "non-numeric", markers_cell(0, "w0", "heavy")),
    Case("markers-empty", BUILDM, 2, "m.csv", write("m.csv", "")),
    *[Case(f"build-{flag.strip('-')}-{val}", [*BUILD, flag, val], 2, flag) for flag, val in (
        ("--knn", "-3"), ("--subset-fraction", "2"), ("--budget", "0"), ("--region-radius", "0"),
        ("--min-quality", "2"), ("--min-motion-rel", "-0.1"), ("--merge-tol", "nan"), ("--subsets", "-1"),
        ("--seed", "-4"))],
    Case("build-jaw-rig-missing", [*BUILD, "--jaw-rig", f"{C}/rig.npz"], 2, "rig.npz"),
    Case("build-jaw-rig-garbage", [*BUILD, "--jaw-rig", f"{C}/rig.npz"], 2, "rig.npz", write("rig.npz", "junk")),
    Case("build-out-is-file", BUILD, 2, "a file of that name exists", write("out", "precious"), ()),
    Case("dataset-manifest-broken", BUILDD, 2, "manifest", chain(copy("s/dataset", "ds"),
                                                                write("ds/manifest.json", "{"))),
    Case("dataset-deltas-truncated", BUILDD, 2, "deltas.npy", chain(copy("s/dataset", "ds"),
                                                                   truncate("ds/deltas.npy", 100))),
    Case("dataset-mesh-missing", BUILDD, 2, "mesh.npz", chain(copy("s/dataset", "ds"),
                                                             lambda w, c: (c / "ds" / "mesh.npz").unlink())),
    Case("dataset-units-mm", BUILDD, 2, "re-import", chain(copy("s/dataset", "ds"), manifest_edit(
        "ds/manifest.json", lambda m: {**m, "units": "mm"}))),
    Case("dataset-deltas-nan", BUILDD, 2, "non-finite", chain(copy("s/dataset", "ds"), lambda w, c: np.save(
        c / "ds" / "deltas.npy", np.load(c / "ds" / "deltas.npy") * np.nan))),
    # --- verify ------------------------------------------------------------------------------------------
    Case("verify-index-missing", ["verify", f"{C}/nope", "-q"], 2, "not an LGI index"),
    Case("verify-tolerance-negative", ["verify", f"{W}/idx", "--tolerance", "-1", "-q"], 2, "--tolerance"),
    Case("verify-shapes-nothing", ["verify", f"{W}/idx", "--shapes", "zzz", "-q"], 2, "zzz"),
    Case("verify-non-finite-fails", ["verify", f"{C}/idx", "-q"], 1, "non-finite",
         chain(IDX, lambda w, c: np.save(c / "idx" / "deltas.npy", np.load(c / "idx" / "deltas.npy") * np.nan)),
         ()),
    # --- augment -----------------------------------------------------------------------------------------
    Case("augment-no-method", AUG, 2, "--linear"),
    *[Case(f"augment-{flag.strip('-')}-{val}", [*AUG, "--linear", flag, val], 2, flag) for flag, val in (
        ("--orders", "9"), ("--orders", "x"), ("--levels", "0"), ("--levels", "1.5"), ("--levels", "abc"),
        ("--budget", "0"), ("--thickness", "0"), ("--iterations", "0"), ("--requires", "mouthClose"))],
    Case("augment-include-nothing", [*AUG, "--linear", "--include", "zzz"], 2, "zzz"),
    Case("augment-dataset-missing", ["augment", f"{C}/nope", "--out", f"{C}/out", "--linear"], 2, "nope"),
    Case("augment-out-is-file", [*AUG, "--linear"], 2, "a file of that name exists", write("out", "x"), ()),
    # --- rig ---------------------------------------------------------------------------------------------
    *[Case(f"rig-jaw-vertices-{name}", [*RIG, "--jaw-vertices", spec], 2, says) for name, spec, says in (
        ("two", "5:6", "at least 3"), ("letters", "a:b", "--jaw-vertices"), ("reversed", "10:5", "out of range"),
        ("beyond", "0:99999", "out of range"), ("file-missing", "{c}/jv.txt", "jv.txt"))],
    Case("rig-shapes-nothing", ["rig", f"{S}/dataset", "--jaw-vertices", "0:100", "--shapes", "zzz", "--out",
                                f"{C}/out"], 2, "zzz"),
    Case("rig-out-is-dir", [*RIG, "--jaw-vertices", "0:100"], 2, "a directory of that name exists",
         lambda w, c: (c / "out").mkdir(), ()),
    # --- export ------------------------------------------------------------------------------------------
    Case("export-no-meshes", [*EXP, "--usd", f"{C}/o.usdc"], 2, "no meshes.npz", lambda w, c: (c / "rec").mkdir(),
         ("o.usdc",)),
    Case("export-meshes-no-frames", [*EXP, "--usd", f"{C}/o.usdc"], 2, "missing arrays",
         chain(REC_COPY, npz_edit("rec/meshes.npz", drop_key("frames"))), ("o.usdc",)),
    Case("export-meshes-wrong-vertices", [*EXP, "--usd", f"{C}/o.usdc"], 2, "do not fit",
         chain(REC_COPY, npz_edit("rec/meshes.npz", lambda a: {**a, "vertices": a["vertices"][:, :10]})), ("o.usdc",)),
    Case("export-meshes-nan", [*EXP, "--usd", f"{C}/o.usdc"], 2, "non-finite",
         chain(REC_COPY, npz_edit("rec/meshes.npz", lambda a: {**a, "vertices": a["vertices"] * np.nan})),
         ("o.usdc",)),
    Case("export-meshes-truncated", [*EXP, "--usd", f"{C}/o.usdc"], 2, "meshes.npz",
         chain(REC_COPY, truncate("rec/meshes.npz", 500)), ("o.usdc",)),
    *[Case(f"export-{what}-zero-frames", [*EXP, f"--{what}", f"{C}/{name}"], 2, "meshes.npz: holds no frames",
           chain(REC_COPY, npz_edit("rec/meshes.npz", lambda a: {k: v[:0] for k, v in a.items()})), (name,))
      for what, name in (("usd", "o.usdc"), ("exr", "x"))],
    Case("review-zero-frames", ["review", f"{C}/rec", "--index", f"{W}/idx", "--out", f"{C}/out"], 2,
         "meshes.npz: holds no frames",
         chain(REC_COPY, npz_edit("rec/meshes.npz", lambda a: {k: v[:0] for k, v in a.items()}))),
    Case("review-diagnostics-header-only", ["review", f"{C}/rec", "--index", f"{W}/idx", "--out", f"{C}/out"], 2,
         "diagnostics.csv: holds no rows", chain(REC_COPY, lambda w, c: (c / "rec" / "diagnostics.csv").write_text(
             (w / "rec" / "diagnostics.csv").read_text().splitlines()[0] + "\n"))),
    *[Case(f"{cmd[0]}-{flag[2:]}-empty", [*cmd, flag, ""], 2, "the output path is empty", REC_COPY, ())
      for cmd, flag in ((REC[:4], "--out"), (["review", f"{C}/rec", "--index", f"{W}/idx"], "--out"),
                        (EXP, "--exr"), (EXP, "--usd"))],
    Case("export-nothing-asked", EXP, 2, "nothing to export", REC_COPY),
    Case("export-exr-size-0", [*EXP, "--exr", f"{C}/x", "--exr-size", "0"], 2, "--exr-size", REC_COPY, ("x",)),
    Case("export-fps-0", [*EXP, "--usd", f"{C}/o.usdc", "--fps", "0"], 2, "--fps", REC_COPY, ("o.usdc",)),
    Case("export-usd-extension", [*EXP, "--usd", f"{C}/o.txt"], 2, "--usd", REC_COPY, ("o.txt",)),
    Case("export-usd-is-dir", [*EXP, "--usd", f"{C}/o.usdc"], 2, "a directory of that name exists",
         chain(REC_COPY, lambda w, c: (c / "o.usdc").mkdir()), ()),
    Case("export-exr-is-file", [*EXP, "--exr", f"{C}/x"], 2, "a file of that name exists",
         chain(REC_COPY, write("x", "y")), ()),
    Case("export-index-missing", ["export", f"{C}/rec", "--index", f"{C}/nope", "--usd", f"{C}/o.usdc"], 2,
         "not an LGI index", REC_COPY, ("o.usdc",)),
    # --- calibrate ---------------------------------------------------------------------------------------
    Case("calibrate-images-missing", [*CAL, "--board", "chessboard:9x6:25"], 2, "imgs"),
    Case("calibrate-images-empty", [*CAL, "--board", "chessboard:9x6:25"], 2, "imgs",
         lambda w, c: (c / "imgs").mkdir()),
    *[Case(f"calibrate-board-{name}", [*CAL, "--board", spec], 2, "board") for name, spec in (
        ("kind", "dartboard:9x6:25"), ("size", "chessboard:9by6:25"), ("square", "chessboard:9x6:-1"),
        ("charuco-dict", "charuco:7x5:15:11:DICT_NOPE"))],
    Case("calibrate-two-models", [*CAL, "--board", "chessboard:9x6:25", "--rational", "--fisheye"], 2, "choose one"),
    Case("calibrate-out-is-dir", [*CAL, "--board", "chessboard:9x6:25"], 2, "a directory of that name exists",
         lambda w, c: (c / "out").mkdir(), ()),
    # --- track ---------------------------------------------------------------------------------------------
    Case("track-footage-missing", TRK, 2, "foot", write("calib.json", "{}")),
    Case("track-calib-missing", TRK, 2, "calib.json", lambda w, c: (c / "foot").mkdir()),
    Case("track-calib-not-json", TRK, 2, "calib.json", chain(write("calib.json", "{oops"),
                                                             lambda w, c: (c / "foot").mkdir())),
    *[Case(f"track-calib-{name}", TRK, 2, says, chain(calib_json(edit), lambda w, c: (c / "foot").mkdir()))
      for name, edit, says in (
          ("no-cameras", lambda d: {k: v for k, v in d.items() if k != "cameras"}, "not a stereo calibration"),
          ("K-nan", lambda d: _cam(d, 0, "K", [[float("nan"), 0, 320], [0, 500, 240], [0, 0, 1]]), "intrinsic matrix"),
          ("K-negative", lambda d: _cam(d, 1, "K", [[-500, 0, 320], [0, 500, 240], [0, 0, 1]]), "intrinsic matrix"),
          ("R-not-rotation", lambda d: {**d, "R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}, "rotation"),
          ("dist-nan", lambda d: _cam(d, 0, "dist", [float("nan"), 0, 0, 0, 0]), "distortion"),
          ("T-inf", lambda d: {**d, "T": [float("inf"), 0, 0]}, "translation"),
          ("size-negative", lambda d: {**d, "image_size": [-640, 480]}, "image size"),
          ("three-cameras", lambda d: {**d, "cameras": d["cameras"] * 2}, "not a stereo calibration"))],
    *[Case(f"track-{flag.strip('-')}-{val}", [*TRK, flag, val], 2, flag) for flag, val in (
        ("--gate", "0"), ("--dot-size", "-1"), ("--reference-frame", "-1"), ("--units", "furlong"))],
    # --- synth, bundles, bench, demo ---------------------------------------------------------------------
    *[Case(f"synth-{flag.strip('-')}-{val}", ["synth", "--out", f"{C}/out", "-q", flag, val], 2, flag)
      for flag, val in (("--vertices", "0"), ("--frames", "-1"), ("--board-views", "1"), ("--image-size", "10x10"),
                        ("--dot-noise", "-1"), ("--lens", "fish"))],
    Case("synth-out-is-file", ["synth", "--out", f"{C}/out", "-q"], 2, "a file of that name exists",
         write("out", "x"), ()),
    Case("bundles-cmd-dataset-missing", ["bundles", f"{C}/nope", "--markers", f"{S}/markers.csv", "--out",
                                         f"{C}/out.csv"], 2, "nope", None, ("out.csv",)),
    Case("bundles-cmd-shapes-nothing", ["bundles", f"{S}/dataset", "--markers", f"{S}/markers.csv", "--out",
                                        f"{C}/out.csv", "--shapes", "zzz"], 2, "zzz", None, ("out.csv",)),
    Case("bundles-cmd-out-is-dir", ["bundles", f"{S}/dataset", "--markers", f"{S}/markers.csv", "--out",
                                    f"{C}/out.csv"], 2, "a directory of that name exists",
         lambda w, c: (c / "out.csv").mkdir(), ()),
    Case("bench-noise-negative", ["bench", "--out", f"{C}/out", "--noise", "-1", "--no-ict"], 2, "--noise"),
    Case("bench-out-is-file", ["bench", "--out", f"{C}/out", "--no-ict"], 2, "a file of that name exists",
         write("out", "x"), ()),
    Case("demo-out-is-file", ["demo", "--out", f"{C}/out", "-q"], 2, "a file of that name exists",
         write("out", "x"), ()),
    Case("demo-vertices-0", ["demo", "--out", f"{C}/out", "--vertices", "0"], 2, "--vertices"),
    # --- outputs that would destroy inputs or someone else's files (campaign 2) ----------------------------
    Case("import-out-is-the-input", [*IMP[:3], f"{C}/objs", *IMP[4:]], 2, "would replace this run's input", OBJS,
         ()),
    Case("import-out-holds-the-input", [*IMP[:3], f"{C}", *IMP[4:]], 2, "would replace this run's input", OBJS, ()),
    Case("import-out-foreign-folder", [*IMP[:3], f"{C}/mine", *IMP[4:]], 2, "thesis.tex",
         chain(OBJS, write("mine/thesis.tex", "precious")), ()),
    Case("build-out-foreign-folder", [*BUILD[:5], f"{C}/mine", "-q"], 2, "not an lgi index's",
         write("mine/thesis.tex", "precious"), ()),
    Case("build-out-is-the-dataset", [*BUILDD[:5], f"{C}/ds", "-q"], 2, "would replace this run's input",
         copy("s/dataset", "ds"), ()),
    Case("augment-out-foreign-folder", [*AUG[:3], f"{C}/mine", "-q", "--linear", "--budget", "2"], 2,
         "not an lgi dataset's", write("mine/thesis.tex", "precious"), ()),
    Case("export-exr-is-the-reconstruction", [*EXP, "--exr", f"{C}/rec", "--exr-size", "16"], 2,
         "would replace this run's input", REC_COPY, ()),
    Case("export-exr-foreign-folder", [*EXP, "--exr", f"{C}/x", "--exr-size", "16"], 2, "notes.txt",
         chain(REC_COPY, write("x/notes.txt", "precious")), ()),
    Case("export-usd-equals-exr", [*EXP, "--exr", f"{C}/o.usdc", "--usd", f"{C}/o.usdc"], 2, "same path", REC_COPY,
         ("o.usdc",)),
    Case("bundles-out-is-the-markers", ["bundles", f"{S}/dataset", "--markers", f"{C}/m.csv", "--out", f"{C}/m.csv"],
         2, "would replace this run's input", markers_cell(0, "name", "forehead_L_01"), ()),
    Case("rig-out-inside-the-dataset", ["rig", f"{C}/ds", "--shapes", "jaw_*", "--jaw-vertices", "0:200", "--out",
                                        f"{C}/ds/mesh.npz"], 2, "would replace this run's input",
         copy("s/dataset", "ds"),
         ()),
    Case("calibrate-out-equals-yaml", [*CAL, "--board", "chessboard:9x6:25", "--yaml", f"{C}/out"], 2, "same path",
         lambda w, c: (c / "imgs").mkdir()),
    Case("track-out-equals-tracks", [*TRK, "--tracks", f"{C}/out"], 2, "same path",
         chain(calib_json(lambda d: d), lambda w, c: (c / "foot").mkdir())),
    # --- corrupt stored arrays the compiled kernels would read out of bounds (a crash before) --------------
    *[Case(f"index-{name}", RECI, 2, says, chain(IDX, npz_edit("idx/index.npz", edit))) for name, edit, says in (
        ("sx-out-of-range", lambda a: {**a, "sx": a["sx"] + 10**6}, "sx row"),
        ("sx-other-marker", lambda a: {**a, "sx": np.where(a["sx"] >= 0, (a["sx"] + 7) % len(a["pts"]), -1)},
         "sx row"),
        ("cell-items-out-of-range", lambda a: {**a, "cell_items": a["cell_items"] + 10**6}, "cell_items"),
        ("hull-out-of-range", lambda a: {**a, "hull": a["hull"] + 10**6}, "hull"),
        ("pt-off-reversed", lambda a: {**a, "pt_off": a["pt_off"][::-1].copy()}, "pt_off"),
        ("ptab-strings", lambda a: {**a, "ptab": a["ptab"].astype(str)}, "ptab holds"),
        ("face-vertices-out-of-range", lambda a: {**a, "face_vertices": a["face_vertices"] + 10**6}, "face_vertices"),
        ("alias-shape-out-of-range", lambda a: {**a, "alias_shape": a["alias_shape"] + 10**6}, "alias_shape"),
        ("w-indices-out-of-range", lambda a: {**a, "w_indices": a["w_indices"] + 10**6}, "w_indices"),
        ("grid-dims-wrong", lambda a: {**a, "grid_dims": a["grid_dims"] + 1}, "grid_dims"))],
    Case("export-index-faces-out-of-range", [*EXP[:3], f"{C}/idx", "-q", "--usd", f"{C}/o.usdc"], 2, "face_vertices",
         chain(REC_COPY, IDX, npz_edit("idx/index.npz", lambda a: {**a, "face_vertices": a["face_vertices"] + 10**6})),
         ("o.usdc",)),
    *[Case(f"dataset-{name}", BUILDD, 2, says, chain(copy("s/dataset", "ds"), npz_edit("ds/mesh.npz", edit)))
      for name, edit, says in (
          ("face-uvs-out-of-range", lambda a: {**a, "face_uvs": a["face_uvs"] + 10**6}, "mesh.npz: face_uvs"),
          ("face-vertices-out-of-range", lambda a: {**a, "face_vertices": a["face_vertices"] + 10**6},
           "mesh.npz: face_vertices"),
          ("face-offsets-broken", lambda a: {**a, "face_offsets": a["face_offsets"][::-1].copy()}, "face_offsets"),
          ("neutral-wrong-shape", lambda a: {**a, "neutral": a["neutral"][:-5]}, "neutral has shape"))],
    # --- option values far out of range (a memory error or the OOM killer before) -------------------------
    Case("synth-vertices-huge", ["synth", "--out", f"{C}/out", "-q", "--vertices", "2000000000"], 2, "--vertices"),
    Case("synth-too-much-memory", ["synth", "--out", f"{C}/out", "-q", "--vertices", "1000000", "--frames",
                                   "1000000"], 2, "GiB of memory"),
    Case("synth-image-size-huge", ["synth", "--out", f"{C}/out", "-q", "--hmc", "--image-size", "100000x100000"], 2,
         "--image-size"),
    Case("demo-vertices-huge", ["demo", "--out", f"{C}/out", "--vertices", "100000000000"], 2, "--vertices"),
    Case("demo-frames-0", ["demo", "--out", f"{C}/out", "--frames", "0"], 2, "lgi demo: error: --frames"),
    Case("bench-frames-0", ["bench", "--out", f"{C}/out", "--frames", "0", "--no-ict"], 2,
         "lgi bench: error: --frames"),
    Case("bench-ict-not-a-folder", ["bench", "--out", f"{C}/out", "--frames", "2", "--ict", f"{C}/ict"], 2,
         "not an ICT FaceKit folder", write("ict", "x")),
    Case("reconstruct-smooth-huge", [*REC, "--smooth", "100000001"], 2, "--smooth"),
    Case("augment-iterations-huge", [*AUG, "--simulate", "--iterations", "1000000000"], 2, "--iterations"),
    Case("augment-requires-unknown-shape", [*AUG, "--linear", "--requires", "nobody=jaw_open", "--budget", "2"], 2,
         "nobody"),
    # --- typed tables and jaw files ----------------------------------------------------------------------------
    Case("bundles-parquet-bool-x", [*RECB[:3], f"{C}/b.parquet", *RECB[4:]], 2, "true/false",
         lambda w, c: pd.read_csv(w / "s" / "bundles.csv").assign(x=lambda d: d.x > 0).to_parquet(c / "b.parquet")),
    Case("bundles-parquet-null-marker", [*RECB[:3], f"{C}/b.parquet", *RECB[4:]], 2, "(row 7)",
         lambda w, c: null_marker(w / "s" / "bundles.csv", 7).to_parquet(c / "b.parquet")),
    *[Case(f"reconstruct-jaw-file-{name}", ["reconstruct", f"{W}/idxr", "--bundles", f"{S}/bundles.csv", "--out",
                                            f"{C}/out", "-q", "--jaw", f"{C}/j.csv"], 2, says,
           write("j.csv", "frame,open_deg,yaw_deg,roll_deg,forward_cm\n" +
                 "".join(f"{f},{v},0,0,0\n" for f in range(12))))
      for name, v, says in (("720-degrees", "720", "outside a jaw's range"), ("text", "wide", "j.csv:2"))],
    Case("reconstruct-jaw-file-fractional-frame", ["reconstruct", f"{W}/idxr", "--bundles", f"{S}/bundles.csv",
                                                   "--out", f"{C}/out", "-q", "--jaw", f"{C}/j.csv"], 2,
         "not a whole number", write("j.csv", "frame,open_deg,yaw_deg,roll_deg,forward_cm\n0.5,1,0,0,0\n")),
    # --- campaign 3 ----------------------------------------------------------------------------------------
    Case("reconstruct-obj-folder-holds-a-user-file", [*REC, "--obj"], 2, "notes.txt",
         write("out/obj/notes.txt", "mine"), ()),
    Case("import-flow-marker-triangle-out-of-range", [*IMP, "--flow", "--markers", f"{C}/m.csv"], 2,
         "triangle 999999", chain(OBJS, markers_cell(0, "triangle", "999999"))),
    Case("bundles-parquet-list-in-y", [*RECB[:3], f"{C}/b.parquet", *RECB[4:]], 2, "(row 0), frame 0, marker",
         lambda w, c: pd.read_csv(w / "s" / "bundles.csv").assign(y=lambda d: [[v, v] for v in d.y]).to_parquet(
             c / "b.parquet")),
    Case("unknown-command", ["fly"], 2, "fly"),
    # --- inputs are never outputs ----------------------------------------------------------------------------
    *[Case(f"reconstruct-{mode}-scan-{where}", [*REC, *flow, *extra, "--scans", f"{C}/pairs.csv"], 2,
           "would replace this run's input", chain(copy("objs/neutral.obj", f"out/obj/{scan}"),
                                                  write("pairs.csv", f"frame,scan\n5,out/obj/{scan}\n")), ())
      for mode, flow in (("plain", []), ("flow", ["--flow"]))
      for where, scan, extra in (("where-obj-writes-it", "frame_00005.obj", ["--obj"]),
                                 ("in-obj-folder", "frame_00005.obj", []))],
    Case("reconstruct-obj-folder-is-a-link", [*REC, "--obj"], 2, "out/obj: is a symbolic link",
         chain(copy("rec", "other"), write("other/obj/frame_00000.obj", "v 0 0 0\n"),
               lambda w, c: (c / "out").mkdir() or (c / "out" / "obj").symlink_to(c / "other" / "obj")),
         ("out/meshes.npz",)),
    Case("reconstruct-out-not-utf8", [*REC[:5], f"{C}/o\udcff", "-q"], 2, "not UTF-8 text", absent=()),
    # --- outputs inside a folder lgi rebuilds as a whole --------------------------------------------------------
    Case("reconstruct-out-inside-an-index", [*RECI[:5], f"{C}/idx/out", "-q"], 2, "inside an LGI index",
         copy("idx"), ("idx/out",)),
    Case("review-out-inside-an-index", ["review", f"{C}/rec", "--index", f"{C}/idx", "--out", f"{C}/idx/rv"], 2,
         "inside an LGI index", chain(copy("idx"), REC_COPY), ("idx/rv",)),
    Case("compare-out-inside-a-dataset", ["compare", f"{C}/rec", "--index", f"{W}/idx", "--frame", "5", "--scan",
                                          f"{C}/scan.obj", "--out", f"{C}/ds/cmp"], 2, "inside a shape dataset",
         chain(copy("s/dataset", "ds"), REC_COPY, copy("objs/neutral.obj", "scan.obj")), ("ds/cmp",)),
    *[Case(f"export-{flag[2:]}-inside-an-index", [*EXP, flag, f"{C}/idx/{name}"], 2, f"{flag} is inside an LGI index",
           chain(copy("idx"), REC_COPY), (f"idx/{name}",)) for flag, name in (("--usd", "o.usdc"), ("--exr", "x"))],
    *[Case(f"reconstruct-{mode}-pairs-is-per-frame", [*REC, *flow, "--scans", f"{C}/out/per_frame.csv"], 2,
           "would replace this run's input",
           chain(copy("objs/neutral.obj", "scan.obj"), write("out/per_frame.csv", "frame,scan\n5,../scan.obj\n")),
           ()) for mode, flow in (("plain", []), ("flow", ["--flow"]))],
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(case: Case, world: Path, tmp_path: Path, capsys) -> None:
    c = tmp_path
    if case.setup is not None:
        case.setup(world, c)
    before = {p: p.read_bytes() for p in c.rglob("*") if p.is_file()}
    argv = [a.replace("{w}", str(world)).replace("{c}", str(c)) for a in case.argv]
    code, out, err = run(argv, capsys)
    assert code == case.code, (code, err)
    assert "Traceback" not in err + out
    said = err if case.code != 1 else out + err  # a failed check is a report (stdout), not an error
    assert case.says.lower() in said.lower(), said[-2000:]
    for rel in case.absent:
        assert not (c / rel).exists(), f"{rel} left behind"
    for p, data in before.items():  # a failed run changes nothing that was there
        assert p.read_bytes() == data, p
    assert not [p for p in c.rglob("*") if ".tmp-" in p.name or ".lgi-staging-" in p.name or ".old-" in p.name]


# ------------------------------------------------------------------- camera footage and calibration images
@pytest.fixture(scope="module")
def hmc(world: Path) -> Path:
    """The small actor's head-mounted camera footage (4 frames) and 6 board views, 640x480."""
    h = world / "h"
    assert main(["synth", "--out", str(h), "--vertices", "1500", "--frames", "4", "--hmc", "--image-size", "640x480",
                 "--board-views", "6", "-q"]) == 0
    return h


def footage_copy(w: Path, c: Path) -> None:
    shutil.copytree(w / "h" / "hmc", c / "foot", ignore=shutil.ignore_patterns("calib"))


def images_copy(w: Path, c: Path) -> None:
    shutil.copytree(w / "h" / "hmc" / "calib", c / "imgs")


def same_view_six_times(w: Path, c: Path) -> None:
    (c / "imgs").mkdir()
    for i in range(1, 7):
        for side in ("left", "right"):
            shutil.copy(w / "h" / "hmc" / "calib" / f"{side}02.png", c / "imgs" / f"{side}0{i}.png")


def shrink_image(rel: str):
    def f(w: Path, c: Path) -> None:
        import cv2

        img = cv2.imread(str(c / rel), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(c / rel), cv2.resize(img, (320, 240)))
    return f


H = f"{W}/h"
TRKH = ["track", f"{C}/foot", "--calib", f"{H}/hmc/cameras_true.json", "--markers", f"{H}/markers.csv", "--out",
        f"{C}/out.csv"]
CALH = ["calibrate", f"{C}/imgs", "--board", "chessboard:9x6:12", "--fisheye", "--out", f"{C}/out.json"]
HMC_CASES = [
    Case("calibrate-same-view-six-times", CALH, 2, "a copy adds nothing", same_view_six_times, ("out.json",)),
    Case("calibrate-left-image-smaller", CALH, 2, "left02.png: image is 320x240",
         chain(images_copy, shrink_image("imgs/left02.png")), ("out.json",)),
    Case("calibrate-out-on-an-image", [*CALH[:-1], f"{C}/imgs/left01.png"], 2, "would replace this run's input",
         images_copy, ()),
    Case("track-tracks-on-a-frame", [*TRKH, "--tracks", f"{C}/foot/cam0/000001.png"], 2,
         "would replace this run's input", footage_copy, ("out.csv",)),
    Case("track-image-undecodable", TRKH, 2, "000002.png", chain(footage_copy, write("foot/cam1/000002.png", "junk")),
         ("out.csv",)),
    Case("track-image-empty", TRKH, 2, "unreadable image", chain(footage_copy, write("foot/cam0/000001.png", b"")),
         ("out.csv",)),
    Case("track-image-smaller", TRKH, 2, "image is 320x240", chain(footage_copy, shrink_image("foot/cam0/000003.png")),
         ("out.csv",)),
    *[Case(f"track-labels-{name}", [*TRKH, "--labels", f"{C}/l.csv"], 2, says,
           chain(footage_copy, write("l.csv", text)), ("out.csv",)) for name, text, says in (
        ("empty", "", "l.csv: label file is empty"),
        ("header-only", "camera,x,y,marker\n", "no rows"),
        ("text-in-y", "camera,x,y,marker\n0,100,left,forehead_L_01\n", "l.csv:2, marker 'forehead_L_01'"),
        ("nan-x", "camera,x,y,marker\n0,nan,3,forehead_L_01\n", "non-finite x"),
        ("camera-2", "camera,x,y,marker\n2,100,3,forehead_L_01\n", "camera must be 0 or 1"))],
    *[Case(f"track-helmet-{name}", [*TRKH, "--helmet", f"{C}/hm.csv"], 2, says,
           chain(footage_copy, write("hm.csv", text)), ("out.csv",)) for name, text, says in (
        ("empty", "", "helmet marker file is empty"),
        ("text", "name,x,y,z\nh1,far,0,0\nh2,1,0,0\nh3,0,1,0\nh4,0,0,1\n", "hm.csv:2, marker 'h1'"),
        ("three", "name,x,y,z\nh1,0,0,0\nh2,1,0,0\nh3,0,1,0\n", "at least 4"))],
    Case("track-markers-text-in-x", [*TRKH[:5], f"{C}/m.csv", *TRKH[6:]], 2, "m.csv:5",
         chain(footage_copy, lambda w, c: pd.read_csv(w / "h" / "markers.csv", dtype=str).assign(
             x=lambda d: d.x.where(d.index != 3, "left")).to_csv(c / "m.csv", index=False)), ("out.csv",)),
]


@pytest.mark.parametrize("case", HMC_CASES, ids=[c.id for c in HMC_CASES])
def test_bad_capture_input(case: Case, hmc: Path, world: Path, tmp_path: Path, capsys) -> None:
    test_bad_input(case, world, tmp_path, capsys)


def test_a_row_of_two_million_fields_is_refused_in_bounded_memory(world: Path, tmp_path: Path) -> None:
    lines = (world / "s" / "bundles.csv").read_text().splitlines()
    lines[1] += ",9" * 2_000_000  # a 4 MB line
    bad = tmp_path / "b.csv"
    bad.write_text("\n".join(lines) + "\n")
    (tmp_path / "run").mkdir()
    code, peak_mib, err = peak_memory_run([sys.executable, "-m", "lgi", "reconstruct", str(world / "idx"), "--bundles",
                                           str(bad), "--out", str(tmp_path / "out"), "-q"], tmp_path / "run")
    assert code == 2 and f"{bad}:2: 2,000,005 fields where the header has 5" in err, err[-500:]
    assert len(err) < 1000 and "Traceback" not in err  # the line quoted, not echoed
    assert peak_mib < 500, peak_mib
    assert not (tmp_path / "out").exists()


def test_a_huge_cell_is_quoted_not_echoed(world: Path, tmp_path: Path, capsys) -> None:
    d = pd.read_csv(world / "s" / "bundles.csv", dtype=str)
    d.loc[3, "x"] = "7" * 1_000_000 + "x"
    bad = tmp_path / "b.csv"
    d.to_csv(bad, index=False)
    code, out, err = run(["reconstruct", str(world / "idx"), "--bundles", str(bad), "--out", str(tmp_path / "o"), "-q"],
                         capsys)
    assert code == 2 and f"{bad}:5" in err and "more characters" in err and len(err) < 1000, err[:2000]


def test_csv_with_a_byte_order_mark_is_read(world: Path, tmp_path: Path, capsys) -> None:
    """Excel's "CSV UTF-8" starts the file with a byte-order mark: bundles and marker files read as without."""
    for name in ("bundles.csv", "markers.csv"):
        (tmp_path / name).write_bytes(b"\xef\xbb\xbf" + (world / "s" / name).read_bytes())
    assert run(["build", str(world / "s" / "dataset"), "--markers", str(tmp_path / "markers.csv"), "--out",
                str(tmp_path / "idx"), "-q"], capsys)[0] == 0
    code, _, err = run(["reconstruct", str(tmp_path / "idx"), "--bundles", str(tmp_path / "bundles.csv"), "--out",
                        str(tmp_path / "rec"), "-q"], capsys)
    assert code == 0, err
    ref = np.load(world / "rec" / "meshes.npz")["vertices"]
    assert np.array_equal(np.load(tmp_path / "rec" / "meshes.npz")["vertices"], ref)


# ----------------------------------------------------------------------------------------------- re-runs
def test_rerun_leaves_exactly_what_it_wrote(world: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    base = ["reconstruct", str(world / "idx"), "--bundles", str(world / "s" / "bundles.csv"), "--out", str(out), "-q"]
    assert run([*base, "--obj", "--usd", "--plot"], capsys)[0] == 0
    assert (out / "obj").is_dir() and (out / "shot.usdc").is_file()
    # A killed run's leftovers (a process that no longer exists) and a live run's staging folder.
    dead = 2**22 + 12345
    (out / f".lgi-staging-{dead}-abc").mkdir()
    (out / f".obj.old-{dead}-x").mkdir()
    alive = out / f".lgi-staging-{os.getpid()}-live"
    alive.mkdir()
    assert run(base, capsys)[0] == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(["meshes.npz", "diagnostics.csv", "per_frame.csv", "run.json", RECORD_FILE, alive.name]), \
        names
    # The record lists exactly what the run left (the earlier --obj and --usd files are gone from it too).
    assert sorted(read_record(out)[0]) == ["diagnostics.csv", "meshes.npz", "per_frame.csv", "run.json"]
    alive.rmdir()
    # A failed re-run leaves the earlier outputs untouched.
    snap = {p.name: p.read_bytes() for p in out.iterdir()}
    code, _, err = run([*base[:3], str(tmp_path / "missing.csv"), *base[4:]], capsys)
    assert code == 2 and "missing.csv" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == snap


def test_synth_rerun_drops_the_earlier_hmc(tmp_path: Path, capsys) -> None:
    out = tmp_path / "s"
    argv = ["synth", "--out", str(out), "--vertices", "800", "--frames", "2", "-q"]
    assert run([*argv, "--hmc", "--image-size", "160x120", "--board-views", "3"], capsys)[0] == 0
    assert (out / "hmc").is_dir()
    (out / "mine.txt").write_text("keep")
    assert run(argv, capsys)[0] == 0
    assert not (out / "hmc").exists() and (out / "mine.txt").read_text() == "keep"


def test_files_lgi_did_not_write_are_never_replaced(world: Path, tmp_path: Path, capsys) -> None:
    """Judged by lgi's record of what it wrote, not by the names: a user's file named like an output, or an output
    the user changed, stays; a refusal comes before the work and names the file."""
    # A folder holding only the user's own index.html is not a review page to replace.
    page = tmp_path / "page"
    page.mkdir()
    (page / "index.html").write_text("<p>my notes</p>")
    code, _, err = run(["review", str(world / "rec"), "--index", str(world / "idx"), "--out", str(page)], capsys)
    assert code == 2 and "index.html" in err and "no record" in err, err
    assert (page / "index.html").read_text() == "<p>my notes</p>"
    # A reconstruction whose review/ and compare/ hold only the user's files: kept, with a warning, when the run
    # writes no page and compares no scans.
    out = tmp_path / "rec"
    base = ["reconstruct", str(world / "idx"), "--bundles", str(world / "s" / "bundles.csv"), "--out", str(out), "-q"]
    for sub, name in (("review", "index.html"), ("compare", "summary.csv")):
        (out / sub).mkdir(parents=True)
        (out / sub / name).write_text("mine")
    code, _, err = run([*base[:-1]], capsys)
    assert code == 0, err
    assert (out / "review" / "index.html").read_text() == "mine" == (out / "compare" / "summary.csv").read_text()
    assert "no record" in err and str(out / "review") in err and str(out / "compare") in err, err
    # ... and a run that would write the page is refused before the work.
    code, _, err = run([*base, "--review"], capsys)
    assert code == 2 and "index.html" in err and "no record" in err, err
    shutil.rmtree(out / "review")
    shutil.rmtree(out / "compare")
    # An output the user edited is theirs now: a re-run refuses to replace it, and replaces nothing.
    before = (out / "per_frame.csv").read_bytes()
    (out / "per_frame.csv").write_bytes(before + b"# checked by hand\n")
    meshes = (out / "meshes.npz").stat().st_mtime_ns
    code, _, err = run(base, capsys)
    assert code == 2 and "per_frame.csv" in err, err
    assert (out / "meshes.npz").stat().st_mtime_ns == meshes
    # The same bytes written back (a copy: another modification time) are lgi's again, by their hash.
    (out / "per_frame.csv").write_bytes(before)
    assert run(base, capsys)[0] == 0
    # A file in an output folder lgi replaces whole (obj/) that the user dropped there.
    assert run([*base, "--obj"], capsys)[0] == 0
    frame = sorted((out / "obj").glob("*.obj"))[0]
    frame.write_text("v 0 0 0\n")
    code, _, err = run([*base, "--obj"], capsys)
    assert code == 2 and frame.name in err, err


def test_import_over_a_dataset_and_a_dead_temporary(world: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "ds"
    argv = ["import", str(world / "objs"), "--out", str(out), "-q", "--rigid-vertices", "none"]
    assert run(argv, capsys)[0] == 0
    first = (out / "manifest.json").read_bytes()
    (tmp_path / f".ds.tmp-{2**22 + 777}-zz").mkdir()
    assert run(argv, capsys)[0] == 0
    assert (out / "manifest.json").read_bytes() == first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


# ---------------------------------------------------------------------------------------------- interrupts
# Each interrupt waits for the stage it means to interrupt: the command marks each stage it enters with a file in
# LGI_DEBUG_STAGES (lgi/_debug_stages.py), so a loaded machine cannot make the signal land elsewhere, and an exit status
# of 0 (a signal lost, or handled as if nothing happened) fails the test.
STATUS = {signal.SIGINT: 130, signal.SIGTERM: 143}
SAYS = {signal.SIGINT: "interrupted", signal.SIGTERM: "SIGTERM"}


def _spawn(argv: list[str], cwd: Path, stages: Path | None = None, hold: str | None = None,
           env: dict[str, str] | None = None, session: bool = False) -> subprocess.Popen:
    env = {**(env or os.environ), "PYTHONUNBUFFERED": "1"}
    if stages is not None:
        env["LGI_DEBUG_STAGES"] = str(stages)
    if hold is not None:
        env["LGI_DEBUG_HOLD"] = hold
    # session: the command and what it starts (a local Prefect server) in a process group of their own, which a
    # failed test can end whole.
    return subprocess.Popen([sys.executable, "-m", "lgi", *argv], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=session)


def _kill(p: subprocess.Popen) -> None:
    """SIGKILL the command, with its process group when it has one of its own (what it started goes too)."""
    try:
        if os.getpgid(p.pid) == p.pid:
            os.killpg(p.pid, signal.SIGKILL)
            return
    except ProcessLookupError:
        return
    p.kill()


def _wait_for(p: subprocess.Popen, ready: Callable[[], bool], what: str, timeout: float = 300) -> None:
    """Until ``ready()``; the test fails if the command ends or the time runs out first."""
    deadline = time.monotonic() + timeout
    while not ready():
        if p.poll() is not None:
            out, err = p.communicate()
            pytest.fail(f"the command ended (status {p.returncode}) before {what}: {out[-500:]} {err[-2000:]}")
        if time.monotonic() > deadline:
            _kill(p)
            p.communicate()
            pytest.fail(f"{what} did not come within {timeout} s")
        time.sleep(0.005)


def _finish(p: subprocess.Popen, timeout: float = 120) -> tuple[str, str]:
    try:
        return p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        _kill(p)
        p.communicate()
        pytest.fail(f"the command did not end within {timeout} s of the signal")


@pytest.fixture(scope="module")
def long_shot(world: Path, tmp_path_factory) -> Path:
    """A 400-frame performance on the small actor (a solve of a few seconds), for interrupting a reconstruction."""
    t = tmp_path_factory.mktemp("long")
    assert main(["synth", "--out", str(t / "s"), "--vertices", "1500", "--frames", "400", "-q"]) == 0
    return t / "s" / "bundles.csv"


@pytest.mark.parametrize(("sig", "stage", "hold"), [
    (signal.SIGINT, "start", None),  # while the command line's modules are imported
    (signal.SIGINT, "solve", None),  # inside the compiled kernels
    (signal.SIGTERM, "solve", None),  # a scheduler cancelling the job
    (signal.SIGINT, "write", "write:60"),  # held with the outputs half staged: the signal ends the hold
    (signal.SIGTERM, "write", "write:60"),
], ids=["sigint-start", "sigint-solve", "sigterm-solve", "sigint-write", "sigterm-write"])
def test_signal_at_a_stage_leaves_nothing(world: Path, long_shot: Path, tmp_path: Path, sig: int, stage: str,
                                          hold: str | None) -> None:
    """A signal during the work: status 130 (SIGINT) or 143 (SIGTERM), one line and no traceback, nothing
    written into OUT and no temporaries left beside it."""
    out, stages = tmp_path / "out", tmp_path / "stages"
    p = _spawn(["reconstruct", str(world / "idx"), "--bundles", str(long_shot), "--out", str(out), "-q"], tmp_path,
               stages, hold)
    _wait_for(p, (stages / stage).exists, f"stage {stage!r}")
    p.send_signal(sig)
    _, err = _finish(p)
    assert p.returncode == STATUS[sig], (p.returncode, err[-2000:])
    assert "Traceback" not in err and SAYS[sig] in err, err[-2000:]
    if stage in ("start", "solve"):  # the signal landed before the outputs were begun
        assert not (stages / "write").exists()
    assert not out.exists() or not list(out.iterdir())
    assert not [q for q in tmp_path.iterdir() if q.name.startswith(".out")]


def _assert_complete(world: Path, out: Path) -> None:
    """OUT holds a whole reconstruction of the 12-frame shot: its four files, every frame and bundle, and meshes
    through every bundle (measured on the meshes, so a run cut short while writing cannot pass)."""
    assert sorted(q.name for q in out.iterdir()) == [RECORD_FILE, "diagnostics.csv", "meshes.npz", "per_frame.csv",
                                                     "run.json"]
    assert np.load(out / "meshes.npz")["frames"].tolist() == list(range(12))
    assert len(pd.read_csv(out / "per_frame.csv")) == 12
    bundles = pd.read_csv(world / "s" / "bundles.csv")
    assert len(pd.read_csv(out / "diagnostics.csv")) == len(bundles)
    assert bundle_gaps_mm(out / "meshes.npz", world / "s" / "markers.csv", bundles).max() < THROUGH_MM


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["sigint", "sigterm"])
def test_signal_during_shutdown_keeps_the_outputs(world: Path, tmp_path: Path, sig: int) -> None:
    """A signal after the command has returned its status, held at the interpreter's shutdown: the outputs are
    complete, and the status says the run was interrupted (130/143), never death by the signal (-2/-15)."""
    out, stages = tmp_path / "out", tmp_path / "stages"
    p = _spawn(["reconstruct", str(world / "idx"), "--bundles", str(world / "s" / "bundles.csv"), "--out", str(out),
                "-q"], tmp_path, stages, "shutdown:60")
    _wait_for(p, (stages / "shutdown").exists, "the shutdown")
    p.send_signal(sig)
    _, err = _finish(p)
    assert p.returncode == STATUS[sig], (p.returncode, err[-2000:])
    assert "Traceback" not in err and "after the outputs of this run were written" in err, err[-2000:]
    _assert_complete(world, out)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["sigint", "sigterm"])
def test_signal_as_the_command_exits(world: Path, tmp_path: Path, sig: int) -> None:
    """Not held: the signal is sent the moment the shutdown begins and lands wherever the exit has got to (or after
    it). The README's promise either way: 130/143, or 0 with complete outputs; nothing else (death by the signal)."""
    out, stages = tmp_path / "out", tmp_path / "stages"
    p = _spawn(["reconstruct", str(world / "idx"), "--bundles", str(world / "s" / "bundles.csv"), "--out", str(out),
                "-q"], tmp_path, stages)
    _wait_for(p, (stages / "shutdown").exists, "the shutdown")
    p.send_signal(sig)
    _, err = _finish(p)
    assert p.returncode in (0, STATUS[sig]), (p.returncode, err[-2000:])
    assert "Traceback" not in err, err[-2000:]
    _assert_complete(world, out)


def test_sigkill_then_rerun_cleans_up(world: Path, long_shot: Path, tmp_path: Path) -> None:
    """Killed (SIGKILL: no clean-up possible) while writing; the next run into the same OUT removes the staging."""
    out, stages = tmp_path / "out", tmp_path / "stages"
    argv = ["reconstruct", str(world / "idx"), "--bundles", str(long_shot), "--out", str(out), "-q", "--obj"]
    p = _spawn(argv, tmp_path, stages, "write:60")
    _wait_for(p, (stages / "write").exists, "the write")
    p.kill()
    p.communicate(timeout=60)
    assert list(out.glob(".lgi-staging-*")), "the kill was meant to land during the write"
    # The next run into the same OUT (a short shot, to keep the test quick) removes the killed run's staging.
    rerun = ["reconstruct", str(world / "idx"), "--bundles", str(world / "s" / "bundles.csv"), "--out", str(out), "-q"]
    r = subprocess.run([sys.executable, "-m", "lgi", *rerun], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert sorted(q.name for q in out.iterdir()) == [RECORD_FILE, "diagnostics.csv", "meshes.npz", "per_frame.csv",
                                                     "run.json"]


def _outputs(folder: Path) -> dict[str, bytes]:
    return {n: (folder / n).read_bytes() for n in ("meshes.npz", "diagnostics.csv", "per_frame.csv")}


@pytest.mark.slow
def test_two_runs_into_one_folder_never_leave_a_mixture(world: Path, tmp_path: Path) -> None:
    """20 rounds of two runs into one OUT (12 and 8 frames), the first held for 6 s inside its commit (its meshes
    replaced, its tables not yet), the second started then or at a random moment: OUT ends as one run's outputs,
    bit for bit, and a run refused names the other's pid."""
    short = tmp_path / "short.csv"
    d = pd.read_csv(world / "s" / "bundles.csv")
    d[d.frame < 8].to_csv(short, index=False)
    argv = {"a": ["reconstruct", str(world / "idx"), "--bundles", str(world / "s" / "bundles.csv"), "-q"],
            "b": ["reconstruct", str(world / "idx"), "--bundles", str(short), "-q"]}
    ref = {}
    for k in argv:
        assert main([*argv[k], "--out", str(tmp_path / f"ref_{k}")]) == 0
        ref[k] = _outputs(tmp_path / f"ref_{k}")
    assert ref["a"]["meshes.npz"] != ref["b"]["meshes.npz"]
    out = tmp_path / "out"
    rng = np.random.default_rng(7)
    refused = 0
    for r in range(20):
        stages = tmp_path / f"stages{r}"
        a = _spawn([*argv["a"], "--out", str(out)], tmp_path, stages, "commit:6")
        if r % 2 == 0:  # the second run starts while the first is inside its commit
            deadline = time.monotonic() + 120
            while not (stages / "commit").exists() and a.poll() is None and time.monotonic() < deadline:
                time.sleep(0.02)
        else:  # or at any moment
            time.sleep(float(rng.uniform(0.0, 3.0)))
        b = _spawn([*argv["b"], "--out", str(out)], tmp_path)
        (_, err_a), (_, err_b) = a.communicate(timeout=300), b.communicate(timeout=300)
        codes = (a.returncode, b.returncode)
        assert codes in ((0, 0), (0, 2), (2, 0)), (r, codes, err_a[-500:], err_b[-500:])
        if 2 in codes:
            refused += 1
            loser, winner = (err_a, b) if codes[0] == 2 else (err_b, a)
            assert f"another lgi run (pid {winner.pid})" in loser, loser[-500:]
        got = _outputs(out)
        assert got in (ref["a"], ref["b"]), f"round {r}: a mixture of the two runs"
        if r % 2 == 0:
            assert codes == (0, 2) and got == ref["a"], (r, codes, err_a[-800:], err_b[-800:])
        assert [p.name for p in out.glob(".lgi-*")] == [RECORD_FILE] and not list(out.glob(".*.old-*"))
    assert refused >= 10


def test_a_deployment_run_never_replaces_a_file_lgi_did_not_write(world: Path, tmp_path: Path, prefect_harness,
                                                                  monkeypatch) -> None:
    """The reconstruct-shot flow run as a deployment's run would be (its output resolved under the data root), into
    a folder where the user keeps a per_frame.csv of their own: refused before the work, naming the file, which
    stays as it was."""
    from prefect.variables import Variable

    import lgi.orchestration.deploy as deploy
    from lgi.errors import InputError
    from lgi.orchestration.reconstruct import reconstruct_shot

    root = tmp_path / "root"
    out = root / "shots" / "recon"
    out.mkdir(parents=True)
    (out / "per_frame.csv").write_text("frame,note\n0,mine\n")
    Variable.set(deploy.DATA_ROOT_VARIABLE, str(root), overwrite=True)
    monkeypatch.setattr(deploy, "in_deployment", lambda: True)
    try:
        with pytest.raises(InputError, match=r"no record of writing \(per_frame\.csv"):
            reconstruct_shot(str(world / "idx"), str(world / "s" / "bundles.csv"), "shots/recon")
    finally:
        Variable.unset(deploy.DATA_ROOT_VARIABLE)
    assert sorted(p.name for p in out.iterdir()) == ["per_frame.csv"]
    assert (out / "per_frame.csv").read_text() == "frame,note\n0,mine\n"


def _page_frames(said: str) -> int:
    return int(re.search(r"review page of (\d+) frames", said).group(1))


def test_readers_never_see_a_commit_half_done(world: Path, tmp_path: Path) -> None:
    """``lgi review`` of an OUT that another run is replacing: a reader started inside the commit waits for it and
    shows the new run whole; a reader already reading holds the commit back until it is done, and shows the old
    run whole. Without the lock the first reader met 12 frames of meshes with 8 of diagnostics."""
    short = tmp_path / "short.csv"
    d = pd.read_csv(world / "s" / "bundles.csv")
    d[d.frame < 8].to_csv(short, index=False)
    out = tmp_path / "out"
    full = ["reconstruct", str(world / "idx"), "--bundles", str(world / "s" / "bundles.csv"), "--out", str(out), "-q"]
    assert main(["reconstruct", str(world / "idx"), "--bundles", str(short), "--out", str(out), "-q"]) == 0

    def review(name: str, stages: Path | None = None, hold: str | None = None) -> subprocess.Popen:
        return _spawn(["review", str(out), "--index", str(world / "idx"), "--out", str(tmp_path / name)], tmp_path,
                      stages, hold)

    # A reader started while the run is held inside its commit (its meshes replaced, its tables not yet).
    sa, sr = tmp_path / "stages_a", tmp_path / "stages_r"
    a = _spawn(full, tmp_path, sa, "commit:5")
    deadline = time.monotonic() + 120
    while not (sa / "commit").exists() and a.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert (sa / "commit").exists(), a.communicate()[1][-800:]
    r = review("page_a", sr)
    (said, err), (_, err_a) = r.communicate(timeout=300), a.communicate(timeout=300)
    assert a.returncode == 0, err_a[-800:]
    assert r.returncode == 0, err[-800:]
    # The reader began to read after the commit's last write (the record, inside the lock), not during the hold.
    assert (sr / "read").stat().st_mtime_ns >= (out / RECORD_FILE).stat().st_mtime_ns and "waiting" in err
    assert _page_frames(said) == 12

    # A reader holding OUT (held 5 s as it reads) while a run commits into it.
    assert main(["reconstruct", str(world / "idx"), "--bundles", str(short), "--out", str(out), "-q"]) == 0
    sr2, sb = tmp_path / "stages_r2", tmp_path / "stages_b"
    r = review("page_b", sr2, "read:5")
    while not (sr2 / "read").exists() and r.poll() is None and time.monotonic() < deadline + 120:
        time.sleep(0.02)
    b = _spawn(full, tmp_path, sb)
    (said, err), (_, err_b) = r.communicate(timeout=300), b.communicate(timeout=300)
    assert r.returncode == 0 and b.returncode == 0, (err[-800:], err_b[-800:])
    # The run's commit began after the reader had written its page (all of it inside its hold on OUT).
    page = max(f.stat().st_mtime_ns for f in (tmp_path / "page_b").rglob("*") if f.is_file())
    assert (sb / "commit").stat().st_mtime_ns >= page and "waiting" in err_b
    assert _page_frames(said) == 8
    with np.load(out / "meshes.npz") as z:
        assert len(z["frames"]) == 12  # the run committed once the reader was done


def test_closed_pipe_is_quiet(world: Path, tmp_path: Path, capsys) -> None:
    """A reader that went away (``lgi ... | head``): the read end is closed before the command starts, so its first
    write breaks the pipe, whatever the output's size. The command ends quietly: status 0, nothing on stderr."""
    code, said, _ = run(["verify", str(world / "idx"), "-q"], capsys)
    assert code == 0 and len(said) > 1000  # what it would print: more than enough to meet the closed pipe
    r_fd, w_fd = os.pipe()
    os.close(r_fd)
    try:
        r = subprocess.run([sys.executable, "-m", "lgi", "verify", str(world / "idx"), "-q"], stdout=w_fd,
                           stderr=subprocess.PIPE, text=True, cwd=tmp_path, timeout=300)
    finally:
        os.close(w_fd)
    assert r.returncode == 0, r.stderr
    assert r.stderr == ""


def test_default_verification_tolerance(world: Path, tmp_path: Path, capsys) -> None:
    """The default tolerance (0.01 mm RMS) on a shape whose error is known to lie between 0.01 and 1 mm: a dent of
    0.3 mm between the markers (no marker's triangle moves, so its bundles are the neutral's and no reconstruction
    can see it) fails the default check and passes a tolerance of 0.5 mm."""
    from scipy.spatial import cKDTree

    from lgi.io.obj import read_obj

    shutil.copytree(world / "objs", tmp_path / "objs")
    neutral = read_obj(tmp_path / "objs" / "neutral.obj")
    x = np.asarray(neutral.vertices, np.float64).copy()
    m = pd.read_csv(world / "s" / "markers.csv")
    dist, _ = cKDTree(m[["x", "y", "z"]].to_numpy()).query(x)
    dent = np.setdiff1d(np.flatnonzero((dist > 0.4) & (dist < 1.0)), m[["v0", "v1", "v2"]].to_numpy().ravel())
    x[dent, 2] += 0.03  # cm
    write_obj(tmp_path / "objs" / "dent.obj", x, neutral.face_vertices, neutral.face_offsets, neutral.uvs,
              neutral.face_uvs)
    assert run(["import", str(tmp_path / "objs"), "--out", str(tmp_path / "ds"), "--rigid-vertices", "none", "-q"],
               capsys)[0] == 0
    assert run(["build", str(tmp_path / "ds"), "--markers", str(world / "s" / "markers.csv"), "--out",
                str(tmp_path / "idx"), "-q"], capsys)[0] == 0
    from lgi.evaluation.verify import verify_index
    from lgi.index.build import LGIIndex

    table = verify_index(LGIIndex.load(tmp_path / "idx")).set_index("shape")
    assert 0.01 < table.loc["dent", "rms_mm"] < 1.0 and table.loc["dent", "max_mm"] == pytest.approx(0.3, abs=1e-3)
    assert (table.drop(index="dent").rms_mm < 0.01).all()
    code, out, _ = run(["verify", str(tmp_path / "idx"), "-q"], capsys)
    assert code == 1 and "FAILED for 1" in out and "(dent)" in out, out
    code, out, _ = run(["verify", str(tmp_path / "idx"), "-q", "--tolerance", "0.5"], capsys)
    assert code == 0 and "passed" in out, out


def test_internal_error_is_status_3_and_debug_prints_the_traceback(world: Path, capsys, monkeypatch) -> None:
    """A bug (a deliberately failing internal call): status 3, one line that says it is a bug and how to get the
    traceback; with ``--debug`` anywhere on the command line, the traceback."""
    import lgi.jobs.verify

    def broken(*args, **kwargs):
        raise ZeroDivisionError("deliberate failure inside the verification")

    monkeypatch.setattr(lgi.jobs.verify, "verify", broken)
    code, out, err = run(["verify", str(world / "idx"), "-q"], capsys)
    assert code == 3, err
    assert "internal error" in err and "ZeroDivisionError" in err and "--debug" in err
    assert "Traceback" not in err + out and len(err.strip().splitlines()) == 1
    code, _, err = run(["--debug", "verify", str(world / "idx"), "-q"], capsys)
    assert code == 3
    assert "Traceback (most recent call last)" in err and "deliberate failure inside the verification" in err


def test_internal_error_status_through_the_command(world: Path, tmp_path: Path) -> None:
    """The same through the installed entry point (the status a shell sees), the failure planted by a wrapper."""
    plant = ("import sys, lgi.jobs.verify as j\n"
             "def broken(*a, **k):\n    raise KeyError('planted')\n"
             "j.verify = broken\n"
             "from lgi._entry import run\n"
             "sys.argv = ['lgi', *sys.argv[1:]]\n"
             "run()\n")
    for debug in ([], ["--debug"]):
        r = subprocess.run([sys.executable, "-c", plant, "verify", str(world / "idx"), *debug], capture_output=True,
                           text=True, cwd=tmp_path, timeout=300)
        assert r.returncode == 3, r.stderr[-2000:]
        assert ("Traceback" in r.stderr) == bool(debug), r.stderr[-2000:]
        assert "internal error: KeyError" in r.stderr


def test_a_value_error_inside_the_solver_is_a_bug(world: Path, tmp_path: Path) -> None:
    """numpy's shape errors are ValueErrors: one raised inside the solver is lgi's bug (status 3, "internal
    error"), not the user's input (status 2), and nothing is written."""
    plant = ("import sys, lgi.solve.solver as s\n"
             "def broken(*a, **k):\n"
             "    raise ValueError('operands could not be broadcast together with shapes (3,) (4,)')\n"
             "s.LGISolver.stream_from = broken\n"
             "from lgi._entry import run\n"
             "sys.argv = ['lgi', *sys.argv[1:]]\n"
             "run()\n")
    out = tmp_path / "rec"
    r = subprocess.run([sys.executable, "-c", plant, "reconstruct", str(world / "idx"), "--bundles",
                        str(world / "s" / "bundles.csv"), "--out", str(out), "-q"], capture_output=True, text=True,
                       cwd=tmp_path, timeout=300)
    assert r.returncode == 3, r.stderr[-2000:]
    assert "internal error: ValueError: operands could not be broadcast" in r.stderr and "--debug" in r.stderr
    assert not out.exists() and not list(tmp_path.glob(".rec*"))


def test_unpaired_calibration_image_is_reported(tmp_path: Path, caplog) -> None:
    from lgi.capture.calibration import pair_images

    for name in ("left1.png", "right1.png", "left2.png"):
        (tmp_path / name).write_bytes(b"")
    with caplog.at_level("WARNING", logger="lgi"):
        pairs = pair_images(tmp_path)
    assert [p[0] for p in pairs] == ["pair1.png"]
    assert "without a partner" in caplog.text and "left2.png" in caplog.text


@pytest.mark.slow
def test_flow_task_failing_on_bad_input_prints_no_traceback(world: Path, tmp_path: Path) -> None:
    """A bad OBJ found inside a task of the rebuild flow: one line and exit 2 (Prefect's own console log, which
    would print the task's traceback, is quiet unless PREFECT_LOGGING_LEVEL or --debug asks for it)."""
    shutil.copytree(world / "objs", tmp_path / "objs")
    obj_vertex("objs/smile_L.obj", 3, "v nan nan nan")(world, tmp_path)
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_LOGGING_LEVEL"}
    env["PREFECT_HOME"] = str(tmp_path / "prefect")
    r = subprocess.run([sys.executable, "-m", "lgi", "import", str(tmp_path / "objs"), "--out", str(tmp_path / "out"),
                        "--flow", "-q"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 2, r.stderr[-2000:]
    assert "Traceback" not in r.stderr and "smile_L.obj" in r.stderr and "non-finite" in r.stderr


@pytest.mark.parametrize("sig", [signal.SIGINT], ids=["sigint"])
def test_signal_inside_a_flow_task_stops_the_local_server(world: Path, long_shot: Path, tmp_path: Path,
                                                           sig: int) -> None:
    """Ctrl-C while the reconstruct-shot flow's tasks run: status 130, no traceback, the chunk folder removed and
    the local Prefect server the command started stopped (left running it would keep the pipes open, and
    ``communicate`` below would time out). The signal waits for a chunk's choices, a file the flow writes."""
    out = tmp_path / "out"
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_LOGGING_LEVEL"}  # the command's own default
    env.update(PREFECT_HOME=str(tmp_path / "prefect"))
    p = _spawn(["reconstruct", str(world / "idx"), "--bundles", str(long_shot), "--out", str(out), "--flow",
                "--chunk-size", "40", "-q"], tmp_path, env=env, session=True)
    _wait_for(p, lambda: bool(list(tmp_path.glob(".out.chunks-*/choice_*.npz"))), "a chunk's choices")
    p.send_signal(sig)
    try:
        _, err = p.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        _kill(p)  # the command and the server it left running
        p.communicate()
        pytest.fail("the command's pipes stayed open after the interrupt: the local Prefect server was left running")
    assert p.returncode == STATUS[sig], err[-2000:]
    assert "Traceback" not in err and SAYS[sig] in err, err[-4000:]
    assert not out.exists() or not [q for q in out.iterdir()]
    # An interrupted flow's finished chunks wait, keyed to the job, for the same command to resume from them.
    assert all((d / ".resume.json").is_file() for d in tmp_path.glob(".out.chunks-*"))


def test_review_refuses_meshes_and_diagnostics_of_different_runs(world: Path, tmp_path: Path, capsys) -> None:
    """A folder holding one run's meshes and another's diagnostics (a copy by hand, a run cut short) is refused,
    not drawn as one shot."""
    for keep in (slice(0, 3), slice(1, None)):  # diagnostics with frames the meshes lack, and the other way
        rec = tmp_path / f"rec{keep.start}"
        shutil.copytree(world / "rec", rec)
        z = dict(np.load(rec / "meshes.npz"))
        frames = z["frames"]
        if keep.start == 0:
            save_npz(rec / "meshes.npz", **{k: (v[keep] if len(v) == len(frames) else v) for k, v in z.items()})
        else:
            d = pd.read_csv(rec / "diagnostics.csv")
            d[d["frame"] != frames[0]].to_csv(rec / "diagnostics.csv", index=False)
        code, _, err = run(["review", str(rec), "--index", str(world / "idx"), "--out", str(tmp_path / "p")], capsys)
        assert code == 2 and "diagnostics.csv" in err and "not of the same reconstruction" in err, err
        assert not (tmp_path / "p").exists()


def test_threads_reading_one_folder_share_its_lock(tmp_path: Path) -> None:
    """Two threads of one process read one folder at once (a flow's review and export tasks): the folder stays
    locked against another process's commit until the last of them is done, whichever took the lock first."""
    import threading

    from lgi.io.atomic import reading

    folder = tmp_path / "rec"
    folder.mkdir()
    probe = [sys.executable, "-c", "import fcntl, os, sys\nfd = os.open(sys.argv[1], os.O_RDONLY | os.O_DIRECTORY)\n"
             "try:\n    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)\nexcept BlockingIOError:\n    sys.exit(1)\n",
             str(folder)]

    def locked() -> bool:
        return subprocess.run(probe).returncode == 1

    start, first_done, second_done = threading.Barrier(2), threading.Event(), threading.Event()

    def reader(done: threading.Event, hold: threading.Event) -> None:
        with reading(folder):
            start.wait()
            hold.wait(30)
        done.set()

    release_first, release_second = threading.Event(), threading.Event()
    threads = [threading.Thread(target=reader, args=(first_done, release_first)),
               threading.Thread(target=reader, args=(second_done, release_second))]
    for t in threads:
        t.start()
    time.sleep(0.3)
    assert locked()
    release_first.set()
    assert first_done.wait(10)
    assert locked()  # the other thread still reads
    release_second.set()
    for t in threads:
        t.join(10)
    assert not locked()
