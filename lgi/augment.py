"""Dataset augmentation with linear in-betweens: combinations of dataset shapes at fixed weights.

A combination's displacement is the weighted sum of its sources' displacements (a linear blend). Rules
skip combinations that make no sense: opposite pairs (``jawLeft`` with ``jawRight``, ``mouthLeft`` with
``mouthRight``, ``eyeLookIn_L`` with ``eyeLookOut_L`` ...), and correctives that belong with one shape
only (ICT's ``mouthClose`` already contains the jaw opening and goes with ``jawOpen``). Augmented shapes
are tagged with their sources, weights and method.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable

import numpy as np

from .dataset import ShapeDataset, ShapeMeta

# Words whose swap turns a shape into its opposite motion (jawLeft/jawRight, eyeLookIn_L/eyeLookOut_L).
# Sides (_L/_R) are not opposites: a left and a right smile make a smile.
OPPOSITES = [("Left", "Right"), ("Up", "Down"), ("In", "Out"), ("left", "right"), ("raise", "lower")]
DEFAULT_REQUIRES = {"mouthClose": "jawOpen"}


def compatible(names: Iterable[str], requires: dict[str, str] | None = None) -> bool:
    """Whether shapes may be combined: no two are opposites of each other (the same name but for one
    opposite word), and a shape that requires a partner (``requires``) has it."""
    names = list(names)
    req = DEFAULT_REQUIRES if requires is None else requires
    for a, b in itertools.combinations(names, 2):
        if any(a.replace(x, y) == b or b.replace(x, y) == a for x, y in OPPOSITES):
            return False
    for n in names:
        if n in req and req[n] not in names:
            return False
    return True


def linear_combinations(
    dataset: ShapeDataset,
    n: int,
    levels: tuple[float, ...] = (0.5, 1.0),
    orders: tuple[int, ...] = (2, 3),
    seed: int = 0,
    requires: dict[str, str] | None = None,
    include: str | None = None,
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

    Returns
    -------
    ShapeDataset
        Source shapes first, then the combinations, named ``a*0.5+b*1``, tagged ``combination`` and
        ``linear``, with ``extra = {"sources": {name: weight}, "method": "linear"}``.
    """
    src = dataset.select(include=include) if include else dataset
    rng = np.random.default_rng(seed)
    names = src.names
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
    out = dataset.take(range(dataset.n_shapes))
    out.deltas = np.concatenate([np.asarray(dataset.deltas, np.float32), deltas])
    out.names = dataset.names + new_names
    out.shape_meta = dataset.shape_meta + meta
    out.info = {**dataset.info, "augmented": {"linear_combinations": len(picks), "levels": list(levels),
                                              "orders": list(orders), "seed": seed}}
    return out


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
    added (augmented shapes), kept (extra points the augmentation left after pruning and merging).
    """
    import pandas as pd

    from .cloud import CloudOptions, build_cloud

    opts = options or CloudOptions()
    rows = []
    tabs = []
    for ds in (original, augmented):
        rest = layout.evaluate(ds.neutral)
        tabs.append(np.concatenate([rest[None], rest[None] + layout.evaluate(np.asarray(ds.deltas, np.float64))]))
    rng = np.random.default_rng(opts.seed)
    for i, name in enumerate(layout.names):
        a = build_cloud(tabs[0][:, i], opts, rng).report["points"]
        b = build_cloud(tabs[1][:, i], opts, rng).report["points"]
        rows.append((name, a, b, augmented.n_shapes - original.n_shapes, b - a))
    return pd.DataFrame(rows, columns=["marker", "points_original", "points_augmented", "added", "kept"])
