"""Actor-specific rigs from a template (LGI 7.7, ``lgi rig-generate``) against the naive transfer.

    python benchmarks/bench_rig.py [--vertices 20000] [--actors 1 2 3] [--no-ict]

Synthetic: the template is the default synthetic actor's rig: its 13 controls at 1 and, for the correctives,
its own combination shapes of the pairs ``--correctives auto`` picks (a template with correctives; a row also
gives a linear template, whose combinations are sums of the parts). The actor is another synthetic actor
(``lgi synth --actor SEED``: other proportions, nose, cheekbones, fold, creases, smile path), its index built
from its own 47-shape dataset with its true jaw rig. Truth: the actor's own shapes at the same activations.
Errors are vertex distances over the whole mesh, mm; "pooled" is the RMS over all shapes of a kind.

Methods, all given the same template shapes and the actor's index (its neutral, markers, jaw rig):
- naive: the template's displacement added to the actor's neutral (the baseline);
- transfer, no LGI: the displacement mapped by the neutrals' affine map and the jaw moved by its parameters
  through the actor's rig, whole mesh: everything ``lgi rig-generate`` does except LGI (the strongest baseline
  with the same information);
- LGI add / LGI scale: ``lgi rig-generate --transfer add|scale`` with the defaults ``--fit 0.5`` (the actor's
  shapes fitted to the transferred bundles) and ``--coverage 2`` (a combination whose bundles lie over 2 mm
  outside the actor's clouds takes the template's corrective, transferred); then ``--fit 0`` (the paper's
  exact interpolation) and ``--coverage inf`` (every combination reconstructed).

ICT (``../shared/data/ict-facekit``): the template is the generic ICT face (its performed expression shapes),
the actor ICT with an identity blend (``lgi import --identity``), 108 markers (data/markers_ict.csv), no jaw rig.
ICT's expressions are identity-independent (an additive model), so the actor's truth IS the naive transfer
here; the figures say what LGI loses by reconstructing from the markers, and what scaling does to a face whose
expressions do not scale. With the actor's index built from all its shapes, every control is a dataset shape
and LGI returns it exactly (paper 7.1: a setup that favours LGI); the second index leaves out the right-side
shapes (``*_R``), and the ``*_R`` controls are generated from the others.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.square(e), axis=-1)))) * 10.0


def pooled(x: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x else float("nan")


def synthetic(n_vertices: int, seed: int) -> list[str]:
    from lgi.index.build import build_index
    from lgi.retarget.template import TemplateTransfer, parse_correctives
    from lgi.solve.solver import LGISolver
    from lgi.synthetic import actor as A

    eye = np.eye(len(A.CONTROLS))
    tmpl_actor = A.make_actor(n_vertices)
    act = A.make_actor(n_vertices, A.ActorVariant.draw(seed))
    ds = A.make_dataset(act)
    layout, _ = A.default_layout(act)
    index, _ = build_index(ds, layout, show_progress=False, jaw_rig=A.jaw_rig(act))
    solver = LGISolver(index)
    controls = list(A.CONTROLS)
    linear = A.make_dataset(tmpl_actor, controls, eye)
    pairs = parse_correctives("auto", TemplateTransfer(linear, solver), controls)
    combos = np.stack([sum(eye[A.C[c]] for c in p) for p in pairs])
    with_corr = A.make_dataset(tmpl_actor, [*controls, *("+".join(p) for p in pairs)], np.vstack([eye, combos]))
    x0 = act.neutral
    truth_c = [act.evaluate(eye[k]) for k in range(len(controls))]
    truth_p = [act.evaluate(a) for a in combos]
    true_corr = [tp - x0 - sum(truth_c[A.C[c]] - x0 for c in p) for tp, p in zip(truth_p, pairs, strict=True)]
    rows = []
    for label, template in (("template with correctives", with_corr), ("linear template", linear)):
        methods = {}
        for transfer, coverage, fit in (("add", 2.0, 0.5), ("scale", 2.0, 0.5), ("scale", 2.0, 0.0),
                                        ("scale", np.inf, 0.5)):
            tt = TemplateTransfer(template, solver, transfer, coverage, fit)
            t0 = time.perf_counter()
            rig = tt.generate(controls, pairs)
            secs = time.perf_counter() - t0
            name = f"LGI {transfer}" + ("" if coverage == 2.0 else f", coverage {coverage:g} mm") + \
                ("" if fit == 0.5 else ", interpolated (fit 0)")
            n_t = rig.corrective_source.count("template")
            methods[name] = ([*rig.shapes], [*rig.combinations], [*rig.corrective_deltas], secs, n_t)
            if transfer == "scale":
                nc = [tt.transferred((c,)) for c in controls]
                npairs = [tt.transferred(p) for p in pairs]
                methods["transfer, no LGI"] = (nc, npairs, [q - x0 - sum(nc[A.C[c]] - x0 for c in p)
                                                            for q, p in zip(npairs, pairs, strict=True)], 0.0, 0)
                nv = [tt.naive((c,)) for c in controls]
                nvp = [tt.naive(p) for p in pairs]
                methods["naive"] = (nv, nvp, [q - x0 - sum(nv[A.C[c]] - x0 for c in p)
                                              for q, p in zip(nvp, pairs, strict=True)], 0.0, 0)
        order = ["naive", "transfer, no LGI", *(k for k in methods if k.startswith("LGI"))]
        for name in order:
            sc, sp, corr, secs, n_t = methods[name]
            ec = [rms(s - t) for s, t in zip(sc, truth_c, strict=True)]
            mc = max(float(np.linalg.norm(s - t, axis=1).max()) * 10 for s, t in zip(sc, truth_c, strict=True))
            ep = [rms(s - t) for s, t in zip(sp, truth_p, strict=True)]
            ek = [rms(c - t) for c, t in zip(corr, true_corr, strict=True)]
            if label == "linear template" and name in ("naive", "transfer, no LGI"):
                continue  # their controls are the same as above; only the combinations differ
            rows.append(f"| {seed} | {label} | {name} | {pooled(ec):.3f} / {mc:.2f} | {pooled(ep):.3f} | "
                        f"{pooled(ec + ep):.3f} | {pooled(ek):.3f} | {n_t} of {len(pairs)} | {secs:.1f} |")
    size = pooled([rms(c) for c in true_corr])
    rows.append(f"| {seed} | | (true correctives' own size) | | | | {size:.3f} | | |")
    return rows


def ict(ict_dir) -> list[str]:
    from common import ICT_NOT_PERFORMED, ict_layout

    from lgi.dataset.importing import import_obj_folder
    from lgi.index.build import build_index
    from lgi.retarget.template import TemplateTransfer
    from lgi.solve.solver import LGISolver

    template = import_obj_folder(ict_dir, rigid_vertices="none", show_progress=False)
    weights = {"identity000": 1.5, "identity003": -1.0, "identity004": 1.0}
    actor = import_obj_folder(ict_dir, rigid_vertices="none", show_progress=False, identity_weights=weights)
    layout = ict_layout(actor.triangles)
    t0 = time.perf_counter()
    index, _ = build_index(actor, layout, show_progress=False)
    build_s = time.perf_counter() - t0
    solver = LGISolver(index)
    controls = [n for n in template.names if n not in ICT_NOT_PERFORMED]
    face = np.zeros(actor.n_vertices, bool)
    from common import ICT_FACE_VERTICES

    face[:ICT_FACE_VERTICES] = True
    rows = []
    truth = {c: actor.neutral + actor.deltas[actor.index(c)] for c in controls}
    change = rms((actor.neutral - template.neutral)[face])
    held = [c for c in controls if c.endswith("_R")]
    index_l, _ = build_index(actor.select(exclude="*_R"), layout, show_progress=False)
    for label, slv, ctrl in (("all shapes", solver, controls),
                             ("without the *_R shapes; the *_R controls", LGISolver(index_l), held)):
        for name in ("naive", "LGI add", "LGI scale"):
            tt = TemplateTransfer(template, slv, "add" if name != "LGI scale" else "scale")
            out = [tt.naive((c,)) for c in ctrl] if name == "naive" else list(tt.generate(ctrl).shapes)
            e = [rms((s - truth[c])[face]) for s, c in zip(out, ctrl, strict=True)]
            m = max(float(np.linalg.norm((s - truth[c])[face], axis=1).max()) * 10 for s, c in zip(out, ctrl,
                                                                                                strict=True))
            rows.append(f"| {label} | {name} | {pooled(e):.3f} / {m:.2f} | {len(ctrl)} |")
    rows.append(f"(actor: identity {weights}, which moves the neutral {change:.2f} mm RMS over the face; index built "
                f"in {build_s:.0f} s)")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vertices", type=int, default=20000)
    ap.add_argument("--actors", type=int, nargs="*", default=[1, 2, 3], help="synthetic actors (none: ICT only)")
    ap.add_argument("--no-ict", action="store_true")
    args = ap.parse_args()
    print(f"synthetic: template = default actor, actor = lgi synth --actor SEED, {args.vertices} vertices; "
          "vertex error against the actor's true shapes, mm\n")
    print("| actor | template | method | controls: pooled RMS / max | combinations: pooled RMS | all shapes: pooled "
          "RMS | correctives: pooled RMS error | correctives from the template | generation s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for seed in args.actors:
        for row in synthetic(args.vertices, seed):
            print(row, flush=True)
    if args.no_ict:
        return
    from common import ict_dir_or_none

    d = ict_dir_or_none()
    if d is None:
        print("\nICT: skipped (ICT FaceKit not found under ../shared/data/ict-facekit)")
        return
    print("\nICT: face vertices, mm (the actor's truth equals the naive transfer here: ICT's expressions are "
          "identity-independent)\n")
    print("| actor's index | method | controls: pooled RMS / max | controls |")
    print("|---|---|---|---|")
    for row in ict(d):
        print(row, flush=True)


if __name__ == "__main__":
    main()
