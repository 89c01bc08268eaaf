"""Dataset augmentation with in-betweens: combinations of dataset shapes at fixed weights.

A linear in-between's displacement is the weighted sum of its sources' displacements (a linear blend).
A simulated in-between uses that blend (or, with a jaw rig, the blend of the unskinned shapes skinned with
the blended jaw) as the target of a volumetric flesh simulation (:mod:`lgi.augment.flesh`) that keeps volume and
keeps the lips apart. Rules
skip combinations that make no sense: opposite pairs (``jawLeft`` with ``jawRight``, ``mouthLeft`` with
``mouthRight``, ``eyeLookIn_L`` with ``eyeLookOut_L`` ...), and correctives that belong with one shape
only (ICT's ``mouthClose`` already contains the jaw opening and goes with ``jawOpen``). Augmented shapes
are tagged with their sources, weights and method.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Iterable

import numpy as np

from lgi.dataset.shapes import ShapeDataset, ShapeMeta
from lgi.index.cloud import CloudOptions, build_cloud
from lgi.progress import progress

# Words whose swap turns a shape into its opposite motion (jawLeft/jawRight, eyeLookIn_L/eyeLookOut_L).
# Sides (_L/_R) are not opposites: a left and a right smile make a smile.
OPPOSITES = [("Left", "Right"), ("Up", "Down"), ("In", "Out"), ("left", "right"), ("raise", "lower")]
DEFAULT_REQUIRES = {"mouthClose": "jawOpen"}


def compatible(names: Iterable[str], requires: dict[str, str] | None = None) -> bool:
    """Whether shapes may be combined: no two are opposites of each other (the same name but for one
    opposite word), no two share a component (names made of ``+``-joined parts, a trailing ``_50``-style
    level ignored: ``jaw_open+pucker`` and ``jaw_open_50+smile_R`` both open the jaw), and a shape that
    requires a partner (``requires``) has it."""
    names = list(names)
    req = DEFAULT_REQUIRES if requires is None else requires
    # The same motion twice (``jaw_open+pucker`` with ``jaw_open_50+smile_R``) is not an in-between.
    parts = [{re.sub(r"_\d+$", "", p) for p in n.split("+")} for n in names]
    for a, b in itertools.combinations(parts, 2):
        if a & b:
            return False
    for a, b in itertools.combinations(names, 2):
        if any(a.replace(x, y) == b or b.replace(x, y) == a for x, y in OPPOSITES):
            return False
    for n in names:
        if n in req and req[n] not in names:
            return False
    return True


def pick_combinations(names: list[str], n: int, levels: tuple[float, ...] = (0.5, 1.0),
                      orders: tuple[int, ...] = (2, 3), seed: int = 0, requires: dict[str, str] | None = None
                      ) -> list[dict[str, float]]:
    """Up to ``n`` distinct compatible combinations ``{shape: weight}`` of the named shapes (deterministic)."""
    rng = np.random.default_rng(seed)
    seen: set[tuple] = set()
    picks: list[dict[str, float]] = []
    tries = 0
    while len(picks) < n and tries < 200 * max(n, 1):
        tries += 1
        k = int(rng.choice(orders))
        if k > len(names):
            continue
        members = sorted(rng.choice(len(names), size=k, replace=False).tolist())
        combo = [names[m] for m in members]
        if not compatible(combo, requires):
            continue
        weights = tuple(float(rng.choice(levels)) for _ in members)
        key = tuple(zip(combo, weights, strict=True))
        if key in seen:
            continue
        seen.add(key)
        picks.append(dict(key))
    return picks


def linear_combinations(
    dataset: ShapeDataset,
    n: int,
    levels: tuple[float, ...] = (0.5, 1.0),
    orders: tuple[int, ...] = (2, 3),
    seed: int = 0,
    requires: dict[str, str] | None = None,
    include: str | None = None,
    picks: list[dict[str, float]] | None = None,
) -> ShapeDataset:
    """The dataset plus ``n`` linear combinations of its shapes.

    Parameters
    ----------
    dataset
        Source shapes.
    n
        Combinations to add (fewer if the rules leave fewer).
    levels
        Weights each source may take.
    orders
        How many sources a combination has (pairs and triples by default), drawn evenly.
    seed
        Sampling seed (deterministic).
    requires
        ``{shape: partner}``: the shape only appears together with the partner (default: ICT's rule
        that ``mouthClose`` goes with ``jawOpen``).
    include
        Shell patterns of the source shapes (default all).
    picks
        The combinations to make (instead of sampling them): ``[{shape: weight}, ...]``.

    Returns
    -------
    ShapeDataset
        Source shapes first, then the combinations, named ``a*0.5+b*1``, tagged ``combination`` and
        ``linear``, with ``extra = {"sources": {name: weight}, "method": "linear"}``.
    """
    src = dataset.select(include=include) if include else dataset
    if picks is None:
        picks = pick_combinations(src.names, n, levels, orders, seed, requires)
    deltas = np.empty((len(picks), *dataset.neutral.shape), np.float32)
    meta, new_names = [], []
    for c, combo in enumerate(picks):
        d = np.zeros(dataset.neutral.shape)
        for name, w in combo.items():
            d += w * np.asarray(src.deltas[src.index(name)], np.float64)
        deltas[c] = d
        new_names.append("+".join(f"{k}*{w:g}" for k, w in combo.items()))
        meta.append(ShapeMeta(source="linear combination", tags=["combination", "linear"],
                              extra={"sources": combo, "method": "linear"}))
    return _append(dataset, deltas, new_names, meta, {"linear_combinations": len(picks), "levels": list(levels),
                                                      "orders": list(orders), "seed": seed})


def _append(dataset: ShapeDataset, deltas: np.ndarray, names: list[str], meta: list[ShapeMeta],
            info: dict) -> ShapeDataset:
    out = dataset.take(range(dataset.n_shapes))
    out.deltas = np.concatenate([np.asarray(dataset.deltas, np.float32), deltas.astype(np.float32)])
    out.names = dataset.names + names
    out.shape_meta = dataset.shape_meta + meta
    aug = dict(dataset.info.get("augmented", {}))
    aug.update(info)
    out.info = {**dataset.info, "augmented": aug}
    return out


class Blender:
    """Targets of in-betweens: a linear blend of the sources, or with a jaw rig a blend of their unskinned
    shapes skinned with the blended jaw parameters (so a blend with ``jawOpen`` rotates, not shears)."""

    def __init__(self, dataset: ShapeDataset, rig=None) -> None:
        self.ds = dataset
        self.rig = rig
        self.index = {n: i for i, n in enumerate(dataset.names)}
        self.deltas = np.asarray(dataset.deltas, np.float32)
        self.params = None
        if rig is not None:
            from lgi.solve.jaw import fit_shape_parameters, unskin_deltas

            self.params = fit_shape_parameters(rig, dataset.neutral, self.deltas)
            self.unskinned = unskin_deltas(rig, dataset.neutral, self.deltas, self.params)

    def target(self, combo: dict[str, float]) -> tuple[np.ndarray, np.ndarray | None]:
        """(V, 3) target positions and the jaw parameters (4,) (None without a rig)."""
        idx = [self.index[k] for k in combo]
        w = np.array(list(combo.values()))
        if self.rig is None:
            return self.ds.neutral + np.tensordot(w, self.deltas[idx].astype(np.float64), axes=1), None
        u = self.ds.neutral + np.tensordot(w, self.unskinned[idx].astype(np.float64), axes=1)
        jaw = w @ self.params[idx]
        return self.rig.skin(u, jaw), jaw


def simulated_combinations(
    dataset: ShapeDataset,
    n: int,
    levels: tuple[float, ...] = (0.5, 1.0),
    orders: tuple[int, ...] = (2, 3),
    seed: int = 0,
    requires: dict[str, str] | None = None,
    include: str | None = None,
    rig=None,
    options=None,
    picks: list[dict[str, float]] | None = None,
    show_progress: bool = False,
) -> ShapeDataset:
    """The dataset plus ``n`` physically simulated in-betweens (:mod:`lgi.augment.flesh`).

    Each combination's target (:class:`Blender`) pulls the skin of a volumetric flesh model that keeps
    its volume and keeps the lips apart. Named like the linear ones with a ``~sim`` suffix, tagged
    ``combination`` and ``simulated``, with ``extra = {"sources", "method": "simulated", "volume_change",
    "target_distance", "lip_contacts"}``.
    """
    from lgi.augment.flesh import FleshModel

    src = dataset.select(include=include) if include else dataset
    if picks is None:
        picks = pick_combinations(src.names, n, levels, orders, seed, requires)
    blender = Blender(dataset, rig)
    # The flesh model is shaped by the captured shapes only (not by earlier in-betweens).
    base = [k for k, m in enumerate(dataset.shape_meta) if "combination" not in (m.tags or [])]
    model = FleshModel(dataset.neutral, dataset.triangles, blender.deltas[base], rig=rig, options=options,
                       shape_jaw=None if blender.params is None else blender.params[base])
    deltas = np.empty((len(picks), *dataset.neutral.shape), np.float32)
    names, meta = [], []
    for c, combo in enumerate(progress(picks, desc="simulated in-betweens", disable=not show_progress)):
        target, jaw = blender.target(combo)
        r = model.solve(target, jaw)
        deltas[c] = r.positions - dataset.neutral
        names.append("+".join(f"{k}*{w:g}" for k, w in combo.items()) + "~sim")
        meta.append(ShapeMeta(source="simulated in-between", tags=["combination", "simulated"],
                              extra={"sources": combo, "method": "simulated",
                                     "volume_change": round(r.volume_change, 6),
                                     "target_distance": round(r.target_distance, 6), "lip_contacts": r.contacts}))
    return _append(dataset, deltas, names, meta,
                   {"simulated_combinations": len(picks), "levels": list(levels), "orders": list(orders), "seed": seed,
                    "flesh": vars(model.options)})


def augmentation_report(original: ShapeDataset, augmented: ShapeDataset, layout, options=None):
    """Per bundle: cloud points from the original shapes and from the added ones, before and after pruning.

    Parameters
    ----------
    original, augmented
        The dataset before and after augmentation (same neutral and topology).
    layout : MarkerLayout
    options : CloudOptions, optional
        Pruning options (defaults otherwise).

    Returns
    -------
    DataFrame with columns marker, points_original (after pruning), points_augmented (after pruning),
    added (augmented shapes), kept (extra points the augmentation left after pruning and merging), and per
    augmentation method (``linear``, ``simulated``) ``added_<method>`` and ``kept_<method>`` (that
    method's shapes alone added to the original).
    """
    import pandas as pd

    opts = options or CloudOptions()
    methods: dict[str, list[int]] = {}
    for k in range(original.n_shapes, augmented.n_shapes):
        m = augmented.shape_meta[k].extra.get("method", "other") if augmented.shape_meta[k].extra else "other"
        methods.setdefault(m, []).append(k)
    rest = layout.evaluate(original.neutral)
    table = np.concatenate([rest[None], rest[None] + layout.evaluate(np.asarray(augmented.deltas, np.float64))])
    base = np.arange(original.n_shapes + 1)
    sets = {"original": base, "augmented": np.arange(augmented.n_shapes + 1)}
    for m, ks in methods.items():
        sets[m] = np.concatenate([base, np.asarray(ks) + 1])
    rows = []
    rng = np.random.default_rng(opts.seed)
    for i, name in enumerate(layout.names):
        pts = {k: build_cloud(table[v, i], opts, rng).report["points"] for k, v in sets.items()}
        row = {"marker": name, "points_original": pts["original"], "points_augmented": pts["augmented"],
               "added": augmented.n_shapes - original.n_shapes, "kept": pts["augmented"] - pts["original"]}
        for m, ks in methods.items():
            row[f"added_{m}"] = len(ks)
            row[f"kept_{m}"] = pts[m] - pts["original"]
        rows.append(row)
    return pd.DataFrame(rows)
