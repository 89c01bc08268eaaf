"""The shot review page (lgi review): packing, bad input, and the page itself in a real headless browser.

The browser tests drive Debian's chromium through Playwright's Python package (no browser download); they skip
with the reason when either is missing."""

from __future__ import annotations

import io
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from _review_checks import SHOW_HOSTILE, check_marker_colours, check_nothing_ran, hostile_page

from lgi.cli import main
from lgi.io.record import RECORD_FILE
from lgi.review.pack import blob, decode_codes, dequantise_frames, encode_codes, quantise_frames, quantise_map, unblob

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"


# ------------------------------------------------------------------------------------------------ packing
def test_quantised_frames_round_trip_within_half_a_step():
    rng = np.random.default_rng(0)
    rest = rng.normal(0, 5, (400, 3)).astype(np.float32)
    verts = rest[None] + rng.normal(0, 0.4, (12, 400, 3)).astype(np.float32)
    verts[:, :100] = rest[:100]  # vertices that never move are left out of the codes
    q = quantise_frames(verts, rest)
    back = dequantise_frames(q)
    err = np.abs(back.astype(np.float64) - verts.astype(np.float64)).max()
    # Half a code step, plus float32 rounding of coordinates of ~15 cm.
    assert err <= q.error_bound_cm + 4e-6
    assert q.error_bound_cm < 1e-4  # 1 um for displacements of a couple of cm
    assert q.codes.dtype == np.int16 and not np.isin(np.arange(100), q.moving).any()
    coarse = quantise_frames(verts, rest, step=1e-3)  # lgi review's default, 10 um
    assert coarse.scale == 1e-3 and np.abs(dequantise_frames(coarse) - verts).max() <= 5e-4 + 4e-6
    for arr in (q.codes, q.moving, q.rest):
        assert np.array_equal(unblob(blob(arr)), arr)
    assert np.array_equal(unblob(blob(q.codes, compress=False)), q.codes)
    # Frame differences wrap in int16 (a jump of more than half the range) and still come back exactly.
    jumpy = q.codes.copy()
    jumpy[::2] = 32767
    jumpy[1::2] = -32767
    for c in (q.codes, jumpy):
        assert np.array_equal(decode_codes(unblob(blob(encode_codes(c))), c.shape), c)


def test_colour_map_codes():
    c = quantise_map(np.array([0.0, 0.5, 1.0, 7.0, np.nan]), 1.0)
    assert c.tolist() == [0, 128, 255, 255, 0]


def test_still_shot_quantises():
    rest = np.ones((5, 3), np.float32)
    q = quantise_frames(np.repeat(rest[None], 3, axis=0), rest)
    assert q.moving.size == 0 and np.array_equal(dequantise_frames(q), np.repeat(rest[None], 3, axis=0))


# ------------------------------------------------------------------------------------------------ a small shot
@pytest.fixture(scope="module")
def shot(tmp_path_factory) -> Path:
    """A 20-frame synthetic shot of 3000 vertices, reconstructed from bundles with a few missing."""
    t = tmp_path_factory.mktemp("review")
    assert main(["synth", "--out", str(t / "s"), "--vertices", "3000", "--frames", "20", "-q"]) == 0
    assert main(["build", str(t / "s" / "dataset"), "--markers", str(t / "s" / "markers.csv"), "--out",
                 str(t / "idx"), "--jaw-rig", str(t / "s" / "jaw_rig.npz"), "-q"]) == 0
    d = pd.read_csv(t / "s" / "bundles.csv")
    d = d.drop(index=np.random.default_rng(1).choice(len(d), len(d) // 25, replace=False))
    d.to_csv(t / "bundles.csv", index=False)
    assert main(["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(t / "rec"),
                 "--noise", "0", "-q"]) == 0
    assert main(["review", str(t / "rec"), "--index", str(t / "idx"), "--truth", str(t / "s" / "truth.npz"),
                 "--out", str(t / "page")]) == 0
    return t


def test_method_blendshape_is_the_baseline_fit(shot, capsys):
    """--method blendshape writes the rigged blendshape fit of the benchmarks, as a reconstruction with its review
    page; lgi review --compare shows LGI against it."""
    from lgi.capture.bundles import read_bundles
    from lgi.evaluation.baselines import RiggedBlendshapeSolver
    from lgi.index.build import LGIIndex

    t = shot
    assert main(["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(t / "recb"),
                 "--method", "blendshape", "--review", "-q"]) == 0
    out = capsys.readouterr().out
    assert "blendshape fit" in out and str(t / "recb" / "review" / "index.html") in out
    index = LGIIndex.load(t / "idx")
    want = RiggedBlendshapeSolver(index).solve_sequence(read_bundles(t / "bundles.csv", index.marker_names).positions)
    got = np.load(t / "recb" / "meshes.npz")
    assert np.array_equal(got["vertices"], want) and got["jaw"].shape == (20, 4)
    d = pd.read_csv(t / "recb" / "diagnostics.csv")
    assert set(d.status) == {"fitted", "missing"}
    seen = d.status == "fitted"
    assert np.allclose(d.residual_mm[seen], d.residual_before_mm[seen])
    assert (t / "recb" / "per_frame.csv").is_file() and (t / "recb" / "review" / "review_frames.js").is_file()
    assert main(["review", str(t / "rec"), "--index", str(t / "idx"), "--compare", str(t / "recb"),
                 "--out", str(t / "page_compare")]) == 0
    assert "compare" in capsys.readouterr().out


def test_a_rerun_without_review_removes_the_earlier_page(shot, tmp_path):
    """A run owns the outputs it writes: a re-run without --review leaves no page of the earlier run behind, and
    a folder named review holding anything else is left alone."""
    t, out = shot, tmp_path / "rec"
    args = ["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(out), "-q"]
    assert main([*args, "--review"]) == 0 and (out / "review" / "index.html").is_file()
    # A comparison with scans in OUT/compare (where the flows write it) measured these meshes: it goes too.
    assert main(["compare", str(out), "--index", str(t / "idx"), "--pairs", str(_scans(t)), "--out",
                 str(out / "compare")]) == 0
    assert main(args) == 0
    assert not (out / "review").exists() and not (out / "compare").exists() and (out / "meshes.npz").is_file()
    (out / "review").mkdir()
    (out / "review" / "notes.txt").write_text("mine")
    assert main(args) == 0
    assert (out / "review" / "notes.txt").read_text() == "mine"


def test_method_blendshape_says_which_options_it_ignores(shot, tmp_path, capsys):
    t = shot
    assert main(["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--out", str(tmp_path / "b"),
                 "--method", "blendshape", "--smooth", "5", "--far-field", "off", "-q"]) == 0
    err = capsys.readouterr().err
    assert "--smooth, --far-field" in err and "ignored by the blendshape fit" in err, err


def test_method_blendshape_refuses_lgi_only_options(shot, tmp_path, capsys):
    assert main(["reconstruct", str(shot / "idx"), "--bundles", str(shot / "bundles.csv"), "--out",
                 str(tmp_path / "r"), "--method", "blendshape", "--max-gap", "3"]) == 2
    assert "--max-gap" in capsys.readouterr().err and not (tmp_path / "r").exists()


def test_review_writes_a_self_contained_page(shot):
    page = shot / "page"
    assert sorted(p.name for p in page.iterdir()) == [RECORD_FILE, "frames", "index.html", "review_frames.js",
                                                      "review_meta.js", "viewer.js"]
    # 20 frames: two blocks of 8 and one of 4
    assert sorted(p.name for p in (page / "frames").iterdir()) == ["block_00000.html", "block_00001.html",
                                                                    "block_00002.html", "overview.html"]
    html = (page / "index.html").read_text()
    js = (page / "viewer.js").read_text()
    for text in (html, js):  # nothing fetched at view time
        assert "http://" not in text and "https://" not in text and "fetch(" not in text


def test_review_not_a_reconstruction(shot, tmp_path, capsys):
    out = tmp_path / "page"
    assert main(["review", str(shot / "s"), "--index", str(shot / "idx"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "meshes.npz" in err and "not a reconstruction" in err and "Traceback" not in err
    assert not out.exists()


def test_review_compare_other_topology(shot, tmp_path, capsys):
    other = tmp_path / "other"
    other.mkdir()
    np.savez(other / "meshes.npz", vertices=np.zeros((20, 50, 3), np.float32), frames=np.arange(20))
    out = tmp_path / "page"
    assert main(["review", str(shot / "rec"), "--index", str(shot / "idx"), "--compare", str(other),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(other / "meshes.npz") in err and "topology" in err and not out.exists()


def test_review_truth_of_another_shot(shot, tmp_path, capsys):
    bad = tmp_path / "truth.npz"
    np.savez(bad, vertices=np.zeros((5, 3000 + 21, 3), np.float32), frames=np.arange(100, 105))
    assert main(["review", str(shot / "rec"), "--index", str(shot / "idx"), "--truth", str(bad),
                 "--out", str(tmp_path / "page")]) == 2
    assert str(bad) in capsys.readouterr().err


def test_review_refuses_a_folder_of_other_files(shot, tmp_path, capsys):
    out = tmp_path / "page"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["review", str(shot / "rec"), "--index", str(shot / "idx"), "--out", str(out)]) == 2
    assert "notes.txt" in capsys.readouterr().err and (out / "notes.txt").read_text() == "mine"


# ------------------------------------------------------------------------------------------------ long takes
def test_colour_top_by_blocks_is_the_percentile():
    """The colour bar's top seen block by block is the same whatever the blocks, and the 99.9th percentile to
    within a bin (2**-12 relative)."""
    from lgi.review.pack import ColourTop, colour_top

    x = np.random.default_rng(3).gamma(2.0, 0.4, (60, 500)).astype(np.float32)
    x[5, 7] = np.nan
    want = np.nanpercentile(x, 99.9)
    tops = set()
    for step in (1, 7, 60):
        t = ColourTop()
        for lo in range(0, 60, step):
            t.add(x[lo:lo + step])
        tops.add(t.top())
    assert len(tops) == 1 and want <= tops.pop() <= want * (1 + 2**-12)
    assert colour_top(np.zeros(4)) == 1e-3 and colour_top(np.array([np.nan])) == 1e-3


def _page_blocks(page: Path) -> tuple[dict, list[dict]]:
    header = _payload(page / "review_frames.js")
    return header, [_payload(page / name) for name in header["files"]]


def _decoded(page: Path) -> dict[str, np.ndarray]:
    """A page's frames decoded as the page does (codes, maps, diagnostics presence), blocks joined."""
    header, blocks = _page_blocks(page)
    n_k = unblob(header["moving"]).size
    out = {"codes": np.concatenate([decode_codes(unblob(b["codes"]), (b["n"], n_k, 3)) for b in blocks])}
    for m in header["maps"]:
        if "values" not in m:
            out[m["key"]] = np.concatenate([unblob(b["maps"][m["key"]]) for b in blocks])
    out["present"] = np.concatenate([unblob(b["present"]) for b in blocks])
    return out


@pytest.fixture(scope="module")
def small_blocks(shot, tmp_path_factory) -> Path:
    """The shot's page in blocks of 8 frames (3 blocks for its 20 frames), its diagnostics read 150 rows at a time
    from a copy whose rows are shuffled (not in frame order)."""
    import lgi.jobs.review as job

    t = tmp_path_factory.mktemp("small_blocks")
    rec = t / "rec"
    shutil.copytree(shot / "rec", rec)
    d = pd.read_csv(rec / "diagnostics.csv", keep_default_na=False, na_values=[""])
    d.sample(frac=1.0, random_state=0).to_csv(rec / "diagnostics.csv", index=False)
    mp = pytest.MonkeyPatch()
    mp.setattr(job, "BLOCK", 6)
    mp.setattr(job, "DIAG_CHUNK_ROWS", 150)
    try:
        job.review(rec, shot / "idx", t / "page", job.ReviewOptions(truth=str(shot / "s" / "truth.npz")))
    finally:
        mp.undo()
    return t / "page"


def test_blocks_decode_to_the_shot_quantised_whole(shot, small_blocks):
    """Blocks of 6 frames hold the codes of the whole shot quantised at once (one scale for the shot: the same
    values as the page of lgi's blocks), within half a step of the meshes; the colour maps and the overview are the
    same whatever the block size."""
    from lgi.index.build import LGIIndex

    meta = _payload(small_blocks / "review_meta.js")
    header, blocks = _page_blocks(small_blocks)
    assert [b["lo"] for b in blocks] == [0, 6, 12, 18] and [b["n"] for b in blocks] == [6, 6, 6, 2]
    assert _page_blocks(shot / "page")[0]["block"] != 6
    got = _decoded(small_blocks)
    one = _decoded(shot / "page")
    verts = np.load(shot / "rec" / "meshes.npz")["vertices"]
    q = quantise_frames(verts, LGIIndex.load(shot / "idx").arrays["neutral"], meta["quantisation"]["scale_cm"])
    assert np.array_equal(unblob(header["moving"]), q.moving) and header["scale"] == q.scale
    assert np.array_equal(got["codes"], q.codes) and np.array_equal(got["codes"], one["codes"])
    assert np.abs(dequantise_frames(q) - verts).max() <= q.error_bound_cm + 4e-6
    for key in ("truth", "correction"):
        assert np.array_equal(got[key], one[key]), key
    tops = {m["key"]: m["vmax_mm"] for m in _payload(shot / "page" / "review_frames.js")["maps"]}
    assert {m["key"]: m["vmax_mm"] for m in header["maps"]} == tops
    # The overview: every 16th frame (at least 16 apart), the same codes as the blocks'.
    ov = _payload(small_blocks / header["overview"])
    assert ov["frames"] == [0, 16]
    n_k = q.moving.size
    assert np.array_equal(decode_codes(unblob(ov["codes"]), (2, n_k, 3)), q.codes[[0, 16]])
    assert np.array_equal(unblob(ov["maps"]["truth"]), got["truth"][[0, 16]])


def test_block_diagnostics_are_the_csv_rows(shot, small_blocks):
    """Each block carries its frames' diagnostics rows in (frame, marker) order, whatever the order of the CSV's
    rows and its chunks; the markers' statuses of every frame are in the page's header."""
    from lgi.review.pack import unjson_blob

    meta = _payload(small_blocks / "review_meta.js")
    _, blocks = _page_blocks(small_blocks)
    d = pd.read_csv(shot / "rec" / "diagnostics.csv", keep_default_na=False, na_values=[""])
    markers, frames = meta["markers"], meta["frames"]
    status = unblob(meta["status"]).reshape(len(frames), len(markers))
    assert np.array_equal(status, unblob(_payload(shot / "page" / "review_meta.js")["status"]).reshape(status.shape))
    for b in blocks:
        cols = {c["name"]: c for c in b["diagnostics"]}
        present = unblob(b["present"]).reshape(b["n"], len(markers)).astype(bool)
        rows = d[d.frame.isin(frames[b["lo"]:b["lo"] + b["n"]])]
        assert present.sum() == len(rows)
        fi = rows.frame.map({f: i for i, f in enumerate(frames)}).to_numpy() - b["lo"]
        mi = rows.marker.map({m: i for i, m in enumerate(markers)}).to_numpy()
        slot = np.cumsum(present.ravel()) - 1  # a present (frame, marker)'s row in the block's columns
        at = slot[fi * len(markers) + mi]
        got = unblob(cols["residual_mm"]["data"])[at]
        assert np.allclose(got, rows.residual_mm.to_numpy(np.float32), equal_nan=True)
        values = np.array(unjson_blob(cols["status"]["values"]))
        assert (values[unblob(cols["status"]["data"])[at]] == rows.status.to_numpy()).all()
        assert (status[b["lo"] + fi, mi] == [meta["statuses"].index(s) for s in rows.status]).all()


def test_review_reads_the_meshes_by_frame_range(shot, tmp_path, monkeypatch):
    """lgi review reads meshes.npz (and the truth) a block of frames at a time, never the whole array: its memory
    does not grow with the take."""
    import lgi.jobs.review as job
    from lgi.io.stored import StoredArray

    reads: list[tuple[str, int]] = []
    rows, array = StoredArray.rows, StoredArray.__array__

    def counted(self, lo, hi):
        if self.ndim == 3:  # meshes; frames and jaw (F,) and (F, 4) are read whole
            reads.append((Path(self.path).name, min(hi, self.shape[0]) - lo))
        return rows(self, lo, hi)

    def whole(self, dtype=None, copy=None):
        assert self.ndim < 3, f"{self.path} read whole"
        return array(self, dtype, copy)

    monkeypatch.setattr(StoredArray, "rows", counted)
    monkeypatch.setattr(StoredArray, "__array__", whole)
    monkeypatch.setattr(job, "BLOCK", 6)
    job.review(shot / "rec", shot / "idx", tmp_path / "page", job.ReviewOptions(truth=str(shot / "s" / "truth.npz")))
    sizes = {name: [n for f, n in reads if f == name] for name in ("meshes.npz", "truth.npz")}
    # Two passes of 4 blocks (6, 6, 6, 2 frames) over each; a scan's single frames are the only other reads.
    assert sizes["meshes.npz"] == [6, 6, 6, 2] * 2 and sizes["truth.npz"] == [6, 6, 6, 2] * 2


# ------------------------------------------------------------------------------------------------ scans
SCANNED = (5, 12)  # positions in the shot of the frames with a scan
HOLE = (0.0, 6.0, 1.6, 1.2)  # a forehead hole in the scans: centre x, y (cm), half width, half height


def _scans(t: Path) -> Path:
    """Scans of the shot's SCANNED frames (their true surfaces remeshed, with a forehead hole) and their pairs
    CSV (relative paths)."""
    from lgi.dataset.shapes import ShapeDataset
    from lgi.evaluation.compare import remeshed_scan
    from lgi.io.obj import write_obj

    folder = t / "scans"
    if (folder / "pairs.csv").is_file():
        return folder / "pairs.csv"
    folder.mkdir()
    truth = np.load(t / "s" / "truth.npz")
    tri = ShapeDataset.load(t / "s" / "dataset").triangles.astype(np.int64)
    rows = []
    for k in SCANNED:
        x = truth["vertices"][k].astype(np.float64)
        v, g = remeshed_scan(x, tri, 0.25, HOLE)
        write_obj(folder / f"take_{k}.obj", v, g.ravel(), np.arange(0, 3 * len(g) + 1, 3))
        rows.append({"frame": int(truth["frames"][k]), "scan": f"take_{k}.obj"})
    pd.DataFrame(rows).to_csv(folder / "pairs.csv", index=False)
    return folder / "pairs.csv"


@pytest.fixture(scope="module")
def scanned(shot) -> Path:
    """lgi compare of the shot's SCANNED frames (face region) and its review page with --scans."""
    pairs = _scans(shot)
    assert main(["compare", str(shot / "rec"), "--index", str(shot / "idx"), "--pairs", str(pairs), "--region",
                 "face", "--out", str(shot / "compare")]) == 0
    assert main(["review", str(shot / "rec"), "--index", str(shot / "idx"), "--scans", str(shot / "compare"),
                 "--out", str(shot / "page_scans")]) == 0
    return shot


def _payload(path: Path) -> dict:
    """The JSON a data script assigns (``window.NAME = {...};``) or a block page holds."""
    import json

    text = path.read_text()
    if path.suffix == ".html":
        start = text.index('id="lgi-block">') + len('id="lgi-block">')
        return json.loads(text[start:text.index("</script>", start)])
    return json.loads(text[text.index("= {") + 2:].rstrip().rstrip(";"))


def _shifted_scan(t: Path, folder: Path) -> Path:
    """A folder with take_5.obj moved 30 cm (a scan of the wrong moment: it covers no face) and its pairs.csv."""
    from lgi.io.obj import read_obj, write_obj

    folder.mkdir()
    mesh = read_obj(t / "scans" / "take_5.obj")
    write_obj(folder / "take_5.obj", mesh.vertices + [30.0, 0, 0], mesh.face_vertices, mesh.face_offsets)
    pd.DataFrame([{"frame": int(np.load(t / "s" / "truth.npz")["frames"][5]), "scan": "take_5.obj"}]).to_csv(
        folder / "pairs.csv", index=False)
    return folder


def test_reconstruct_with_scans_plain_and_flow(prefect_harness, scanned, tmp_path, capsys):
    """lgi reconstruct --scans compares the shot with its scans after the reconstruction, plain and with --flow:
    the same compare files, the page's scan map. A scan that covers no face leaves the reconstruction written,
    no compare folder, and exits 2 naming the scan, on both paths."""
    import filecmp

    t = scanned
    base = ["reconstruct", str(t / "idx"), "--bundles", str(t / "bundles.csv"), "--noise", "0", "--review", "-q",
            "--scans", str(t / "scans" / "pairs.csv"), "--scan-region", "face"]
    assert main([*base, "--out", str(tmp_path / "plain")]) == 0
    assert main([*base, "--out", str(tmp_path / "flow"), "--flow", "--chunk-size", "7"]) == 0
    assert "2 frames compared" in capsys.readouterr().out
    # The scan options without --scans do nothing, and say so.
    assert main([*base[:base.index("--scans")], "--scan-gate", "5", "--out", str(tmp_path / "noscans")]) == 0
    assert "ignored without it" in capsys.readouterr().err and not (tmp_path / "noscans" / "compare").exists()
    for name in ("summary.csv", "summary.json", "vertex_distances.parquet", "scan_distances.parquet"):
        assert filecmp.cmp(tmp_path / "plain" / "compare" / name, tmp_path / "flow" / "compare" / name,
                           shallow=False), name
    for out in ("plain", "flow"):
        assert '"key":"scan"' in (tmp_path / out / "review" / "review_frames.js").read_text()
    # A scan shifted 30 cm covers no face.
    bad = _shifted_scan(t, tmp_path / "bad")
    base[base.index(str(t / "scans" / "pairs.csv"))] = str(bad / "pairs.csv")
    for out, extra in (("plain_bad", []), ("flow_bad", ["--flow"])):
        assert main([*base, "--out", str(tmp_path / out), *extra]) == 2
        err = capsys.readouterr().err
        assert "covers no part of the face" in err and "take_5.obj" in err and "is written" in err
        assert (tmp_path / out / "meshes.npz").is_file() and not (tmp_path / out / "compare").exists()


def test_scan_map_packs_the_scanned_frames_only(scanned):
    """The scan map holds codes for the frames with a scan only; covered vertices carry their distance (within
    half a code step), uncovered ones (the scans' forehead hole) and those outside the compared region their own
    codes, never 0 mm; the RMS curve and the marks are at the scanned frames and nowhere else."""
    from lgi.review.pack import NOT_COVERED, NOT_MEASURED, TOP_WITH_GAPS

    t = scanned
    data = _payload(t / "page_scans" / "review_frames.js")
    meta = _payload(t / "page_scans" / "review_meta.js")
    m = next(mp for mp in data["maps"] if mp["key"] == "scan")
    slots = np.array(m["slots"])
    assert np.flatnonzero(slots >= 0).tolist() == list(SCANNED) and slots[list(SCANNED)].tolist() == [0, 1]
    codes = unblob(m["values"])
    assert codes.shape == (2, meta["n_vertices"]) and codes.dtype == np.uint8
    table = pd.read_parquet(t / "compare" / "vertex_distances.parquet")
    frames = meta["frames"]
    neutral = np.load(t / "s" / "truth.npz")["vertices"][0]
    for k, pos in enumerate(SCANNED):
        rows = table[table.frame == frames[pos]]
        c = codes[k]
        cov = rows[rows.covered]
        step = m["vmax_mm"] / TOP_WITH_GAPS
        got = c[cov.vertex].astype(float) * step
        want = np.minimum(cov.distance_mm.to_numpy(), m["vmax_mm"])
        assert np.abs(got - want).max() <= step / 2 + 1e-6
        assert (c[cov.vertex] <= TOP_WITH_GAPS).all()
        unc = rows[~rows.covered].vertex.to_numpy()
        assert unc.size > 20 and (c[unc] == NOT_COVERED).all()
        # The scans' forehead hole is among the uncovered vertices.
        cx, cy, hx, hy = HOLE
        x = neutral
        hole = np.flatnonzero((np.abs(x[:, 0] - cx) < hx - 0.3) & (np.abs(x[:, 1] - cy) < hy - 0.3) & (x[:, 2] > 0))
        assert hole.size and np.isin(hole, unc).all()
        outside = np.setdiff1d(np.arange(c.size), rows.vertex.to_numpy())
        assert outside.size > 0 and (c[outside] == NOT_MEASURED).all()
    curve = unblob(next(cv for cv in meta["curves"] if cv["key"] == "scan_rms")["values"])
    summary = pd.read_csv(t / "compare" / "summary.csv")
    assert np.flatnonzero(np.isfinite(curve)).tolist() == list(SCANNED)
    assert np.allclose(curve[list(SCANNED)], summary.rms_mm)
    assert meta["marks"] == [{"label": "scan", "frames": list(SCANNED)}]


def test_scans_of_another_reconstruction_are_refused(scanned, tmp_path, capsys):
    """Distances measured on other meshes than the page's (here the truth, on the same frames) are refused, the
    file named; so is a folder that is not lgi compare's."""
    from lgi.io.npz import save_npz

    t = scanned
    truth = np.load(t / "s" / "truth.npz")
    (tmp_path / "true").mkdir()
    save_npz(tmp_path / "true" / "meshes.npz", vertices=truth["vertices"], frames=truth["frames"])
    assert main(["compare", str(tmp_path / "true"), "--index", str(t / "idx"), "--pairs",
                 str(t / "scans" / "pairs.csv"), "--out", str(tmp_path / "c_true")]) == 0
    capsys.readouterr()
    out = tmp_path / "page"
    assert main(["review", str(t / "rec"), "--index", str(t / "idx"), "--scans", str(tmp_path / "c_true"),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path / "c_true" / "summary.json") in err and "other vertices" in err and not out.exists()
    assert main(["review", str(t / "rec"), "--index", str(t / "idx"), "--scans", str(t / "s"),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(t / "s") in err and "lgi compare --out" in err and not out.exists()


def test_shot_flow_compares_its_scans(prefect_harness, scanned, tmp_path):
    """The reconstruct-shot flow given scans runs lgi compare's job into OUT/compare (the same files as the
    command), links its table and heat maps in the report, and puts the scan map on its review page. A scan that
    covers no part of the face is reported (table artifact, report, page warning) and the reconstruction kept;
    a scan file that is not there is refused before any work."""
    import filecmp

    from prefect.artifacts import Artifact

    from flows.reconstruct_shot import reconstruct_shot
    from lgi.errors import InputError
    from lgi.orchestration import artifact_key

    t = scanned
    pairs = t / "scans" / "pairs.csv"
    out = tmp_path / "flow"
    summary = reconstruct_shot(index_dir=str(t / "idx"), bundles=str(t / "bundles.csv"), out=str(out), noise=0,
                               chunk_size=10, scans=str(pairs), scan_region="face")
    assert summary["compare"]["status"] == "done"
    assert main(["compare", str(out), "--index", str(t / "idx"), "--pairs", str(pairs), "--region", "face",
                 "--out", str(tmp_path / "cli")]) == 0
    for name in ("summary.csv", "summary.json", "vertex_distances.parquet", "scan_distances.parquet"):
        assert filecmp.cmp(out / "compare" / name, tmp_path / "cli" / name, shallow=False), name
    assert sorted(p.name for p in (out / "compare" / "heatmaps").iterdir()) == \
        sorted(p.name for p in (tmp_path / "cli" / "heatmaps").iterdir())
    assert '"key":"scan"' in (out / "review" / "review_frames.js").read_text()
    report = Artifact.get(artifact_key("shot-report", out)).data
    assert (out / "compare" / "summary.csv").as_uri() in report and report.count("data:image/png;base64,") >= 3
    table = Artifact.get(artifact_key("shot-compare", out))
    assert table is not None and "take_5.obj" in table.data
    # A scan of the wrong moment (shifted 30 cm): the comparison fails, the shot is reconstructed all the same.
    bad = _shifted_scan(t, tmp_path / "bad")
    out2 = tmp_path / "flow_bad"
    s2 = reconstruct_shot(index_dir=str(t / "idx"), bundles=str(t / "bundles.csv"), out=str(out2), noise=0,
                          chunk_size=10, scans=str(bad / "pairs.csv"))
    assert s2["compare"]["status"] == "failed" and "covers no part of the face" in s2["compare"]["error"]
    assert str(bad / "take_5.obj") in s2["compare"]["error"]
    assert (out2 / "meshes.npz").is_file() and not (out2 / "compare").exists()
    table = Artifact.get(artifact_key("shot-compare", out2))
    assert "failed" in table.data and "covers no part of the face" in table.data
    assert "scan comparison failed" in Artifact.get(artifact_key("shot-report", out2)).data
    meta = (out2 / "review" / "review_meta.js").read_text()
    assert "scan comparison failed" in meta and '"key":"scan"' not in (out2 / "review" / "review_frames.js").read_text()
    # A scan file that is not there: refused before the reconstruction.
    out3 = tmp_path / "flow_missing"
    with pytest.raises(InputError, match="scan not found"):
        reconstruct_shot(index_dir=str(t / "idx"), bundles=str(t / "bundles.csv"), out=str(out3),
                         scans=[[int(np.load(t / "s" / "truth.npz")["frames"][5]), str(bad / "nope.obj")]])
    assert not out3.exists()
    # A re-run without scans removes the earlier comparison, which measured the earlier meshes.
    reconstruct_shot(index_dir=str(t / "idx"), bundles=str(t / "bundles.csv"), out=str(out), noise=0,
                     chunk_size=10, review=False)
    assert not (out / "compare").exists()


def test_shot_flow_writes_and_links_the_page(prefect_harness, shot):
    """The reconstruct-shot flow writes OUT/review and links it from its report artifact. (Before the browser
    tests: Playwright's sync API keeps an event loop running in this thread, where Prefect's sync calls would
    return coroutines.)"""
    from prefect.artifacts import Artifact

    from flows.reconstruct_shot import reconstruct_shot
    from lgi.orchestration import artifact_key

    out = shot / "via_flow"
    summary = reconstruct_shot(index_dir=str(shot / "idx"), bundles=str(shot / "bundles.csv"), out=str(out),
                               noise=0, chunk_size=10)
    page = out / "review" / "index.html"
    assert summary["review"] == str(page.resolve()) and (out / "review" / "review_frames.js").is_file()
    report = Artifact.get(artifact_key("shot-report", out))
    assert report is not None and page.resolve().as_uri() in report.data


def test_demo_writes_the_page_and_prints_its_path(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "demo"), "--vertices", "1500", "--frames", "8", "-q"]) == 0
    page = (tmp_path / "demo" / "review" / "index.html").resolve()
    assert str(page) in capsys.readouterr().out
    meta = (tmp_path / "demo" / "review" / "review_meta.js").read_text()
    assert '"noise estimate"' in meta and '"options"' in meta
    assert "distance to the truth" in (page.parent / "review_frames.js").read_text()


# ------------------------------------------------------------------------------------------------ the browser
@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api", reason="Playwright's Python package is not installed "
                                                                 "(pip install playwright)")
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"no chromium at {CHROMIUM} (apt-get install -y chromium)")
    with sync_api.sync_playwright() as p:
        try:
            # SwiftShader: WebGL on the CPU, as a headless machine has no GPU.
            b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--use-angle=swiftshader",
                                                                  "--enable-unsafe-swiftshader"])
        except Exception as exc:  # noqa: BLE001 - any launch failure means the browser cannot run here
            pytest.skip(f"chromium cannot start here: {exc}")
        yield b
        b.close()


@pytest.fixture()
def page(browser, shot):
    pg = browser.new_page(viewport={"width": 1100, "height": 760}, device_scale_factor=1, bypass_csp=True)
    errors: list[str] = []
    pg.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto((shot / "page" / "index.html").resolve().as_uri())
    pg.wait_for_function("window.lgiReview && (window.lgiReview.idle || window.lgiReview.error)", timeout=60_000)
    pg.errors = errors
    yield pg
    pg.close()


def _pixels(png: bytes) -> np.ndarray:
    import matplotlib.image

    return (matplotlib.image.imread(io.BytesIO(png), format="png")[..., :3] * 255).round().astype(np.int16)


def test_page_loads_from_file_without_errors(page):
    assert page.evaluate("window.lgiReview.error") is None
    assert page.errors == []
    timing = page.evaluate("window.lgiReview.timing")
    assert timing["decode_ms"] >= 0 and page.evaluate("window.lgiReview.nFrames") == 20


def test_canvas_is_not_blank_and_screenshot_kept(page, tmp_path):
    png = page.locator("#gl").screenshot()
    px = _pixels(png)
    background = px[2, 2]
    differs = np.any(np.abs(px - background) > 12, axis=2)
    assert differs.mean() > 0.1  # the face covers a good share of the view
    assert len(np.unique(px[differs].reshape(-1, 3), axis=0)) > 50  # shaded, not flat
    page.screenshot(path=str(tmp_path / "review.png"))
    assert (tmp_path / "review.png").stat().st_size > 10_000


def test_slider_changes_the_picture(page, tmp_path):
    page.uncheck("#showMarkers")
    before = _pixels(page.locator("#gl").screenshot())
    page.locator("#slider").fill("15")
    assert page.evaluate("window.lgiReview.frame()") == 15
    assert "16/20" in page.inner_text("#frameLabel")
    after = _pixels(page.locator("#gl").screenshot(path=str(tmp_path / "frame15.png")))
    assert np.any(np.abs(after - before) > 12, axis=2).sum() > 200


def test_colour_map_changes_the_colours(page, tmp_path):
    page.uncheck("#showMarkers")
    shaded = _pixels(page.locator("#gl").screenshot())
    assert set(page.evaluate("window.lgiReview.maps")) >= {"truth", "correction"}
    for key in ("truth", "correction"):
        page.select_option("#map", key)
        coloured = _pixels(page.locator("#gl").screenshot(path=str(tmp_path / f"map_{key}.png")))
        assert np.any(np.abs(coloured - shaded) > 20, axis=2).mean() > 0.05
        # The shaded face is grey; a map paints it in the ramp's blues.
        face = np.any(np.abs(coloured - coloured[2, 2]) > 12, axis=2)
        assert (coloured[face][:, 2] - coloured[face][:, 0]).mean() > 20
        assert page.is_visible("#colourbar") and "mm" in page.locator("#cbar").get_attribute("title")


def test_marker_status_colour_matches_the_diagnostics(page, shot, tmp_path):
    diag = pd.read_csv(shot / "rec" / "diagnostics.csv", keep_default_na=False)
    frames = sorted(diag.frame.unique())
    markers = page.evaluate("window.lgiReview && window.LGI_REVIEW_META.markers")
    checked = set()
    for frame_pos in (0, 10, 19):
        page.evaluate(f"window.lgiReview.setFrame({frame_pos})")
        rows = diag[diag.frame == frames[frame_pos]].set_index("marker")
        screen = np.array([page.evaluate(f"window.lgiReview.markerScreen({m})") for m in range(len(markers))])
        img = _pixels(page.locator("#gl").screenshot(path=str(tmp_path / f"markers_{frame_pos}.png")))
        got, roomy = check_marker_colours(img, screen, rows, markers,
                                          lambda s: page.evaluate(f"window.lgiReview.statusColour('{s}')"))
        checked |= got
    assert {"missing", "fitted"} <= checked or len(checked) >= 2, checked
    # Hovering a marker shows its name and its diagnostics row.
    m = int(roomy[0])
    x, y = page.evaluate(f"window.lgiReview.markerScreen({m})")
    box = page.locator("#gl").bounding_box()
    page.mouse.move(box["x"] + x, box["y"] + y)
    text = page.inner_text("#marker")
    assert markers[m] in text and "residual_mm" in text and rows.loc[markers[m], "status"] in text


def test_clicking_a_curve_jumps_to_its_frame(page):
    box = page.locator("#curves").bounding_box()
    page.mouse.click(box["x"] + box["width"] - 8, box["y"] + box["height"] / 2)
    assert page.evaluate("window.lgiReview.frame()") == 19
    page.click("#back")
    assert page.evaluate("window.lgiReview.frame()") == 18


def test_frames_in_blocks_show_the_same_picture(browser, shot, monkeypatch, tmp_path):
    """A shot longer than a block is loaded block by block; frame 19 from blocks of 3 frames is the same
    picture as from lgi's blocks."""
    import lgi.jobs.review as job

    assert job.BLOCK != 3
    monkeypatch.setattr(job, "BLOCK", 3)
    job.review(shot / "rec", shot / "idx", tmp_path / "blocks", job.ReviewOptions(truth=str(shot / "s" / "truth.npz")))
    shots = []
    for folder in (shot / "page", tmp_path / "blocks"):
        pg = browser.new_page(viewport={"width": 900, "height": 600}, device_scale_factor=1, bypass_csp=True)
        pg.goto((folder / "index.html").resolve().as_uri())
        pg.wait_for_function("window.lgiReview && (window.lgiReview.idle || window.lgiReview.error)",
                             timeout=60_000)
        assert pg.evaluate("window.lgiReview.error") is None
        pg.evaluate("window.lgiReview.setFrame(19).then(() => window.lgiReview.setMap('truth'))")
        shots.append(_pixels(pg.locator("#gl").screenshot()))
        pg.close()
    assert np.abs(shots[0] - shots[1]).max() <= 2


def _open(browser, folder: Path):
    pg = browser.new_page(viewport={"width": 900, "height": 600}, device_scale_factor=1, bypass_csp=True)
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    pg.goto((folder / "index.html").resolve().as_uri())
    pg.wait_for_function("window.lgiReview && (window.lgiReview.idle || window.lgiReview.error)", timeout=60_000)
    pg.errors = errors
    return pg


def test_a_block_file_loads_on_its_own(browser, small_blocks):
    """A block file is a page of its own: opened alone, it puts its block in window.LGI_REVIEW_BLOCKS (framed by
    the review page, it hands the block over instead); its data is JSON the browser does not run."""
    pg = browser.new_page(bypass_csp=True)
    pg.goto((small_blocks / "frames" / "block_00001.html").resolve().as_uri())
    got = pg.evaluate("[Object.keys(window.LGI_REVIEW_BLOCKS), window.LGI_REVIEW_BLOCKS[1].lo, "
                      "window.LGI_REVIEW_BLOCKS[1].n, Object.keys(window.LGI_REVIEW_BLOCKS[1].maps)]")
    assert got == [["1"], 6, 6, ["truth", "correction"]]
    pg.close()


def test_a_far_frame_shows_the_overview_then_the_full_frame(browser, shot, monkeypatch, tmp_path):
    """The page loads the blocks around the cursor only. A jump to a frame whose block is not loaded draws the
    overview's nearest frame at once, then the full frame when its block arrives (the same picture as a page that
    had it from the start); far blocks are dropped, so the page holds a bounded number however long the shot."""
    import lgi.jobs.review as job

    monkeypatch.setattr(job, "BLOCK", 1)  # 20 blocks of 1 frame
    job.review(shot / "rec", shot / "idx", tmp_path / "page", job.ReviewOptions())
    pg = _open(browser, tmp_path / "page")
    assert pg.evaluate("window.lgiReview.error") is None and pg.errors == []
    assert pg.evaluate("window.lgiReview.blocksHeld()") == [0, 1, 2, 3, 4]  # the cursor's and four ahead
    pg.uncheck("#showMarkers")
    first = pg.evaluate("""async () => { const p = window.lgiReview.setFrame(15); const at = window.lgiReview.shown();
        const rough = window.lgiReview.positions(); await p;
        return [at, window.lgiReview.shown(), rough]; }""")
    assert first[0] == {"frame": 15, "at": 16, "exact": False} and first[1] == {"frame": 15, "at": 15, "exact": True}
    assert "~" not in pg.inner_text("#frameLabel")
    full = _pixels(pg.locator("#gl").screenshot())
    pg.evaluate("window.lgiReview.setFrame(16)")
    assert np.allclose(first[2], pg.evaluate("window.lgiReview.positions()"))  # the rough mesh was frame 16's
    # Step through the whole shot: never more than 12 blocks held.
    held = [len(pg.evaluate(f"window.lgiReview.setFrame({f}).then(() => window.lgiReview.blocksHeld())"))
            for f in range(20)]
    assert max(held) <= 12 and pg.evaluate("window.lgiReview.blocksHeld()")[0] > 0
    pg.close()
    other = _open(browser, shot / "page")  # frame 15 in its first block: there from the start
    other.uncheck("#showMarkers")
    other.evaluate("window.lgiReview.setFrame(15)")
    assert np.abs(_pixels(other.locator("#gl").screenshot()).astype(int) - full).max() <= 2
    other.close()


def test_scan_map_in_the_browser(browser, scanned, tmp_path):
    """On a frame with a scan the scan map paints the face: covered vertices in the ramp's colour of their
    distance, uncovered ones (the scan's hole) in the gap colour, those outside the compared region as the shaded
    skin; the note names the scan. On a frame without one the picture is the shaded face and the note says there
    is no scan for the frame."""
    from lgi.review.pack import NOT_COVERED, TOP_WITH_GAPS

    t = scanned
    pg = browser.new_page(viewport={"width": 1000, "height": 700}, device_scale_factor=1, bypass_csp=True)
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto((t / "page_scans" / "index.html").resolve().as_uri())
    pg.wait_for_function("window.lgiReview && (window.lgiReview.idle || window.lgiReview.error)",
                         timeout=60_000)
    assert pg.evaluate("window.lgiReview.error") is None and errors == []
    pg.uncheck("#showMarkers")
    assert "scan" in pg.evaluate("window.lgiReview.maps")
    assert pg.evaluate("window.lgiReview.marked()") == [list(SCANNED)]
    pos = SCANNED[0]
    pg.evaluate(f"window.lgiReview.setFrame({pos})")
    shaded = _pixels(pg.locator("#gl").screenshot())
    pg.select_option("#map", "scan")
    coloured = _pixels(pg.locator("#gl").screenshot(path=str(tmp_path / "scan_map.png")))
    assert np.any(np.abs(coloured - shaded) > 20, axis=2).mean() > 0.05
    assert "take_5.obj" in pg.evaluate("window.lgiReview.mapNote()") and pg.is_visible("#cbar")
    frame = _payload(t / "page_scans" / "review_meta.js")["frames"][pos]
    rows = pd.read_parquet(t / "compare" / "vertex_distances.parquet").query("frame == @frame")
    m = next(mp for mp in _payload(t / "page_scans" / "review_frames.js")["maps"] if mp["key"] == "scan")
    codes = unblob(m["values"])[0]
    shade = [0.78, 0.74, 0.70]
    gap = pg.evaluate(f"window.lgiReview.gapColour({NOT_COVERED})")
    cov = rows[rows.covered].vertex.to_numpy()[::97]
    for v in cov:
        want = pg.evaluate(f"window.lgiReview.rampColour({codes[v] / TOP_WITH_GAPS})")
        assert np.allclose(pg.evaluate(f"window.lgiReview.vertexColour({v})"), want, atol=1e-5)
    for v in rows[~rows.covered].vertex.to_numpy()[:20]:
        assert np.allclose(pg.evaluate(f"window.lgiReview.vertexColour({v})"), gap, atol=1e-5)
    # The gap colour is none of the ramp's: a hole never reads as a distance.
    ramp = np.array([pg.evaluate(f"window.lgiReview.rampColour({k / 50})") for k in range(51)])
    assert np.abs(ramp - gap).max(axis=1).min() > 0.1
    outside = np.setdiff1d(np.arange(codes.size), rows.vertex.to_numpy())[:20]
    for v in outside:
        assert np.allclose(pg.evaluate(f"window.lgiReview.vertexColour({v})"), shade, atol=1e-5)
    # A frame without a scan: no map colours, and the note says so.
    pg.evaluate("window.lgiReview.setFrame(0)")
    note = pg.evaluate("window.lgiReview.mapNote()")
    assert "no scan for frame" in note and str(frame) in note and not pg.is_visible("#cbar")
    for v in cov:
        assert np.allclose(pg.evaluate(f"window.lgiReview.vertexColour({v})"), shade, atol=1e-5)
    pg.screenshot(path=str(tmp_path / "no_scan_page.png"))
    # The picture alone (the colour bar's box with the note lies over the canvas).
    pg.evaluate("document.getElementById('colourbar').style.visibility = 'hidden'")
    scan_at_0 = _pixels(pg.locator("#gl").screenshot())
    pg.select_option("#map", "none")
    assert np.abs(scan_at_0 - _pixels(pg.locator("#gl").screenshot())).max() <= 2
    pg.close()


@pytest.fixture(scope="module")
def hostile(tmp_path_factory) -> dict:
    return hostile_page(tmp_path_factory.mktemp("hostile"))


# An inline handler added to the page after it loaded: the page's policy forbids it, whatever put it there.
INJECTED = """new Promise((done) => {
  document.body.insertAdjacentHTML("beforeend", '<img src="data:," onload="window.__injected = 1">');
  setTimeout(() => done(window.__injected === undefined ? null : window.__injected), 500);
})"""


def test_names_in_the_data_run_no_script(browser, hostile):
    # The page's policy on (the other tests bypass it: it forbids the eval of Playwright's wait_for_function).
    pg = browser.new_page()
    violations: list[str] = []
    pg.on("console", lambda m: violations.append(m.text) if "Content Security Policy" in m.text else None)
    pg.goto(hostile["page"].resolve().as_uri())
    pg.evaluate("""new Promise((done) => { const poll = () => { const a = window.lgiReview;
      if (a && (a.idle || a.error)) done(); else setTimeout(poll, 20); }; poll(); })""")
    assert pg.evaluate("window.lgiReview.error") is None
    check_nothing_ran(pg.evaluate(SHOW_HOSTILE), hostile)
    assert not violations  # the names were text: nothing even tried to run
    assert pg.evaluate(INJECTED) is None and violations  # and markup that did get in would not run
    pg.close()
