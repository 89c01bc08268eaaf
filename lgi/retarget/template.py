"""Actor-specific rigs from a generic template rig (LGI paper 7.7).

A template rig is a set of shapes (controls) on a template neutral with the actor's mesh topology. The
paper applies the template rig to the actor's neutral, evaluates the bundles of each control (and of
combinations of controls, for correctives), and reconstructs them with LGI on the actor: the actor's
dataset supplies what the actor's face does between the markers, so the generated shape is the actor's
local geometry passing through the template's marker motion.

How the template's motion reaches the actor's markers (``transfer``):

* ``"add"``: the template's displacement at each marker is added to the actor's neutral marker
  position: "the template rig applied to the actor's neutral" taken literally (without a jaw rig, the
  naive transfer of whole meshes it is compared with, sampled at the markers).
* ``"scale"``: the displacement is first mapped by the linear part ``A`` of the affine map fitted (least
  squares, all vertices) from the template neutral to the actor's. A face 10 % wider smiles about 10 %
  wider; a global affine map is the simplest deformation transfer that says so.

The jaw (when the actor's index has a jaw rig) is transferred as jaw parameters, not as marker
displacements: a rotation about the template's hinge, added to markers that sit elsewhere relative to the
actor's hinge, is no rotation of the actor's jaw (on the second synthetic actor it left 1.7 mm RMS on a
full jaw opening). The template's rig is the actor's, carried back: the same skinning weights (the
topology is shared) and the actor's hinge mapped through the inverse of the fitted affine map. Each
template shape's jaw parameters are fitted with it, its unskinned displacement is transferred to the
actor's markers as above, and the actor's rig skins them with the same parameters; the solve is then
given that jaw. The angles carry over as they are; the forward slide (cm) is not scaled by the affine map
(on a face 10 % larger it comes out about 10 % short).

Fitted, not interpolated (``fit_mm``): the template's displacements at the markers are not measurements of
the actor; they carry the template's own detail (its forehead creases at the template's spacing, sampled
wherever a marker sits). Interpolating them exactly puts that detail into the actor's shape. By default they
are treated as measurements with ``fit_mm`` of noise (the solver's noise model): the actor's shapes are fitted
to them, so the actor's own detail comes through. On the second synthetic actor (20,000 vertices) this took
the controls' error from 0.087 to 0.054 mm RMS (a brow raise from 0.19 to under 0.01); ``fit_mm=0`` is the
paper's exact interpolation.

Coverage: LGI blends the actor's shapes, so it cannot produce a combination the actor's dataset holds
nothing like (a deeper nasolabial fold than any captured shape has). Such a combination's bundles fall
outside their clouds; when one lies farther out than ``coverage_mm``, the generated combination is the
generated parts plus the template's own corrective, transferred like the shapes, and the rig says so
(``corrective_source``, a warning). On the second synthetic actor, the combinations its dataset covers (the
jaw opening with an expression) lay at most 1.1 mm out, the others 3-7 mm.

Correctives: for a combination ``a+b[+c]`` the template's combination shape is used when the template
has it (a shape of that name), otherwise the sum of the parts' deltas (a linear template). The
reconstructed combination minus the sum of the reconstructed parts' deltas is the corrective, so the
actor's rig reproduces the reconstructed combination exactly when its controls are at 1.
"""

from __future__ import annotations

import fnmatch
import logging
from dataclasses import dataclass, field

import numpy as np

from lgi.dataset.markers import MarkerLayout
from lgi.dataset.shapes import ShapeDataset
from lgi.errors import InputError

log = logging.getLogger(__name__)

TRANSFERS = ("add", "scale")


def fit_affine(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares affine map ``dst ~ src @ A.T + b``.

    Parameters
    ----------
    src, dst : (V, 3) float, same units (cm)

    Returns
    -------
    A : (3, 3) float64; b : (3,) float64
    """
    x = np.c_[np.asarray(src, np.float64), np.ones(len(src))]
    m, *_ = np.linalg.lstsq(x, np.asarray(dst, np.float64), rcond=None)
    return m[:3].T, m[3]


def combination_parts(name: str, controls: list[str]) -> tuple[str, ...]:
    """The controls of a combination name ``a+b[+c]``; refuses unknown or repeated parts and sizes other than
    2 or 3."""
    parts = tuple(p.strip() for p in name.split("+"))
    if len(parts) not in (2, 3) or len(set(parts)) != len(parts):
        raise InputError(f"corrective {name!r}: give two or three different controls joined by '+'")
    unknown = [p for p in parts if p not in controls]
    if unknown:
        raise InputError(f"corrective {name!r}: {', '.join(map(repr, unknown))} is not among the controls (the "
                         "template's shapes without '+', narrowed by --controls)")
    return parts


def auto_correctives(deltas_at_markers: np.ndarray, controls: list[str], limit: int = 24,
                     min_overlap: float = 0.25) -> list[tuple[str, str]]:
    """Pairs of controls that move the same markers (where a linear sum of the two is most wrong).

    Parameters
    ----------
    deltas_at_markers : (K, M, 3) float
        Each control's displacement at the markers.
    controls : list of str, K names
    limit : int
        At most this many pairs, by decreasing overlap.
    min_overlap : float
        Overlap ``sum_m min(|d_a|, |d_b|) / min(sum_m |d_a|, sum_m |d_b|)`` a pair needs, in [0, 1].

    Returns
    -------
    list of (a, b) control names.
    """
    mag = np.linalg.norm(deltas_at_markers, axis=2)  # (K, M)
    tot = mag.sum(1)
    pairs = []
    for i in range(len(controls)):
        for j in range(i + 1, len(controls)):
            if tot[i] <= 0 or tot[j] <= 0:
                continue
            ov = float(np.minimum(mag[i], mag[j]).sum() / min(tot[i], tot[j]))
            a, b = deltas_at_markers[i].ravel(), deltas_at_markers[j].ravel()
            cos = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
            # An in-between of the other (parallel), or the other contains it (smile_L within smile_LR): a sum of
            # the two is no expression, so there is no corrective to make.
            small, big = (i, j) if tot[i] <= tot[j] else (j, i)
            where = mag[small] > 0.1 * mag[small].max()
            rest = np.linalg.norm(deltas_at_markers[big][where] - deltas_at_markers[small][where], axis=1).sum()
            if cos > 0.9 or rest < 0.2 * mag[small][where].sum():
                continue
            if ov >= min_overlap:
                pairs.append((ov, controls[i], controls[j]))
    pairs.sort(key=lambda p: -p[0])
    return [(a, b) for _, a, b in pairs[:limit]]


@dataclass
class GeneratedRig:
    """An actor-specific rig.

    Attributes
    ----------
    neutral : (V, 3) float64, cm
    controls : list of str, K names
    shapes : (K, V, 3) float32, cm: each control's reconstructed shape (positions)
    correctives : list of tuple of str: the combinations, each 2 or 3 control names
    corrective_deltas : (P, V, 3) float32, cm: reconstructed combination minus the sum of its parts' deltas
    combinations : (P, V, 3) float32, cm: the reconstructed combination shapes (positions)
    residual_mm : (K + P,) float64: largest distance of a generated shape from its transferred bundles (0 when
        interpolated; up to the template's own detail at a marker when fitted), mm
    projection_mm : (K + P,) float64: farthest a transferred bundle lay outside its cloud (0: all inside), mm
    corrective_source : P entries: "actor" (reconstructed with LGI) or "template" (the template's corrective,
        transferred, where the actor's dataset does not cover the combination)
    jaw : (K + P, 4) float64 or None: each shape's jaw parameters (open, yaw, roll deg; forward cm), the pose its
        LGI reconstruction was skinned with (None without a jaw rig)
    """

    neutral: np.ndarray
    controls: list[str]
    shapes: np.ndarray
    correctives: list[tuple[str, ...]] = field(default_factory=list)
    corrective_deltas: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3), np.float32))
    combinations: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3), np.float32))
    residual_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    projection_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    corrective_source: list[str] = field(default_factory=list)
    jaw: np.ndarray | None = None

    def unskinned(self, rig) -> tuple[np.ndarray, np.ndarray]:
        """The rig in the jaw-closed space of ``rig`` (:class:`lgi.solve.jaw.JawRig`), as an index stores shapes.

        Returns
        -------
        controls : (K, V, 3) float32, cm: each control's shape unskinned with its own jaw parameters, minus the
            neutral (its non-rigid part: a jaw opening's stretched lips, not its rotation)
        correctives : (P, V, 3) float32, cm: each combination unskinned with its jaw parameters, minus the
            neutral and its parts' unskinned displacements; skinned with the combination's jaw parameters, the
            controls at 1 give the combination exactly
        """
        if self.jaw is None:
            raise InputError("the rig was generated without a jaw rig")
        k = len(self.controls)
        ctrl = np.stack([rig.unskin(np.asarray(x, np.float64), th) - self.neutral
                         for x, th in zip(self.shapes, self.jaw[:k], strict=True)]) if k else \
            np.zeros((0, *self.neutral.shape))
        at = {c: i for i, c in enumerate(self.controls)}
        corr = np.zeros((len(self.correctives), *self.neutral.shape))
        for i, (combo, th) in enumerate(zip(self.correctives, self.jaw[k:], strict=True)):
            whole = rig.unskin(np.asarray(self.combinations[i], np.float64), th)
            corr[i] = whole - self.neutral - sum(ctrl[at[c]] for c in combo)
        return ctrl.astype(np.float32), corr.astype(np.float32)

    def evaluate(self, weights: dict[str, float]) -> np.ndarray:
        """(V, 3) float64: the rig at control weights (correctives driven by the product of their controls'
        weights, the usual combination-shape rule)."""
        x = self.neutral.copy()
        k = {c: i for i, c in enumerate(self.controls)}
        for c, w in weights.items():
            x += w * (self.shapes[k[c]] - self.neutral)
        for combo, d in zip(self.correctives, self.corrective_deltas, strict=True):
            x += float(np.prod([weights.get(c, 0.0) for c in combo])) * d
        return x


class TemplateTransfer:
    """Maps a template rig's shapes onto an actor's markers and reconstructs them with the actor's index.

    Parameters
    ----------
    template : ShapeDataset
        The template rig: its neutral and control shapes, on the actor's mesh topology.
    solver : LGISolver
        A solver over the actor's index.
    transfer : {"add", "scale"}
        How template displacements reach the actor's markers (module docstring).
    coverage_mm : float
        A combination whose bundles lie farther than this outside the actor's clouds takes the template's
        corrective (module docstring); ``inf`` always reconstructs.
    fit_mm : float
        Noise (mm per coordinate) the transferred bundles are fitted with; 0 interpolates them exactly.
    """

    def __init__(self, template: ShapeDataset, solver, transfer: str = "scale", coverage_mm: float = 2.0,
                 fit_mm: float = 0.5) -> None:
        if transfer not in TRANSFERS:
            raise InputError(f"unknown transfer {transfer!r}; use one of {', '.join(TRANSFERS)}")
        index = solver.index
        self.solver = solver
        self.layout: MarkerLayout = solver.layout
        self.neutral = np.asarray(index.arrays["neutral"], np.float64)
        if template.n_vertices != len(self.neutral):
            raise InputError(
                f"the template has {template.n_vertices} vertices and the actor's neutral {len(self.neutral)}: "
                "the template must be on the actor's mesh topology (wrap it onto the actor's mesh first)")
        self.template = template
        self.transfer = transfer
        self.coverage_mm = float(coverage_mm)
        self.fit_mm = float(fit_mm)
        self.fitter = solver
        if self.fit_mm > 0:
            from lgi.solve.solver import LGISolver

            # The exact solver measures coverage (how far outside the clouds); this one makes the shapes.
            self.fitter = LGISolver(index, noise=self.fit_mm)
        affine, shift = fit_affine(template.neutral, self.neutral)
        sv = np.linalg.svd(affine, compute_uv=False)
        if not np.all(np.isfinite(sv)) or sv.min() < 0.5 or sv.max() > 2.0:
            raise InputError(
                f"the template's neutral does not match the actor's: the best affine map between them scales by "
                f"{sv.min():.3g}-{sv.max():.3g} (expected about 1): other units, another orientation or another "
                "face layout?")
        self.A = np.eye(3) if transfer == "add" else affine
        self.neutral_bundles = self.layout.evaluate(self.neutral)
        self.rig = index.jaw_rig()
        self.template_rig = None
        if self.rig is not None:
            from lgi.solve.jaw import JawRig

            self.template_rig = JawRig(np.linalg.solve(affine, self.rig.pivot - shift), self.rig.weights)

    def marker_deltas(self, delta: np.ndarray) -> np.ndarray:
        """(M, 3) float64, cm: a template displacement (V, 3) at the actor's markers, transferred."""
        return self.layout.evaluate(np.asarray(delta, np.float64)) @ self.A.T  # barycentric, so linear

    def template_shape(self, parts: tuple[str, ...]) -> str | None:
        """The template's shape for a control or combination (any order of the parts), or None when the
        template has no such combination shape."""
        names = self.template.names
        if "+".join(parts) in names:
            return "+".join(parts)
        for n in names:
            if "+" in n and sorted(p.strip() for p in n.split("+")) == sorted(parts):
                return n
        return None

    def template_delta(self, parts: tuple[str, ...]) -> np.ndarray:
        """(V, 3) float64: the template's displacement for a control or a combination of controls (the sum of
        the parts' when the template has no combination shape)."""
        names = self.template.names
        name = self.template_shape(parts)
        if name is not None:
            return np.asarray(self.template.deltas[names.index(name)], np.float64)
        return sum(np.asarray(self.template.deltas[names.index(p)], np.float64) for p in parts)

    def bundles(self, parts: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray | None]:
        """The actor's bundles (M, 3) float64 cm for a control or combination, and its jaw parameters (4,)
        (None without a jaw rig)."""
        x, theta = self._transfer(parts)
        return self.layout.evaluate(x), theta

    def moves_jaw(self, control: str) -> bool:
        """Whether a template control opens or moves the jaw (its fitted jaw parameters exceed 1 degree or
        0.5 mm); False without a jaw rig."""
        if self.rig is None:
            return False
        theta = self._transfer((control,))[1]
        return bool(np.any(np.abs(theta) > np.array([1.0, 1.0, 1.0, 0.05])))

    def transferred(self, parts: tuple[str, ...]) -> np.ndarray:
        """(V, 3) float64: the whole template shape transferred as the bundles are (the displacement mapped,
        the jaw by its parameters), without LGI: what the bundles are sampled from."""
        return self._transfer(parts)[0]

    def _transfer(self, parts: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray | None]:
        delta = self.template_delta(parts)
        if self.rig is None:
            return self.neutral + delta @ self.A.T, None
        from lgi.solve.jaw import fit_shape_parameters, unskin_deltas

        theta = fit_shape_parameters(self.template_rig, self.template.neutral, delta[None])[0]
        u = unskin_deltas(self.template_rig, self.template.neutral, delta[None], theta[None])[0]
        # Skinned per vertex (then sampled at the markers), as the solver's surface is.
        return self.rig.skin(self.neutral + np.asarray(u, np.float64) @ self.A.T, theta), theta

    def reconstruct(self, bundles: np.ndarray, jaw: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
        """The actor's shape (V, 3) float32 for ``bundles`` (M, 3) with the jaw (4,) given (or estimated when
        None and the index has a rig), its largest distance from the bundles and the farthest a bundle lies
        outside its cloud, mm."""
        exact = self.solver.solve_frame(bundles, jaw=jaw)
        out = float(exact.projection[exact.status == 1].max(initial=0.0)) * 10.0
        r = exact if self.fitter is self.solver else self.fitter.solve_frame(bundles, jaw=jaw)
        return r.vertices, float(np.nanmax(r.residual)) * 10.0, out

    def naive(self, parts: tuple[str, ...]) -> np.ndarray:
        """(V, 3) float64: the naive transfer: the template's displacement added to the actor's neutral."""
        return self.neutral + self.template_delta(parts)

    def generate(self, controls: list[str] | None = None, correctives: list[tuple[str, ...]] | None = None,
                 progress=None) -> GeneratedRig:
        """Reconstruct every control (default: every template shape that is not a combination) and every
        corrective combination."""
        names = self.template.names
        controls = controls or [n for n in names if "+" not in n]
        correctives = correctives or []
        items: list[tuple[str, ...]] = [(c,) for c in controls] + list(correctives)
        shapes, resid, proj, jaw = [], [], [], []
        for parts in (progress(items) if progress else items):
            b, theta = self.bundles(parts)
            v, r, o = self.reconstruct(b, theta)
            jaw.append(theta)
            shapes.append(v)
            resid.append(r)
            proj.append(o)
        out = np.stack(shapes) if shapes else np.zeros((0, len(self.neutral), 3), np.float32)
        ctrl = out[:len(controls)].astype(np.float64)
        combos = out[len(controls):].astype(np.float64)
        k = {c: i for i, c in enumerate(controls)}
        cdel = np.zeros((len(correctives), len(self.neutral), 3))
        source = []
        for i, parts in enumerate(correctives):
            parts_sum = sum(ctrl[k[c]] - self.neutral for c in parts)
            if proj[len(controls) + i] > self.coverage_mm:
                moved = self.transferred(parts) - self.neutral
                cdel[i] = moved - sum(self.transferred((c,)) - self.neutral for c in parts)
                combos[i] = self.neutral + parts_sum + cdel[i]
                source.append("template")
            else:
                cdel[i] = combos[i] - self.neutral - parts_sum
                source.append("actor")
        far = [(c, proj[i]) for i, c in enumerate(controls) if proj[i] > self.coverage_mm]
        if far:
            log.warning("%d of %d controls lie outside the actor's dataset (bundles up to %.1f mm outside their "
                        "clouds: %s): LGI blends the actor's shapes, so these come out short of the template's "
                        "motion", len(far), len(controls), max(o for _, o in far),
                        ", ".join(f"{n} {o:.1f} mm" for n, o in far[:6]) + (" ..." if len(far) > 6 else ""))
        outside = [("+".join(p), proj[len(controls) + i]) for i, p in enumerate(correctives) if source[i] == "template"]
        if outside:
            log.warning("%d of %d combinations lie outside the actor's dataset (bundles up to %.1f mm outside their "
                        "clouds: %s): their correctives are the template's, transferred (zero where the template has "
                        "no such combination shape), not the actor's",
                        len(outside), len(correctives), max(o for _, o in outside),
                        ", ".join(f"{n} {o:.1f} mm" for n, o in outside[:6]) + (" ..." if len(outside) > 6 else ""))
        return GeneratedRig(self.neutral, list(controls), ctrl.astype(np.float32), list(correctives),
                            cdel.astype(np.float32), combos.astype(np.float32), np.asarray(resid), np.asarray(proj),
                            source, None if self.rig is None else np.asarray(jaw, np.float64).reshape(len(items), 4))


def parse_correctives(spec: str | None, transfer: TemplateTransfer, controls: list[str]) -> list[tuple[str, ...]]:
    """``--correctives``: None or "" (none), ``auto`` (:func:`auto_correctives`), or comma-separated
    combinations ``a+b[,c+d+e]`` (shell patterns are not expanded)."""
    if not spec:
        return []
    if spec.strip() == "auto":
        own = template_combinations(transfer.template.names, controls)
        if own:
            return own  # the template's own combination shapes say which correctives its rig has
        d = np.stack([transfer.marker_deltas(transfer.template_delta((c,))) for c in controls])
        moving = {c for c in controls if transfer.moves_jaw(c)}
        # Two jaw controls combine through the jaw's parameters (the rig), not through a corrective shape.
        pairs = [p for p in auto_correctives(d, controls, limit=10**6) if not set(p) <= moving]
        if not pairs:
            log.warning("--correctives auto: no two controls move the same markers; no corrective generated")
        return pairs[:24]
    out = []
    for item in spec.split(","):
        if item.strip():
            if any(ch in item for ch in "*?["):
                raise InputError(f"corrective {item!r}: patterns are not accepted; name the controls")
            out.append(combination_parts(item, controls))
    if not out:
        raise InputError(f"--correctives {spec!r} names no combination")
    if len({tuple(sorted(p)) for p in out}) != len(out):
        raise InputError("--correctives names a combination twice")
    return out


def template_combinations(names: list[str], controls: list[str]) -> list[tuple[str, ...]]:
    """The template's combination shapes (``a+b[+c]`` names) whose parts are all among ``controls``."""
    out = []
    for n in names:
        parts = tuple(p.strip() for p in n.split("+"))
        if len(parts) in (2, 3) and len(set(parts)) == len(parts) and all(p in controls for p in parts):
            out.append(parts)
    return out


def in_between_or_combination(name: str, names: list[str], tags: list[str] | None = None) -> bool:
    """Whether a template shape is an in-between (tagged so, or ``NAME_<digits>`` beside a shape ``NAME``) or a
    combination (tagged so): not a control unless asked for by name."""
    tags = tags or []
    if "inbetween" in tags or "combination" in tags:
        return True
    base, _, level = name.rpartition("_")
    return level.isdigit() and base in names


def select_controls(names: list[str], pattern: str | None, tags: list[list[str]] | None = None) -> list[str]:
    """Template shapes used as controls: not combinations (``+`` in the name), matching ``pattern`` (shell
    patterns, comma-separated) when given; by default (no pattern) not in-betweens or combinations either
    (:func:`in_between_or_combination`; ``tags``: each shape's metadata tags)."""
    pats = [p.strip() for p in (pattern or "").split(",") if p.strip()]
    unmatched = [p for p in pats if not any("+" not in n and fnmatch.fnmatchcase(n, p) for n in names)]
    if unmatched:
        raise InputError(f"--controls: {', '.join(map(repr, unmatched))} matches no template shape (have "
                         f"{', '.join(n for n in names if '+' not in n)[:300]})")
    if pats:
        return [n for n in names if "+" not in n and any(fnmatch.fnmatchcase(n, p) for p in pats)]
    tags = tags or [[] for _ in names]
    return [n for n, t in zip(names, tags, strict=True) if "+" not in n and not in_between_or_combination(n, names, t)]
