"""A procedural, deterministic synthetic actor with a nonlinear ground truth.

The face is a parametric surface over ``x in [-8, 8]``, ``y in [-11, 11]`` cm (x toward the actor's
left, y up, z out of the face) sampled on a quad grid, with UVs ``((x + 8) / 16, (y + 11) / 22)``.
Its lips are separated by a slit: the lower lip's vertices on the slit are duplicates of the upper
lip's, so the mouth opens.

An expression is a vector of activations in [0, 1] for :data:`CONTROLS`. The true mesh is::

    x(a) = LBS_jaw(theta(a)) [ x0 + sum_k m_k(a_k) + wrinkles(a) + folds(a) ]

* ``m_k``: muscle-like regional displacements that follow curved (quadratic) paths in ``a_k``;
* wrinkles (forehead, glabella, lips) and the nasolabial folds, whose depth is quadratic in a
  *sum* of activations, so regions interact (the cross terms are what a linear blend lacks);
* cheek puff damped by jaw opening (a product term);
* the jaw: a rotation about a hinge behind the face (open up to 22 degrees, sideways yaw and roll)
  with a forward slide that grows with the square of the opening, applied by linear blend skinning.

So the linear blend of the extreme shapes is not the truth: :func:`nonlinearity` measures by how much.
Nothing here is random except :func:`random_performance`, which is seeded.

Other actors: :class:`ActorVariant` (``make_actor(variant=ActorVariant.draw(seed))``, ``lgi synth --actor
SEED``) gives a face with other proportions (a scale per axis and a larger or smaller nose and cheekbones,
applied as a smooth warp of space after the expression) and its own expression details (where the
nasolabial fold sits and how deep it gets, the spacing of forehead and lip lines, the smile's path and how
much the open jaw damps it), on the same mesh topology. Its jaw hinge is the warped hinge. It is what
template-to-actor transfer (``lgi rig-generate``) is measured on: the template's deltas are not this actor's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lgi.dataset.mesh import triangulate, vertex_normals
from lgi.dataset.shapes import ShapeDataset, ShapeMeta
from lgi.errors import InputError
from lgi.paths import shipped

CONTROLS = [
    "jaw_open", "jaw_left", "jaw_right", "jaw_forward",
    "smile_L", "smile_R", "pucker", "brow_raise_L", "brow_raise_R", "brow_lower",
    "sneer_L", "sneer_R", "cheek_puff",
]
C = {name: i for i, name in enumerate(CONTROLS)}

HALF_W, HALF_H = 8.0, 11.0  # cm
MOUTH_Y, MOUTH_HALF_WIDTH = -4.5, 2.4  # cm
JAW_PIVOT = np.array([0.0, 0.5, -8.0])  # cm, the hinge (near the ear)
JAW_OPEN_DEG, JAW_YAW_DEG, JAW_ROLL_DEG = 22.0, 7.0, 2.0
JAW_FORWARD_CM, JAW_SLIDE_CM = 0.5, 0.35
EYE_CENTERS = np.array([[3.2, 2.8], [-3.2, 2.8]])


def _g(x: np.ndarray, y: np.ndarray, cx: float, cy: float, sx: float, sy: float | None = None) -> np.ndarray:
    sy = sx if sy is None else sy
    return np.exp(-((x - cx) ** 2) / (2 * sx**2) - ((y - cy) ** 2) / (2 * sy**2))


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def face_depth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """z (cm) of the neutral face surface at (x, y) (cm)."""
    ax = np.abs(x)
    z = 5.0 - 0.09 * x**2 - 0.015 * y**2
    z += 2.2 * _g(x, y, 0, -1.0, 0.7, 1.0)  # nose tip
    z += 1.2 * np.exp(-(x**2) / (2 * 0.6**2)) * _smoothstep((y + 1.0) / 1.5) * _smoothstep((4.2 - y) / 1.2)
    z -= 0.9 * _g(ax, y, 3.2, 2.8, 1.2)  # eye sockets
    z += 0.4 * np.exp(-((y - 4.4) ** 2) / (2 * 0.5**2) - x**2 / (2 * 4.0**2))  # brow ridge
    z += 0.5 * _g(x, y, 0, MOUTH_Y, 1.8, 0.8)  # lips
    z += 0.5 * _g(x, y, 0, -8.0, 1.8, 1.0)  # chin
    z += 0.5 * _g(ax, y, 4.2, -0.5, 1.5)  # cheekbones
    return z


@dataclass(frozen=True)
class ActorVariant:
    """How an actor differs from the default one (seed 0 is the default actor, unchanged).

    Attributes
    ----------
    seed : int
    scale : (3,) float
        Scale of x (width), y (height), z (depth) about the origin.
    nose, cheekbones : float, cm
        Extra height of the nose and cheekbone bumps (along z, after the scale).
    fold_shift, fold_depth : float
        How far the nasolabial crease slides per unit pull (cm) and its depth coefficient.
    forehead_period, lip_line_period : float, cm
        Spacing of the forehead creases and of the lip lines.
    smile_path : (3,) float
        The smile's first-order path (x outward, y up, z), cm per unit activation.
    smile_jaw_damping : float
        How much of the smile's lift an open jaw takes away.
    """

    seed: int = 0
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    nose: float = 0.0
    cheekbones: float = 0.0
    fold_shift: float = 0.45
    fold_depth: float = 0.3
    forehead_period: float = 1.3
    lip_line_period: float = 0.35
    smile_path: tuple[float, float, float] = (0.55, 0.45, -0.25)
    smile_jaw_damping: float = 0.4

    @classmethod
    def draw(cls, seed: int) -> ActorVariant:
        """A variant drawn from ``seed`` (0: the default actor): proportions within about 10 %, expression
        details within about 30 % of the default's."""
        if seed == 0:
            return cls()
        rng = np.random.default_rng(seed + 7919)
        d = cls()

        def u(lo: float, hi: float) -> float:
            return float(rng.uniform(lo, hi))

        return cls(seed=seed, scale=(u(0.9, 1.1), u(0.9, 1.1), u(0.9, 1.15)), nose=u(-0.3, 0.4),
                   cheekbones=u(-0.25, 0.3), fold_shift=d.fold_shift * u(0.7, 1.3),
                   fold_depth=d.fold_depth * u(0.7, 1.4), forehead_period=d.forehead_period * u(0.8, 1.25),
                   lip_line_period=d.lip_line_period * u(0.8, 1.25),
                   smile_path=(d.smile_path[0] * u(0.8, 1.2), d.smile_path[1] * u(0.8, 1.2),
                               d.smile_path[2] * u(0.8, 1.2)),
                   smile_jaw_damping=d.smile_jaw_damping * u(0.6, 1.4))

    @property
    def is_default(self) -> bool:
        return self == ActorVariant()

    def warp(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) positions in the default actor's space to this actor's, cm."""
        if self.is_default:
            return p
        q = p * np.asarray(self.scale)
        x, y = p[..., 0], p[..., 1]
        q[..., 2] += self.nose * _g(x, y, 0, -1.0, 0.8, 1.1) + self.cheekbones * _g(np.abs(x), y, 4.2, -0.5, 1.5)
        return q


@dataclass
class SyntheticActor:
    """The synthetic face and its expression model.

    Build with :func:`make_actor`. Evaluate expressions with :meth:`evaluate`.

    Attributes
    ----------
    neutral : (V, 3) float64, cm
    face_vertices, face_offsets
        Quads (flat layout, see :class:`lgi.io.obj.PolyMesh`).
    uvs : (V, 2) float32; face_uvs : (N,) int32
    lower_lip : (V,) bool
        Vertices on the lower side of the mouth slit (duplicated slit vertices included).
    jaw_weights : (V,) float64
        Linear-blend-skinning weight of the jaw bone, in [0, 1].
    variant : ActorVariant
        Proportions and expression details (default: the default actor).
    base : (V, 3) float64 or None
        The neutral in the default actor's space, where the expression model is defined (None: ``neutral``).
    """

    neutral: np.ndarray
    face_vertices: np.ndarray
    face_offsets: np.ndarray
    uvs: np.ndarray
    face_uvs: np.ndarray
    lower_lip: np.ndarray
    jaw_weights: np.ndarray
    grid_shape: tuple[int, int]
    variant: ActorVariant = field(default_factory=ActorVariant)
    base: np.ndarray | None = None
    _fields: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    @property
    def x0(self) -> np.ndarray:
        """(V, 3) float64: the neutral in the expression model's space (the default actor's)."""
        return self.neutral if self.base is None else self.base

    @property
    def pivot(self) -> np.ndarray:
        """(3,) float64, cm: the jaw hinge of this actor."""
        return self.variant.warp(JAW_PIVOT[None].copy())[0]

    def lip_contours(self) -> dict[str, np.ndarray]:
        """The vertices of the lips' inner edges, left to right: ``upper_inner`` (the slit row) and
        ``lower_inner`` (its lower-lip copies), both ending at the mouth corners they share. Where the mouth
        opens these edges are the lips' inner contours; closed, the line where the lips meet."""
        nv, nu = self.grid_shape
        dup = np.arange(nv * nu, self.n_vertices)
        rows_y = self.x0[np.arange(nv) * nu, 1]
        row = int(np.argmin(np.abs(rows_y - MOUTH_Y))) * nu + np.arange(nu)
        cols = np.searchsorted(self.x0[row, 0], self.x0[dup, 0] - 1e-9)
        c0, c1 = int(cols.min()) - 1, int(cols.max()) + 1
        return {"upper_inner": row[c0:c1 + 1], "lower_inner": np.concatenate([[row[c0]], dup, [row[c1]]])}

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    @property
    def triangles(self) -> np.ndarray:
        return triangulate(self.face_vertices, self.face_offsets)[0]

    # ------------------------------------------------------------------ expression model
    def jaw_parameters(self, a: np.ndarray) -> np.ndarray:
        """(..., 4) jaw parameters from activations (..., C): open, yaw, roll (degrees), forward (cm)."""
        a = np.asarray(a, np.float64)
        side = a[..., C["jaw_left"]] - a[..., C["jaw_right"]]
        return np.stack([
            JAW_OPEN_DEG * a[..., C["jaw_open"]],
            JAW_YAW_DEG * side,
            JAW_ROLL_DEG * side,
            JAW_FORWARD_CM * a[..., C["jaw_forward"]] + JAW_SLIDE_CM * a[..., C["jaw_open"]] ** 2,
        ], axis=-1)

    def unskinned(self, a: np.ndarray) -> np.ndarray:
        """(V, 3) float64: the face before the jaw is applied (muscles, wrinkles, folds)."""
        a = np.asarray(a, np.float64)
        f = self._fields
        va = self.variant
        x0 = self.x0
        x = x0.copy()
        n = f["normal"]
        for side, sgn in (("L", 1.0), ("R", -1.0)):
            s = a[C[f"smile_{side}"]]
            # The corner's lift weakens as the jaw opens and stretches the cheek (a product term).
            lift = 1 - va.smile_jaw_damping * a[C["jaw_open"]]
            sp = va.smile_path
            path = s * np.array([sp[0] * sgn, sp[1] * lift, sp[2]]) + s**2 * np.array([0.15 * sgn, 0.35 * lift, 0.1])
            x += f[f"smile_{side}"][:, None] * path
            b = a[C[f"brow_raise_{side}"]]
            x += f[f"brow_{side}"][:, None] * np.array([0.0, 0.8, 0.05]) * (1 - np.exp(-2.5 * b)) / (1 - np.exp(-2.5))
            sn = a[C[f"sneer_{side}"]]
            x += f[f"sneer_{side}"][:, None] * (sn * np.array([0.0, 0.5, 0.15]) + sn**2 * np.array([0.0, 0.1, 0.05]))
            # Nasolabial fold: depth grows with the square of the combined pull (smile, sneer, puff).
            pull = s + 0.6 * sn + 0.3 * a[C["cheek_puff"]]
            if pull > 0:
                crease, bulge = fold_profile(x0[:, 0], x0[:, 1], sgn, va.fold_shift * pull)
                x += n * (va.fold_depth * pull**2 * (0.6 * bulge - crease))[:, None]
        p = a[C["pucker"]]
        x += f["pucker"][:, None] * np.array([0.0, 0.0, 0.7]) * p
        x[:, 0] -= f["pucker"] * 0.35 * p**1.5 * np.clip(x0[:, 0] / MOUTH_HALF_WIDTH, -1, 1)
        x -= n * (0.06 * p**2 * f["lip_lines"])[:, None]
        bl = a[C["brow_lower"]]
        x += f["brow_lower"][:, None] * np.array([0.0, -0.45, -0.05]) * bl
        x[:, 0] -= f["brow_lower"] * 0.3 * bl * np.tanh(x0[:, 0] / 1.0) * f["glabella_mask"]
        x -= n * (0.1 * bl**2 * f["glabella_lines"])[:, None]
        raise_ = a[C["brow_raise_L"]] * f["forehead_L"] + a[C["brow_raise_R"]] * f["forehead_R"]
        # Forehead creases ride up with the brow (a moving pattern, like the nasolabial fold).
        yy = x0[:, 1] - 5.0 - 0.5 * raise_
        lines = f["forehead_mask"] * (0.5 - 0.5 * np.cos(2 * np.pi * yy / va.forehead_period))
        x -= n * (0.2 * raise_**2 * lines)[:, None]
        # Puffed cheeks flatten as the jaw opens (a product term).
        puff = a[C["cheek_puff"]] * (1 - 0.6 * a[C["jaw_open"]])
        x += n * (1.0 * puff * f["cheeks"])[:, None]
        return va.warp(x)

    def jaw_transform(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotation (3, 3) and translation (3,) of the jaw bone for parameters (4,)."""
        return jaw_transform(params, self.pivot)

    def skin(self, x: np.ndarray, params: np.ndarray) -> np.ndarray:
        """Apply the jaw to unskinned positions (V, 3) by linear blend skinning."""
        r, t = jaw_transform(params, self.pivot)
        moved = x @ r.T + t
        w = self.jaw_weights[:, None]
        return (1 - w) * x + w * moved

    def evaluate(self, a: np.ndarray) -> np.ndarray:
        """(V, 3) float64 true positions for activations (C,)."""
        a = np.asarray(a, np.float64)
        return self.skin(self.unskinned(a), self.jaw_parameters(a))

    def evaluate_many(self, activations: np.ndarray) -> np.ndarray:
        """(N, V, 3) float32 true positions for activations (N, C)."""
        return np.stack([self.evaluate(a) for a in activations]).astype(np.float32)

    def linear_blend(self, a: np.ndarray, extremes: np.ndarray | None = None) -> np.ndarray:
        """(V, 3) the linear blendshape prediction ``x0 + sum_k a_k (x(e_k) - x0)``."""
        ext = self.extreme_deltas() if extremes is None else extremes
        return self.neutral + np.tensordot(np.asarray(a, np.float64), ext, axes=1)

    def extreme_deltas(self) -> np.ndarray:
        """(C, V, 3) float64 displacement of each control at activation 1, alone."""
        return np.stack([self.evaluate(np.eye(len(CONTROLS))[k]) - self.neutral for k in range(len(CONTROLS))])


def jaw_transform(params: np.ndarray, pivot: np.ndarray = JAW_PIVOT) -> tuple[np.ndarray, np.ndarray]:
    """Rigid jaw motion for parameters ``(open_deg, yaw_deg, roll_deg, forward_cm)`` about JAW_PIVOT, in
    the rig convention of :func:`lgi.solve.jaw.jaw_matrix`.

    Returns
    -------
    R : (3, 3); t : (3,) such that a point ``p`` moves to ``R p + t``.
    """
    from lgi.solve.jaw import jaw_matrix

    m = jaw_matrix(params, pivot)
    return m[:3, :3], m[:3, 3]


def _grid_size(n_vertices: int) -> tuple[int, int]:
    nu = int(np.ceil(np.sqrt(n_vertices * HALF_W / HALF_H)))
    nv = int(np.ceil(n_vertices / nu))
    return nu, nv


def make_actor(n_vertices: int = 20000, variant: ActorVariant | None = None) -> SyntheticActor:
    """Build the synthetic actor with at least ``n_vertices`` vertices (deterministic); ``variant``: another
    actor's proportions and expression details (default: the default actor)."""
    if n_vertices < 500:
        raise InputError(f"the synthetic actor needs at least 500 vertices, got {n_vertices}")
    nu, nv = _grid_size(n_vertices)
    us = np.linspace(0, 1, nu)
    vs = np.linspace(0, 1, nv)
    # Put a grid row exactly on the mouth line so the slit follows grid edges.
    jm = int(round((MOUTH_Y + HALF_H) / (2 * HALF_H) * (nv - 1)))
    vs = vs + ((MOUTH_Y + HALF_H) / (2 * HALF_H) - vs[jm]) * np.clip(1 - np.abs(np.arange(nv) - jm) / 8, 0, 1)
    uu, vv = np.meshgrid(us, vs)  # (nv, nu)
    gx = (uu * 2 - 1) * HALF_W
    gy = (vv * 2 - 1) * HALF_H
    base = np.stack([gx.ravel(), gy.ravel(), face_depth(gx, gy).ravel()], axis=1)
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
    vid = np.arange(nu * nv).reshape(nv, nu)
    slit_cols = np.flatnonzero(np.abs(gx[jm]) < MOUTH_HALF_WIDTH)
    slit_cols = slit_cols[(slit_cols > 0) & (slit_cols < nu - 1)]
    dup = np.arange(nu * nv, nu * nv + slit_cols.size)
    low_id = vid.copy()
    low_id[jm, slit_cols] = dup  # the lower lip's copy of the slit row
    vertices = np.vstack([base, base[vid[jm, slit_cols]]])
    uvs = np.vstack([uv, uv[vid[jm, slit_cols]]]).astype(np.float32)
    j, i = np.meshgrid(np.arange(nv - 1), np.arange(nu - 1), indexing="ij")
    j, i = j.ravel(), i.ravel()
    # Quads in the row below the slit use the lower-lip copies for their top corners.
    ids_top = np.where((j + 1) == jm, low_id[j + 1, i], vid[j + 1, i])
    ids_top1 = np.where((j + 1) == jm, low_id[j + 1, i + 1], vid[j + 1, i + 1])
    quads = np.stack([vid[j, i], vid[j, i + 1], ids_top1, ids_top], axis=1).astype(np.int32)
    face_vertices = quads.ravel()
    face_offsets = np.arange(0, face_vertices.size + 1, 4, dtype=np.int64)

    lower = np.zeros(len(vertices), bool)
    lower[: nu * nv] = (vertices[: nu * nv, 1] < MOUTH_Y - 1e-9)
    lower[dup] = True
    variant = variant or ActorVariant()
    actor = SyntheticActor(
        neutral=variant.warp(vertices.copy()), base=None if variant.is_default else vertices, variant=variant,
        face_vertices=face_vertices, face_offsets=face_offsets, uvs=uvs,
        face_uvs=face_vertices.copy(), lower_lip=lower, jaw_weights=_jaw_weights(vertices, lower),
        grid_shape=(nv, nu),
    )
    actor._fields = _fields(actor)
    return actor


def _jaw_weights(v: np.ndarray, lower: np.ndarray) -> np.ndarray:
    x, y = v[:, 0], v[:, 1]
    # Away from the mouth: a jaw line rising toward the ears, with a soft band.
    boundary = MOUTH_Y + 0.1 * x**2
    band = 1.0 + 0.15 * np.abs(x)
    outer = _smoothstep((boundary - y) / band + 0.5)
    # At the mouth: the lower lip is on the jaw, the upper lip is not.
    inner = np.where(lower, 1.0, 0.0) * _smoothstep((MOUTH_Y + 0.01 - y) / 0.3 + 1.0)
    m = _smoothstep((MOUTH_HALF_WIDTH - np.abs(x)) / 0.8)
    return m * inner + (1 - m) * outer


def fold_profile(x: np.ndarray, y: np.ndarray, sgn: float, shift: float) -> tuple[np.ndarray, np.ndarray]:
    """Nasolabial crease and the cheek bulge beside it, for a fold line moved ``shift`` cm outward.

    The line runs from beside the nose wing to beyond the mouth corner; as the cheek is pulled the
    crease slides laterally, so no fixed set of displacement patterns reproduces it.
    """
    p0 = np.array([sgn * (1.7 + shift), -2.0 + 0.5 * shift])
    p1 = np.array([sgn * (3.4 + shift), -5.8 + 0.5 * shift])
    d = p1 - p0
    t = np.clip(((x - p0[0]) * d[0] + (y - p0[1]) * d[1]) / (d @ d), 0, 1)
    dist = np.hypot(p0[0] + t * d[0] - x, p0[1] + t * d[1] - y)
    # Which side of the (infinite) line: the cheek side (lateral, above) carries the bulge.
    lateral = (sgn * ((x - p0[0]) * d[1] - (y - p0[1]) * d[0])) < 0
    crease = np.exp(-(dist**2) / (2 * 0.25**2))
    bulge = np.exp(-((dist - 0.6) ** 2) / (2 * 0.35**2)) * lateral
    return crease, bulge


def _fields(actor: SyntheticActor) -> dict[str, np.ndarray]:
    v = actor.x0
    x, y = v[:, 0], v[:, 1]
    ax = np.abs(x)
    f: dict[str, np.ndarray] = {"normal": vertex_normals(v, actor.triangles)}
    for side, sgn in (("L", 1.0), ("R", -1.0)):
        f[f"smile_{side}"] = _g(x, y, sgn * MOUTH_HALF_WIDTH, MOUTH_Y, 1.6, 1.3)
        f[f"brow_{side}"] = _g(x, y, sgn * 3.0, 4.6, 2.2, 2.5) * _smoothstep((y - 2.8) / 1.5)
        f[f"forehead_{side}"] = _smoothstep((sgn * x + 2.5) / 5.0)
        f[f"sneer_{side}"] = _g(x, y, sgn * 1.1, -1.8, 0.8, 1.2) + 0.6 * _g(x, y, sgn * 1.0, -3.9, 0.9, 0.45)
    f["pucker"] = _g(x, y, 0, MOUTH_Y, 1.8, 1.0)
    period = actor.variant.lip_line_period
    f["lip_lines"] = _g(x, y, 0, MOUTH_Y, 1.6, 0.5) * (0.5 - 0.5 * np.cos(2 * np.pi * x / period))
    f["brow_lower"] = _g(x, y, 0, 4.2, 2.5, 1.0)
    f["glabella_mask"] = _g(x, y, 0, 4.0, 1.5, 1.0)
    f["glabella_lines"] = _g(x, y, 0, 3.8, 1.0, 0.8) * (0.5 - 0.5 * np.cos(2 * np.pi * x / 0.8))
    f["forehead_mask"] = _smoothstep((y - 5.0) / 0.8) * _smoothstep((9.5 - y) / 0.8) * np.exp(-(x**2) / (2 * 4.5**2))
    f["cheeks"] = _g(ax, y, 3.2, -3.8, 1.6)
    return f


# ---------------------------------------------------------------------- datasets and performances
def default_dataset_activations() -> tuple[list[str], np.ndarray]:
    """Names and activations (S, C) of the synthetic dataset: extremes, in-betweens, combinations.

    Every control at 0.5 and 1.0; symmetric pairs at 1.0; jaw_open at 0.5 and 1.0 combined with every
    non-jaw control at 1.0.
    """
    names, rows = [], []
    eye = np.eye(len(CONTROLS))
    for k, c in enumerate(CONTROLS):
        for lv in (0.5, 1.0):
            names.append(c if lv == 1.0 else f"{c}_50")
            rows.append(eye[k] * lv)
    for pair in ("smile", "brow_raise", "sneer"):
        names.append(f"{pair}_LR")
        rows.append(eye[C[f"{pair}_L"]] + eye[C[f"{pair}_R"]])
    for k, c in enumerate(CONTROLS[4:], start=4):
        for lv in (0.5, 1.0):
            names.append(f"jaw_open{'_50' if lv == 0.5 else ''}+{c}")
            rows.append(eye[C["jaw_open"]] * lv + eye[k])
    return names, np.asarray(rows)


def make_dataset(actor: SyntheticActor, names: list[str] | None = None,
                 activations: np.ndarray | None = None) -> ShapeDataset:
    """A shape dataset of the actor's expressions (default: :func:`default_dataset_activations`).

    Each shape's metadata records its activations and true jaw parameters.
    """
    if activations is None:
        names, activations = default_dataset_activations()
    assert names is not None
    shapes = actor.evaluate_many(activations)
    deltas = (shapes - actor.neutral[None]).astype(np.float32)
    meta = []
    for a in activations:
        active = {CONTROLS[k]: round(float(a[k]), 6) for k in np.flatnonzero(a)}
        tags = ["extreme"] if all(v == 1.0 for v in active.values()) else ["inbetween"]
        tags += ["combination"] if len(active) > 1 else []
        meta.append(ShapeMeta(
            source="synthetic:" + ",".join(f"{k}={v:g}" for k, v in active.items()), tags=tags,
            extra={"activations": active, "jaw": actor.jaw_parameters(a).round(9).tolist()},
        ))
    return ShapeDataset(
        neutral=actor.neutral, deltas=deltas, names=list(names), face_vertices=actor.face_vertices,
        face_offsets=actor.face_offsets, uvs=actor.uvs, face_uvs=actor.face_uvs, units="cm", shape_meta=meta,
        info={"name": "synthetic-actor", "controls": CONTROLS, "vertices": actor.n_vertices,
              "jaw_pivot_cm": actor.pivot.tolist(),
              **({} if actor.variant.is_default else {"actor_seed": actor.variant.seed})},
    )


#: Template correctives (:func:`template_dataset`): combinations whose shape differs from the sum of their controls'
#: by at least this much (mm), the largest first, at most TEMPLATE_PAIRS of them.
TEMPLATE_CORRECTIVE_MM = 0.1
TEMPLATE_PAIRS = 24


def template_dataset(n_vertices: int) -> ShapeDataset:
    """A template rig on the synthetic mesh of ``n_vertices``: the default actor's 13 controls (each at full
    activation, no in-betweens) and its combination shapes ``a+b`` of the pairs whose shape is not the sum of
    the two (a corrective of at least :data:`TEMPLATE_CORRECTIVE_MM`, the largest :data:`TEMPLATE_PAIRS`; no
    two jaw controls), for ``lgi rig-generate --template`` on an actor of the same topology."""
    actor = make_actor(n_vertices)
    eye = np.eye(len(CONTROLS))
    x0 = actor.neutral.astype(np.float64)
    single = {c: actor.evaluate(eye[C[c]]).astype(np.float64) - x0 for c in CONTROLS}
    sizes = []
    for i, a in enumerate(CONTROLS):
        for b in CONTROLS[i + 1:]:
            if a.startswith("jaw_") and b.startswith("jaw_"):
                continue
            both = actor.evaluate(eye[C[a]] + eye[C[b]]).astype(np.float64) - x0
            size = float(np.linalg.norm(both - single[a] - single[b], axis=1).max()) * 10
            if size >= TEMPLATE_CORRECTIVE_MM:
                sizes.append((size, a, b))
    pairs = [(a, b) for _, a, b in sorted(sizes, reverse=True)[:TEMPLATE_PAIRS]]
    combos = [eye[C[a]] + eye[C[b]] for a, b in pairs]
    return make_dataset(actor, [*CONTROLS, *(f"{a}+{b}" for a, b in pairs)], np.vstack([eye, *combos]))


def random_performance(n_frames: int, seed: int = 0, fps: float = 30.0) -> np.ndarray:
    """(F, C) float64 smooth random activations in [0, 1]: sparse overlapping expression events.

    Each control gets a few events (raised-cosine bumps, 0.4-2 s long, peaks 0.3-1.0); left and right
    controls are often driven together, as faces are mostly symmetric.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames)
    a = np.zeros((n_frames, len(CONTROLS)))
    duration_s = max(n_frames / fps, 1.0)
    for k, c in enumerate(CONTROLS):
        rate = 0.35 if c.startswith("jaw_open") else 0.18  # events per second
        n_ev = rng.poisson(rate * duration_s) + (1 if c == "jaw_open" else 0)
        for _ in range(n_ev):
            center = rng.uniform(0, n_frames)
            half = rng.uniform(0.2, 1.0) * fps
            peak = rng.uniform(0.3, 1.0)
            u = np.clip((t - center) / half, -1, 1)
            a[:, k] += peak * 0.5 * (1 + np.cos(np.pi * u))
    for pair in ("smile", "brow_raise", "sneer"):
        shared = 0.5 * (a[:, C[f"{pair}_L"]] + a[:, C[f"{pair}_R"]])
        mix = rng.uniform(0.3, 0.8)
        a[:, C[f"{pair}_L"]] = mix * shared + (1 - mix) * a[:, C[f"{pair}_L"]]
        a[:, C[f"{pair}_R"]] = mix * shared + (1 - mix) * a[:, C[f"{pair}_R"]]
    side = a[:, C["jaw_left"]] - a[:, C["jaw_right"]]
    a[:, C["jaw_left"]] = np.clip(side, 0, None) * 0.6
    a[:, C["jaw_right"]] = np.clip(-side, 0, None) * 0.6
    return np.clip(a, 0.0, 1.0)


def nonlinearity(actor: SyntheticActor, activations: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Distance between the truth and the linear blend of extremes, per expression.

    Parameters
    ----------
    activations : (N, C)
    mask : (V,) bool, optional
        Vertices to measure on (default all).

    Returns
    -------
    (N, 2) float64
        RMS and max vertex distance in mm.
    """
    ext = actor.extreme_deltas()
    out = np.empty((len(activations), 2))
    for i, a in enumerate(activations):
        d = np.linalg.norm(actor.evaluate(a) - actor.linear_blend(a, ext), axis=1)
        if mask is not None:
            d = d[mask]
        out[i] = 10 * np.sqrt(np.mean(d**2)), 10 * d.max()
    return out


def jaw_rig(actor: SyntheticActor):
    """The actor's true jaw rig (:class:`lgi.solve.jaw.JawRig`): its hinge and skinning weights."""
    from lgi.solve.jaw import JawRig

    return JawRig(actor.pivot.copy(), actor.jaw_weights.copy())


def default_layout(actor: SyntheticActor):
    """The shipped synthetic marker layout (``data/markers_synth.csv``) attached to this actor.

    The file's neutral positions are snapped to the closest points of the actor's surface, so the layout
    fits an actor of any resolution.

    Returns
    -------
    layout : MarkerLayout
    distance : (M,) float64, cm
        How far each shipped position was from this actor's surface.
    """
    import pandas as pd

    from lgi.dataset.markers import layout_from_points, read_layout

    path = shipped("markers_synth.csv")
    xyz = pd.read_csv(path)[["x", "y", "z"]].to_numpy(float)
    # Snapped in the default actor's space, so a marker sits on the same part of any variant's face.
    return layout_from_points(read_layout(path).names, xyz, actor.x0, actor.triangles)
