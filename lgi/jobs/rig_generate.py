"""``lgi rig-generate``: an actor-specific blendshape rig from a template rig and the actor's index (paper 7.7).

The algorithm is :mod:`lgi.retarget.template`; this job reads the inputs, checks the outputs before the work,
and writes a shape dataset (controls and correctives, tagged) and optionally a UsdSkel rig.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lgi.errors import InputError
from lgi.export.convention import convention_option
from lgi.options import declared, option

log = logging.getLogger(__name__)


#: A corrective whose largest displacement is under this (mm) is left out of the rig.
ZERO_CORRECTIVE_MM = 1e-3


@declared
@dataclass(frozen=True)
class RigGenerateOptions:
    """Options of ``lgi rig-generate`` (:mod:`lgi.options`); the rig dataset stays in lgi's convention, the USD
    rig takes ``dcc``, ``up_axis`` and ``units``."""

    controls: str | None = option(
        None, "template shapes to use as controls (shell patterns; default: every name without '+' that is not an "
        "in-between (NAME_50 beside NAME, or tagged inbetween) or a combination (tagged so))", group="inputs",
        metavar="PATTERN")
    correctives: str | None = option(
        None, "combinations a+b[+c] (comma-separated) or 'auto' (the template's combination shapes, or else up to "
        "24 pairs moving the same markers); the template's combination shape (its parts in any order) is used when "
        "it has one, else the sum of the parts (default: none)", group="inputs", metavar="PAIRS|auto")
    transfer: str = option(
        "scale", "template displacements scaled by the affine map between the neutrals, or added (default "
        "%(default)s)", group="method", choices=("scale", "add"))
    coverage_mm: float = option(
        2.0, "a combination whose bundles lie farther than this outside the actor's dataset takes the template's "
        "corrective, transferred, and is reported, mm (default %(default)s; inf: always reconstruct)",
        group="method", metavar="MM", name="--coverage", units="mm")
    fit_mm: float = option(
        0.5, "fit the actor's shapes to the transferred bundles as measurements with this noise, mm, so the "
        "template's own detail at the markers is not copied (default %(default)s; 0: interpolate exactly)",
        group="method", metavar="MM", name="--fit", units="mm")
    dcc: str | None = convention_option("dcc", "the written geometry", "outputs")
    up_axis: str | None = convention_option("up_axis", "the written geometry", "outputs")
    units: str | None = convention_option("units", "the written geometry", "outputs")

    @property
    def convention(self):
        """The scene convention of the rig's USD (``dcc`` preset, ``up_axis`` and ``units`` over it)."""
        from lgi.export.convention import Convention

        return Convention.of(self.dcc, self.up_axis, self.units)

    def __post_init__(self) -> None:
        import math

        from lgi.retarget.template import TRANSFERS

        self.convention  # noqa: B018 - checks the values

        if self.transfer not in TRANSFERS:
            raise InputError(f"--transfer {self.transfer!r}: use one of {', '.join(TRANSFERS)}")
        if math.isnan(self.coverage_mm) or self.coverage_mm < 0:
            raise InputError(f"--coverage must be a distance >= 0 in mm (inf: always reconstruct), not "
                             f"{self.coverage_mm!r}")
        if not math.isfinite(self.fit_mm) or self.fit_mm < 0:
            raise InputError(f"--fit must be a finite distance >= 0 in mm (0: interpolate exactly), not "
                             f"{self.fit_mm!r}")


def generate_rig(template_dir: str | Path, index_dir: str | Path, out: str | Path,
                 options: RigGenerateOptions | None = None, usd: str | Path | None = None,
                 show_progress: bool = False) -> dict[str, Any]:
    """Generate the actor's rig; returns a summary (:func:`rig_generate_report`)."""
    from lgi.dataset.shapes import ShapeDataset
    from lgi.export.blender import for_blender, write_blender_script
    from lgi.index.build import LGIIndex
    from lgi.progress import progress
    from lgi.retarget.template import (
        TemplateTransfer,
        parse_correctives,
        select_controls,
        template_combinations,
    )
    from lgi.solve.solver import LGISolver

    o = options or RigGenerateOptions()
    _check_outputs(template_dir, index_dir, out, usd, o)
    t0 = time.perf_counter()
    template = ShapeDataset.load(template_dir)
    index = LGIIndex.load(index_dir)
    transfer = TemplateTransfer(template, LGISolver(index), o.transfer, o.coverage_mm, o.fit_mm)
    controls = select_controls(template.names, o.controls, [m.tags for m in template.shape_meta])
    if not o.controls:
        skipped = [n for n in template.names if "+" not in n and n not in controls]
        if skipped:
            log.info("template shapes that are in-betweens or combinations, not controls (name them in --controls "
                     "to use them): %s", ", ".join(skipped))
    if not controls:
        raise InputError(f"no template shape is a control (patterns {o.controls!r}; shapes whose name has '+' "
                         "are combinations)", path=template_dir)
    correctives = parse_correctives(o.correctives, transfer, controls)
    own = template_combinations(template.names, controls)
    if own and not correctives:
        log.warning("the template has %d combination shapes (%s) but no corrective was asked for: pass "
                    "--correctives auto to generate them", len(own), ", ".join("+".join(c) for c in own[:4]))
    names = [*controls, *("+".join(p) for p in correctives)]
    if usd is not None:
        from lgi.export.formats import usd_name

        tokens = [usd_name(n) for n in names]
        clash = sorted({n for n, t in zip(names, tokens, strict=True) if tokens.count(t) > 1})
        if clash:
            raise InputError(f"shape names {', '.join(map(repr, clash))} become the same USD name; rename them in the "
                             "template", path=template_dir)
    if transfer.rig is None:
        log.warning("the actor's index has no jaw rig: the jaw moves as marker displacements (a template's jaw "
                    "rotation lands off the actor's hinge); build the index with --jaw-rig for a jaw transfer")
    rig = transfer.generate(controls, correctives,
                            progress=lambda it: progress(it, "generating", disable=not show_progress))

    a = index.arrays
    # An index may be stored without its faces; the template shares the actor's topology (checked).
    faces = a if "face_vertices" in a else {"face_vertices": template.face_vertices,
                                             "face_offsets": template.face_offsets, "uvs": template.uvs,
                                             "face_uvs": template.face_uvs}
    neutral = rig.neutral
    jaw = transfer.rig
    if jaw is None:
        deltas = np.concatenate([rig.shapes - neutral[None].astype(np.float32),
                                 rig.corrective_deltas]).astype(np.float32)
    else:
        # The jaw becomes the rig's joint: a UsdSkel user opens the jaw by rotating it, and a jaw control's
        # blend shape keeps only what the rotation does not do (the lips' stretch, the chin's bulge). The shapes
        # are stored unskinned (the jaw closed), as the index stores them, and the joint skins them with the
        # jaw rig's weights; a control's own jaw pose is kept in its metadata ("jaw").
        deltas = np.concatenate(rig.unskinned(jaw)).astype(np.float32)
    meta = _shape_meta(names, len(controls), correctives, transfer, rig, o.transfer, Path(template_dir).name)
    # A corrective that moves nothing (the sum of its controls is already the shape) would be one more target
    # and one more curve in every DCC for nothing: it is left out, and said so.
    size_mm = np.linalg.norm(rig.corrective_deltas, axis=2).max(axis=1) * 10 if correctives else np.zeros(0)
    keep_c = size_mm >= ZERO_CORRECTIVE_MM
    if not keep_c.all():
        log.warning("%d corrective%s left out: %s move%s no vertex by %g mm or more (the sum of the controls is "
                    "already the shape)", int((~keep_c).sum()), "s" if (~keep_c).sum() > 1 else "",
                    ", ".join("+".join(c) for c, k in zip(correctives, keep_c, strict=True) if not k),
                    "" if (~keep_c).sum() > 1 else "s", ZERO_CORRECTIVE_MM)
        keep = np.r_[np.ones(len(controls), bool), keep_c]
        names = [n for n, k in zip(names, keep, strict=True) if k]
        meta = [m for m, k in zip(meta, keep, strict=True) if k]
        deltas = deltas[keep]
        correctives = [c for c, k in zip(correctives, keep_c, strict=True) if k]
    uvs = faces.get("uvs") if "uvs" in faces else None
    face_uvs = faces.get("face_uvs") if "face_uvs" in faces else None
    ds = ShapeDataset(neutral=neutral, deltas=deltas, names=names, face_vertices=np.asarray(faces["face_vertices"]),
                      face_offsets=np.asarray(faces["face_offsets"]),
                      uvs=None if uvs is None else np.asarray(uvs), face_uvs=None if face_uvs is None else
                      np.asarray(face_uvs), units="cm", shape_meta=meta,
                      info={"name": "actor-rig", "template": str(Path(template_dir).resolve()),
                            "index": str(Path(index_dir).resolve()), "transfer": o.transfer,
                            "controls": controls, "correctives": ["+".join(p) for p in correctives],
                            "jaw": "none" if jaw is None else "joint: shapes unskinned, jaw parameters "
                                   "(open_deg, yaw_deg, roll_deg, forward_cm) per shape in its metadata"},
                      jaw_pivot=None if jaw is None else jaw.pivot, jaw_weights=None if jaw is None else jaw.weights)
    existed = Path(out).exists()
    ds.save(out)
    if usd is not None:
        from lgi.export.formats import write_usd_rig

        try:
            write_usd_rig(usd, neutral, ds.face_vertices, ds.face_offsets, names, deltas,
                          [None] * len(controls) + list(correctives), ds.uvs, ds.face_uvs, jaw_rig=jaw,
                          jaw_parameters=None if rig.jaw is None else rig.jaw[np.r_[np.ones(len(controls), bool),
                                                                                      keep_c]],
                          convention=o.convention)
            if for_blender(o.convention):
                from lgi.export.formats import usd_name

                script = write_blender_script(usd, 30.0, 0, 0, {usd_name("+".join(c)): [usd_name(n) for n in c]
                                                                for c in correctives})
        except BaseException:
            if not existed:  # a run that fails leaves nothing of itself behind
                import shutil

                shutil.rmtree(out, ignore_errors=True)
            raise
    sources = [src for src, k in zip(rig.corrective_source, keep_c, strict=True) if k]
    return {"path": str(Path(out).resolve()), "usd": None if usd is None else str(Path(usd).resolve()),
            "blender_script": str(script.resolve()) if usd is not None and for_blender(o.convention) else None,
            "controls": len(controls), "correctives": ["+".join(p) for p in correctives],
            "controls_outside": [c for c, d in zip(controls, rig.projection_mm, strict=False) if d > o.coverage_mm],
            "corrective_max_mm": size_mm[keep_c].tolist(), "correctives_left_out": int((~keep_c).sum()),
            "residual_max_mm": float(rig.residual_mm.max(initial=0.0)),
            "correctives_from_template": [n for n, src in zip(("+".join(p) for p in correctives), sources, strict=True)
                                          if src == "template"],
            "jaw": transfer.rig is not None, "transfer": o.transfer, "fit_mm": o.fit_mm,
            "seconds": time.perf_counter() - t0}


def _check_outputs(template_dir: str | Path, index_dir: str | Path, out: str | Path, usd: str | Path | None,
                   o: RigGenerateOptions) -> None:
    """Refuse, before the work, outputs that cannot be written: the rig's dataset folder and USD file."""
    from lgi.dataset.shapes import ENTRIES as DATASET_ENTRIES
    from lgi.export.blender import for_blender, script_path
    from lgi.index.build import ENTRIES as INDEX_ENTRIES
    from lgi.io.atomic import check_output, files_in

    inputs = [template_dir, index_dir, *files_in(template_dir, DATASET_ENTRIES), *files_in(index_dir, INDEX_ENTRIES)]
    check_output(out, "dir", inputs=inputs, owned=DATASET_ENTRIES, what="shape dataset")
    if usd is None:
        return
    if Path(usd).suffix not in (".usd", ".usda", ".usdc"):
        raise InputError("the rig's USD file must end in .usd, .usda or .usdc", path=usd)
    check_output(usd, "file", inputs=[*inputs, out])
    if for_blender(o.convention):
        check_output(script_path(usd), "file", inputs=[*inputs, out])
    if Path(out).resolve() in Path(usd).resolve().parents:
        raise InputError("the rig's USD file cannot be inside the rig's dataset directory (which is replaced whole)",
                         path=usd)


def _shape_meta(names: list[str], n_controls: int, correctives: list[tuple[str, ...]], transfer, rig, how: str,
                template: str) -> list:
    """Each generated shape's metadata: where it came from, how well it fits, its jaw pose, and for a corrective
    its combination and source."""
    from lgi.dataset.shapes import ShapeMeta

    meta = []
    for i, name in enumerate(names):
        combo = None if i < n_controls else list(correctives[i - n_controls])
        shape = transfer.template_shape(tuple(combo)) if combo else None
        from_template = f"combination shape {shape}" if shape else "sum of parts"
        meta.append(ShapeMeta(
            source=f"lgi rig-generate: template {template}/{name}",
            tags=["control"] if combo is None else ["corrective", "combination"],
            extra={"residual_mm": round(float(rig.residual_mm[i]), 6), "transfer": how,
                   "outside_clouds_mm": round(float(rig.projection_mm[i]), 4),
                   **({} if rig.jaw is None else {"jaw": [round(float(v), 6) for v in rig.jaw[i]]}),
                   **({} if combo is None else {
                       "combination": combo, "template": from_template, "driver": "product of the controls' weights",
                       "corrective_from": rig.corrective_source[i - n_controls]})}))
    return meta


def rig_generate_report(s: dict[str, Any]) -> list[str]:
    lines = [f"actor rig: {s['controls']} controls, {len(s['correctives'])} correctives "
             f"({'jaw as the rig joint' if s['jaw'] else 'no jaw rig: one fixed joint'}, transfer {s['transfer']}, "
             f"{'fitted with ' + format(s['fit_mm'], 'g') + ' mm' if s['fit_mm'] else 'interpolated'}) "
             f"in {s['seconds']:.1f} s",
             f"largest distance of a generated shape from its bundles: {s['residual_max_mm']:.2g} mm"]
    if s["controls_outside"]:
        lines.append(f"{len(s['controls_outside'])} of {s['controls']} controls lie over the coverage distance outside "
                     "the actor's dataset (they come out short of the template's motion): "
                     + ", ".join(s["controls_outside"]))
    if s.get("correctives_left_out"):
        lines.append(f"{s['correctives_left_out']} corrective(s) left out: they move no vertex by "
                     f"{ZERO_CORRECTIVE_MM:g} mm or more")
    if s["correctives_from_template"]:
        lines.append(f"{len(s['correctives_from_template'])} of {len(s['correctives'])} correctives are the "
                     "template's, transferred (the actor's dataset does not cover them): "
                     + ", ".join(s["correctives_from_template"]))
    if s["correctives"]:
        top = sorted(zip(s["corrective_max_mm"], s["correctives"], strict=True), reverse=True)[:5]
        lines.append("largest correctives (max mm): " + ", ".join(f"{n} {m:.2f}" for m, n in top))
    lines.append(f"dataset: {s['path']}" + (f"  usd: {s['usd']}" if s["usd"] else "")
                 + (f"  Blender: run {s['blender_script']}" if s.get("blender_script") else ""))
    return lines
