"""A solved shot as a UsdSkel animation of the actor's rig (``lgi rig-solve --usd``).

The animation is a layer of its own that sublayers the rig's USD (``lgi rig-generate --usd``) and gives the
rig's SkelAnimation (``/Rig/Skel/Anim``) time samples of every blend shape's weight and, for a rig with a jaw
joint, of the joints' translations and rotations (the jaw's from lgi's jaw parameters,
:func:`jaw_joint_transform`; the root's at rest): a DCC opening it plays the shot on the rig, and the rig file
stays as it is. UsdSkel has no combination driver, so each corrective's weight is written as the product of its
controls' (what the rig's ``lgi:combination`` says).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lgi.errors import InputError
from lgi.io.atomic import atomic_file

ANIM_PATH = "/Rig/Skel/Anim"
MESH_PATH = "/Rig/Face"


def jaw_joint_transform(params: np.ndarray, pivot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The jaw joint's local transform for jaw parameters, as UsdSkel's SkelAnimation holds it.

    lgi's jaw motion is ``M = jaw_matrix(params, pivot)`` (a rotation ``R`` about the pivot, then the slide along
    +z). The rig's jaw joint is bound at the hinge (bind transform ``T(pivot)``) under a root at the origin, so
    its skinning transform is ``M`` when its world (= local) transform is ``M T(pivot) = [R | M pivot]``: the
    rotation ``R`` and the translation ``R pivot + M[:3, 3]`` (the pivot plus the slide).

    Parameters
    ----------
    params : (F, 4) float: open, yaw, roll (degrees), forward (cm)
    pivot : (3,) float, cm

    Returns
    -------
    translations : (F, 3) float64, cm
    rotations : (F, 4) float64: unit quaternions (w, x, y, z), w >= 0
    """
    from scipy.spatial.transform import Rotation

    from lgi.solve.jaw import jaw_matrix

    params = np.asarray(params, np.float64).reshape(-1, 4)
    pivot = np.asarray(pivot, np.float64).reshape(3)
    m = np.stack([jaw_matrix(p, pivot) for p in params]) if len(params) else np.zeros((0, 4, 4))
    trans = m[:, :3, :3] @ pivot + m[:, :3, 3]
    xyzw = Rotation.from_matrix(m[:, :3, :3]).as_quat() if len(params) else np.zeros((0, 4))
    quat = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    quat *= np.where(quat[:, :1] < 0, -1.0, 1.0)
    return trans, quat


def check_rig_usd(path: str | os.PathLike[str], names: list[str], neutral: np.ndarray, deltas: np.ndarray,
                  tol_cm: float = 1e-4, jaw=None) -> None:
    """Refuse a rig USD that is not the rig dataset's: its blend shapes (names and order), mesh size, neutral or
    offsets differ (more than ``tol_cm``), or its skeleton is not the dataset's (a jaw joint at the jaw rig's
    pivot with its weights when the dataset has a jaw rig, the single fixed joint when not).

    Parameters
    ----------
    names : K + P shape names, in the dataset's order
    neutral : (V, 3) float, cm
    deltas : (K + P, V, 3) float, cm
    jaw : JawRig, optional
        The rig dataset's jaw rig.
    """
    from pxr import Usd, UsdGeom, UsdSkel

    from lgi.export.formats import stage_convention, usd_name

    p = Path(path)
    if not p.is_file():
        raise InputError("rig USD file not found", path=p)
    try:
        stage = Usd.Stage.Open(str(p))
    except Exception as exc:  # noqa: BLE001 - pxr raises its own Tf errors for unreadable files
        raise InputError(f"not a readable USD file ({exc})", path=p) from None
    try:
        conv = stage_convention(stage)
    except ValueError as exc:
        raise InputError(str(exc), path=p) from None
    # The dataset's geometry as the USD holds it (its up axis and units), compared in centimetres.
    neutral = conv.points(neutral, np.float64)
    tol = tol_cm * conv.scale
    mesh = stage.GetPrimAtPath(MESH_PATH)
    anim = UsdSkel.Animation(stage.GetPrimAtPath(ANIM_PATH))
    if not mesh or not anim:
        raise InputError(f"no {MESH_PATH} mesh and {ANIM_PATH} SkelAnimation: not a rig written by lgi rig-generate "
                         "--usd", path=p)
    tokens = [usd_name(n) for n in names]
    have = list(UsdSkel.BindingAPI(mesh).GetBlendShapesAttr().Get() or [])
    if have != tokens or list(anim.GetBlendShapesAttr().Get() or []) != tokens:
        raise InputError(f"its blend shapes ({len(have)}: {', '.join(have[:4])}...) are not the rig dataset's "
                         f"({len(tokens)}: {', '.join(tokens[:4])}...): the USD belongs to another rig", path=p)
    points = np.asarray(UsdGeom.Mesh(mesh).GetPointsAttr().Get(), np.float64)
    if points.shape != np.shape(neutral):
        raise InputError(f"its mesh has {len(points)} points, the rig dataset {len(neutral)} vertices", path=p)
    off = float(np.abs(points - neutral).max(initial=0.0))
    if off > tol:
        raise InputError(f"its neutral is {off / conv.scale * 10:.3g} mm from the rig dataset's: the USD belongs to "
                         "another rig", path=p)
    _check_joints(stage, p, mesh, jaw, len(neutral), tol, conv)
    targets = UsdSkel.BindingAPI(mesh).GetBlendShapeTargetsRel().GetTargets()
    for i, t in enumerate(targets):
        o = np.asarray(UsdSkel.BlendShape(stage.GetPrimAtPath(t)).GetOffsetsAttr().Get(), np.float64)
        if o.shape != np.shape(deltas[i]) or float(np.abs(o - conv.points(deltas[i], np.float64)).max(
                initial=0.0)) > tol:
            raise InputError(f"blend shape {tokens[i]!r} differs from the rig dataset's shape {names[i]!r}: the USD "
                             "belongs to another rig", path=p)


def _check_joints(stage, p: Path, mesh, jaw, n_vertices: int, tol: float, conv) -> None:
    """The skeleton part of :func:`check_rig_usd` (``tol`` in the stage's units, ``conv`` its convention)."""
    from pxr import UsdSkel

    skel = UsdSkel.Skeleton(stage.GetPrimAtPath("/Rig/Skel"))
    joints = list(skel.GetJointsAttr().Get() or []) if skel else []
    if jaw is None:
        if joints != ["root"]:
            raise InputError(f"its skeleton has the joints {joints}, the rig dataset has no jaw rig (one fixed joint, "
                             "'root'): the USD belongs to another rig", path=p)
        return
    if joints == ["root"]:
        raise InputError("its skeleton has a single fixed joint, but the rig dataset has a jaw rig (a 'root/jaw' "
                         "joint): the USD was written before the jaw became the rig's joint, or belongs to another "
                         "rig; write it again with lgi rig-generate --usd", path=p)
    if joints != ["root", "root/jaw"]:
        raise InputError(f"its skeleton has the joints {joints}, not ['root', 'root/jaw']: not a rig written by lgi "
                         "rig-generate --usd", path=p)
    bind = skel.GetBindTransformsAttr().Get()
    at = np.asarray(bind[1].ExtractTranslation(), np.float64) if bind is not None and len(bind) == 2 else None
    if at is None or float(np.abs(at - conv.points(jaw.pivot, np.float64)).max()) > tol:
        raise InputError("its jaw joint is not bound at the rig dataset's jaw pivot: the USD belongs to another rig",
                         path=p)
    binding = UsdSkel.BindingAPI(mesh)
    weights = np.asarray(binding.GetJointWeightsPrimvar().Get() or [], np.float64)
    if weights.shape != (2 * n_vertices,) or float(np.abs(weights[1::2] - jaw.weights).max()) > 1e-6:
        raise InputError("its jaw skinning weights are not the rig dataset's: the USD belongs to another rig", path=p)


def write_rig_animation(path: str | os.PathLike[str], rig_usd: str | os.PathLike[str], weights: np.ndarray,
                        frames: np.ndarray | None = None, fps: float = 30.0, jaw: np.ndarray | None = None,
                        pivot: np.ndarray | None = None) -> Path:
    """Write the animation layer.

    Parameters
    ----------
    path : the animation (.usda / .usdc / .usd)
    rig_usd : the rig's USD, sublayered (by a path relative to ``path``'s folder when it can be)
    weights : (F, K + P) float: every blend shape's weight per frame, in the rig's blend-shape order
    frames : (F,) int time codes (default 0..F-1)
    fps : time codes per second
    jaw : (F, 4) float, optional: the jaw parameters per frame (open, yaw, roll deg, forward cm), for a rig with a
        jaw joint
    pivot : (3,) float, cm: the jaw rig's pivot (with ``jaw``)
    """
    from pxr import Sdf, Usd, UsdGeom, Vt

    from lgi.export.formats import stage_convention

    path = Path(path)
    weights = np.asarray(weights, np.float32)
    frames = np.arange(len(weights)) if frames is None else np.asarray(frames)
    try:
        ref = os.path.relpath(Path(rig_usd).resolve(), path.resolve().parent)
    except ValueError:  # another drive
        ref = str(Path(rig_usd).resolve())
    layer = Sdf.Layer.CreateAnonymous(path.suffix or ".usda")
    # Composed with the absolute path (an anonymous layer has no folder to resolve a relative one from); the
    # file keeps the relative one, so the shot and its rig can move together.
    layer.subLayerPaths.append(str(Path(rig_usd).resolve()))
    stage = Usd.Stage.Open(layer)
    layer.defaultPrim = "Rig"
    # Stage metadata is read from the root layer only: repeat the rig's units and axis.
    rig_stage = Usd.Stage.Open(str(rig_usd))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.GetStageUpAxis(rig_stage))
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.GetStageMetersPerUnit(rig_stage))
    try:
        convention = stage_convention(rig_stage)
    except ValueError as exc:
        raise InputError(str(exc), path=rig_usd) from None
    stage.SetStartTimeCode(float(frames[0]))
    stage.SetEndTimeCode(float(frames[-1]))
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    attr = stage.OverridePrim(ANIM_PATH).GetAttribute("blendShapeWeights")
    if not attr:
        raise InputError(f"the rig USD has no {ANIM_PATH}.blendShapeWeights", path=rig_usd)
    for f, w in zip(frames, weights, strict=True):
        attr.Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(w)), Usd.TimeCode(float(f)))
    if jaw is not None:
        from pxr import Gf

        over = stage.OverridePrim(ANIM_PATH)
        trans_attr, rot_attr = over.GetAttribute("translations"), over.GetAttribute("rotations")
        if not trans_attr or not rot_attr:
            raise InputError(f"the rig USD's {ANIM_PATH} has no joint translations and rotations (no jaw joint)",
                             path=rig_usd)
        # The joint moves in the rig's convention (lgi's jaw parameters are about lgi's axes, in cm).
        trans, quat = jaw_joint_transform(jaw, pivot)
        trans, quat = convention.points(trans, np.float64), convention.quaternions(quat)
        # Only the jaw is animated: the root (the head) stays at its rest transform, unkeyed (lgi's meshes are in
        # the head's frame, its motion removed), so a DCC keys one bone, not two.
        over.GetAttribute("joints").Set(Vt.TokenArray(["root/jaw"]))
        scales = over.GetAttribute("scales")
        if scales:
            scales.Set(Vt.Vec3hArray([Gf.Vec3h(1.0)]))
        for f, t, q in zip(frames, trans, quat, strict=True):
            trans_attr.Set(Vt.Vec3fArray([Gf.Vec3f(*t.tolist())]), Usd.TimeCode(float(f)))
            rot_attr.Set(Vt.QuatfArray([Gf.Quatf(*q.tolist())]), Usd.TimeCode(float(f)))
    del stage
    layer.subLayerPaths[0] = ref
    with atomic_file(path, suffix=path.suffix or ".usda") as tmp:
        layer.Export(str(tmp))
    return path


def usd_playback(path: str | os.PathLike[str], frames: list[float]) -> np.ndarray:
    """(len(frames), V, 3) float64: the rig's mesh as UsdSkel bakes it (``UsdSkel.BakeSkinning``: blend shapes,
    then skinning) at each time code, read back from the file: what a DCC shows. The file is not changed (the
    bake goes to the stage's session layer)."""
    from pxr import Gf, Usd, UsdGeom, UsdSkel

    stage = Usd.Stage.Open(str(path))
    session = stage.GetSessionLayer()
    # A layer's time codes are scaled by the root layer's rate over its own (default 24): give the bake's layer
    # the shot's rate, or its samples land at other times.
    session.timeCodesPerSecond = stage.GetRootLayer().timeCodesPerSecond
    session.framesPerSecond = stage.GetRootLayer().framesPerSecond
    stage.SetEditTarget(session)
    times = [float(t) for t in frames]
    if not UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetPrimAtPath("/Rig")), Gf.Interval(min(times), max(times))):
        raise RuntimeError(f"UsdSkel.BakeSkinning failed on {path}")
    points = UsdGeom.Mesh(stage.GetPrimAtPath(MESH_PATH)).GetPointsAttr()
    return np.stack([np.asarray(points.Get(Usd.TimeCode(t)), np.float64) for t in times])


def validate_usd(path: str | os.PathLike[str]) -> list[str]:
    """Errors UsdValidation's registered validators find on the stage (empty: valid)."""
    from pxr import Usd, UsdValidation

    stage = Usd.Stage.Open(str(path))
    reg = UsdValidation.ValidationRegistry()
    validators = reg.GetOrLoadAllValidators()
    ctx = UsdValidation.ValidationContext(validators)
    errors = ctx.Validate(stage)
    return [f"{e.GetName()}: {e.GetMessage()}" for e in errors
            if e.GetType() == UsdValidation.ValidationErrorType.Error]
