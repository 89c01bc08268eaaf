"""Exports of reconstructed performances: USD (animated mesh), OpenEXR displacement maps, OBJ sequences.

Every writer works on plain arrays and writes atomically (a temporary name, then a rename).
"""

from __future__ import annotations

import hashlib
import os
from fractions import Fraction
from pathlib import Path
from typing import Any

import numba as nb
import numpy as np

from lgi.dataset.mesh import triangulate
from lgi.errors import InputError
from lgi.export import clips
from lgi.export.clips import USD_CLIP_CONTENTS, usd_clip_dir
from lgi.export.convention import Convention
from lgi.io.atomic import atomic_dir, atomic_file, remove_recorded


def write_usd(
    path: str | os.PathLike[str],
    vertices: np.ndarray,
    face_vertices: np.ndarray,
    face_offsets: np.ndarray,
    uvs: np.ndarray | None = None,
    face_uvs: np.ndarray | None = None,
    frames: np.ndarray | None = None,
    fps: float = 30.0,
    convention: Convention | None = None,
    prim: str = "/Face/mesh",
    clip_frames: int | None = None,
) -> Path:
    """Write an animated mesh as USD (binary ``.usdc``, or text ``.usda``, by extension).

    A shot of more than ``clip_frames`` frames is written as value clips: the file
    and, beside it, the folder :func:`usd_clip_dir` of binary layers of ``clip_frames`` frames each. Composed,
    the stage is the single file's. A shorter shot is one file, and a clip folder an earlier, longer export of
    the same name left is removed.

    Parameters
    ----------
    vertices : (F, V, 3) float, dataset units (cm by default)
        One time sample per frame.
    face_vertices, face_offsets
        Polygons as given (quads stay quads).
    uvs : (T, 2), face_uvs : (N,), optional
        Written as the face-varying primvar ``st`` (seams kept).
    frames : (F,) int, optional
        Time codes (default 0..F-1).
    fps : float
        Time codes per second.
    convention : Convention, optional
        The up axis and units the points are written in and the stage says (default lgi's: Y up, cm).
    clip_frames : int, optional
        Frames per value clip (0: always one file; default :data:`~lgi.export.clips.USD_CLIP_FRAMES`).
    """
    from pxr import Sdf, Usd, UsdGeom, Vt

    frames = np.arange(len(vertices)) if frames is None else np.asarray(frames)
    convention = convention or Convention()
    stage = Usd.Stage.CreateInMemory()
    _stage_convention(stage, convention)
    stage.SetStartTimeCode(float(frames[0]))
    stage.SetEndTimeCode(float(frames[-1]))
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    root = prim.rsplit("/", 1)[0] or "/"
    if root != "/":
        stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, root).GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, prim)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.diff(np.asarray(face_offsets)).astype(np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(face_vertices, np.int32)))
    if uvs is not None and face_uvs is not None:
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                     UsdGeom.Tokens.faceVarying)
        st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(uvs, np.float32)))
        st.SetIndices(Vt.IntArray.FromNumpy(np.asarray(face_uvs, np.int32)))
    points = mesh.CreatePointsAttr()
    extent = mesh.CreateExtentAttr()
    path = Path(path)
    clip_dir = usd_clip_dir(path)
    clip_frames = clips.USD_CLIP_FRAMES if clip_frames is None else clip_frames
    if clip_frames <= 0 or len(frames) <= clip_frames:
        _set_samples(points, extent, frames, vertices, convention)
        with atomic_file(path, suffix=path.suffix or ".usdc") as tmp:
            stage.GetRootLayer().Export(str(tmp))
        remove_recorded(clip_dir, USD_CLIP_CONTENTS, "earlier USD clip folder")  # clips no longer used
        return path
    from pxr import Gf

    spans = [(lo, min(lo + clip_frames, len(frames))) for lo in range(0, len(frames), clip_frames)]
    names = [f"clip_{k:05d}.usdc" for k in range(len(spans))]
    with atomic_dir(clip_dir, USD_CLIP_CONTENTS, "lgi USD clip folder") as tmp_dir:
        for name, (lo, hi) in zip(names, spans, strict=True):
            # One clip's samples in memory at a time: its own stage, written and dropped. It ends with the next
            # clip's first frame, so that a time between the two interpolates as in one file.
            hi = min(hi + 1, len(frames))
            clip = Usd.Stage.CreateInMemory()
            clip_mesh = UsdGeom.Mesh.Define(clip, prim)
            _set_samples(clip_mesh.CreatePointsAttr(), clip_mesh.CreateExtentAttr(), frames[lo:hi],
                         _rows(vertices, lo, hi), convention)
            clip.GetRootLayer().Export(str(tmp_dir / name))
            del clip, clip_mesh
        # The manifest names the attributes the clips animate (USD would otherwise open every clip to learn it).
        manifest = Usd.Stage.CreateInMemory()
        shape = UsdGeom.Mesh.Define(manifest, prim)
        shape.CreatePointsAttr()
        shape.CreateExtentAttr()
        manifest.GetRootLayer().Export(str(tmp_dir / "manifest.usda"))
        api = Usd.ClipsAPI(mesh.GetPrim())
        api.SetClipAssetPaths([Sdf.AssetPath(f"./{clip_dir.name}/{n}") for n in names])
        api.SetClipPrimPath(prim)
        api.SetClipManifestAssetPath(Sdf.AssetPath(f"./{clip_dir.name}/manifest.usda"))
        api.SetClipActive([Gf.Vec2d(float(frames[lo]), k) for k, (lo, _) in enumerate(spans)])
        # Stage time is clip time: the clips keep the frames' own time codes.
        api.SetClipTimes([Gf.Vec2d(float(frames[0]), float(frames[0])), Gf.Vec2d(float(frames[-1]), float(frames[-1]))])
        with atomic_file(path, suffix=path.suffix or ".usdc") as tmp:
            stage.GetRootLayer().Export(str(tmp))
    return path


def _rows(vertices, lo: int, hi: int, block: int = 32):
    """Frames lo .. hi of ``vertices`` (an array or a :class:`~lgi.io.stored.StoredArray`), read ``block`` at a
    time: a clip's frames (320 MB for 1,000 ICT frames) are never read at once beside their USD samples."""
    for a in range(lo, hi, block):
        yield from vertices[a:min(a + block, hi)]


def _stage_convention(stage, convention: Convention) -> None:
    from pxr import UsdGeom

    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if convention.up == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, convention.meters_per_unit)


def stage_convention(stage) -> Convention:
    """The convention a USD stage's metadata states (lgi's writers state one of :class:`Convention`'s)."""
    from pxr import UsdGeom

    up, mpu = UsdGeom.GetStageUpAxis(stage), UsdGeom.GetStageMetersPerUnit(stage)
    units = [u for u in ("cm", "m") if abs(Convention("Y", u).meters_per_unit - mpu) < 1e-9]
    if up not in ("Y", "Z") or not units:
        raise InputError(f"a stage with upAxis {up} and metersPerUnit {mpu} is not in a convention lgi writes")
    return Convention(str(up), units[0])


def usd_convention(path: str | os.PathLike[str]) -> Convention:
    """The convention of the USD file ``path`` (:func:`stage_convention`)."""
    from pxr import Usd

    return stage_convention(Usd.Stage.Open(str(path)))


def _set_samples(points, extent, frames: np.ndarray, vertices, convention: Convention) -> None:
    """One time sample per frame of ``vertices`` (F, V, 3) cm on a mesh's ``points`` and ``extent`` attributes,
    in ``convention``."""
    from pxr import Usd, Vt

    for f, v in zip(frames, vertices, strict=True):
        # Frame by frame, so that a shot read by frame range (lgi.io.npz.npz_member) is never read whole; USD's
        # buffers take aligned float32 only.
        if not convention.native:
            v = convention.points(v)
        v = np.require(v, np.float32, ["C_CONTIGUOUS", "ALIGNED"])
        points.Set(Vt.Vec3fArray.FromNumpy(v), Usd.TimeCode(float(f)))
        extent.Set(Vt.Vec3fArray.FromNumpy(np.stack([v.min(0), v.max(0)])), Usd.TimeCode(float(f)))


@nb.njit(cache=True)
def _rasterize(uv_tri, values_tri, size):  # pragma: no cover - compiled
    """Barycentric rasterisation of per-corner values over UV triangles into a (size, size, 3) image
    (image row 0 at v = 1); returns the image and a coverage mask."""
    img = np.zeros((size, size, 3), np.float32)
    mask = np.zeros((size, size), np.bool_)
    for t in range(uv_tri.shape[0]):
        ax, ay = uv_tri[t, 0, 0] * size, (1 - uv_tri[t, 0, 1]) * size
        bx, by = uv_tri[t, 1, 0] * size, (1 - uv_tri[t, 1, 1]) * size
        cx, cy = uv_tri[t, 2, 0] * size, (1 - uv_tri[t, 2, 1]) * size
        den = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
        if abs(den) < 1e-12:
            continue
        x0 = max(0, int(np.floor(min(ax, bx, cx))))
        x1 = min(size - 1, int(np.ceil(max(ax, bx, cx))))
        y0 = max(0, int(np.floor(min(ay, by, cy))))
        y1 = min(size - 1, int(np.ceil(max(ay, by, cy))))
        for py in range(y0, y1 + 1):
            for px in range(x0, x1 + 1):
                x = px + 0.5
                y = py + 0.5
                l0 = ((by - cy) * (x - cx) + (cx - bx) * (y - cy)) / den
                l1 = ((cy - ay) * (x - cx) + (ax - cx) * (y - cy)) / den
                l2 = 1 - l0 - l1
                if l0 < -1e-6 or l1 < -1e-6 or l2 < -1e-6:
                    continue
                for k in range(3):
                    img[py, px, k] = l0 * values_tri[t, 0, k] + l1 * values_tri[t, 1, k] + l2 * values_tri[t, 2, k]
                mask[py, px] = True
    return img, mask


def displacement_map(
    displacement: np.ndarray, face_vertices: np.ndarray, face_offsets: np.ndarray, uvs: np.ndarray,
    face_uvs: np.ndarray, size: int = 512, tile: tuple[int, int] = (0, 0),
) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex displacements painted in UV space.

    Parameters
    ----------
    displacement : (V, 3) float, cm
        E.g. reconstructed minus neutral positions.
    uvs, face_uvs
        The mesh's texture coordinates (seams kept: each side of a seam paints its own chart).
    size : int
        Image width and height in pixels.
    tile : (u, v) int
        The UDIM-style tile to paint (UVs in [u, u+1) x [v, v+1)).

    Returns
    -------
    image : (size, size, 3) float32 (RGB = x, y, z displacement, cm)
    mask : (size, size) bool, pixels covered by the mesh
    """
    tri_v, _ = triangulate(face_vertices, face_offsets)
    tri_uv, _ = triangulate(face_uvs, face_offsets)
    uv = np.asarray(uvs, np.float64)[tri_uv] - np.asarray(tile, np.float64)
    keep = np.all((uv >= -1e-6) & (uv <= 1 + 1e-6), axis=(1, 2))
    vals = np.asarray(displacement, np.float64)[tri_v][keep]
    return _rasterize(uv[keep], vals, int(size))


def exr_header(convention: Convention, neutral_name: str, neutral: np.ndarray, fps: float) -> dict[str, Any]:
    """The header attributes of lgi's displacement maps (:func:`write_exr`; each map adds its ``lgi:frame``).

    ``lgi:content`` says what the pixels are; ``lgi:units`` (``cm`` or ``m``) and ``lgi:upAxis`` (``Y`` or ``Z``)
    the convention of the displacement vectors (RGB = x, y, z); ``lgi:neutral`` names the neutral they are
    measured from (the index's folder name) and ``lgi:neutralSha256`` is the SHA-256 of that neutral's vertex
    positions as little-endian float32 (V, 3), cm, Y up, the index's own; ``framesPerSecond`` (the standard
    rational attribute) the shot's rate.

    Parameters
    ----------
    neutral : (V, 3) float, cm
    fps : float, frames per second
    """
    digest = hashlib.sha256(np.ascontiguousarray(neutral, "<f4").tobytes()).hexdigest()
    return {"lgi:content": "displacement of the reconstructed face from the neutral, per texel of its UV layout "
                           "(RGB = x, y, z)",
            "lgi:units": convention.units, "lgi:upAxis": convention.up, "lgi:neutral": neutral_name,
            "lgi:neutralSha256": digest, "framesPerSecond": Fraction(fps).limit_denominator(1001)}


def write_exr(path: str | os.PathLike[str], image: np.ndarray, attributes: dict[str, Any] | None = None) -> Path:
    """Write an (H, W, 3) float32 image as an OpenEXR RGB file (ZIP compression), atomically, with the header
    ``attributes`` (strings, ints, floats, fractions) beside the required ones."""
    import OpenEXR

    path = Path(path)
    pixels = np.ascontiguousarray(np.asarray(image, np.float32))  # strided views are written wrongly
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(attributes or {})}
    with atomic_file(path, suffix=".exr") as tmp:
        OpenEXR.File(header, {"RGB": pixels}).write(str(tmp))
    return path


def read_exr(path: str | os.PathLike[str]) -> np.ndarray:
    """(H, W, 3) float32 RGB pixels of an OpenEXR file."""
    import OpenEXR

    ch = OpenEXR.File(str(path)).channels()
    if "RGB" in ch:
        return np.asarray(ch["RGB"].pixels)
    return np.stack([np.asarray(ch[c].pixels) for c in "RGB"], axis=-1)


def usd_name(name: str) -> str:
    """A valid USD prim name for a shape name (``jaw_open+smile_L`` -> ``jaw_open__smile_L``)."""
    out = "".join(c if c.isalnum() or c == "_" else "_" for c in name.replace("+", "__"))
    return out if out and not out[0].isdigit() else "_" + out


def write_usd_rig(
    path: str | os.PathLike[str],
    neutral: np.ndarray,
    face_vertices: np.ndarray,
    face_offsets: np.ndarray,
    names: list[str],
    deltas: np.ndarray,
    combinations: list[tuple[str, ...] | None],
    uvs: np.ndarray | None = None,
    face_uvs: np.ndarray | None = None,
    convention: Convention | None = None,
    jaw_rig=None,
    jaw_parameters: np.ndarray | None = None,
) -> Path:
    """Write a blendshape rig as UsdSkel: the neutral mesh with one BlendShape target per shape.

    Layout: ``/Rig`` (SkelRoot) holds ``Skel`` (a one-joint Skeleton whose ``Anim`` (SkelAnimation) lists
    the blend shapes with weights 0) and ``Face`` (the Mesh, bound to the skeleton, with ``skel:blendShapes``
    and ``skel:blendShapeTargets`` pointing at ``Face/<name>`` BlendShape prims holding the offsets).
    UsdSkel has no combination driver, so a corrective is a target like any other, carrying
    ``lgi:combination`` (its controls' blend-shape names, as in ``skel:blendShapes``, for a DCC to drive its
    weight by the product of theirs) and
    ``lgi:kind`` ("control" or "corrective"); every target keeps its original name in ``lgi:name``.

    With ``jaw_rig`` (:class:`lgi.solve.jaw.JawRig`) the skeleton has two joints, ``root`` (the head, fixed)
    and ``root/jaw``, and the mesh is bound to both with weights ``[1 - w, w]`` (``w`` the jaw rig's skinning
    weight, ``elementSize`` 2): the jaw joint's bind and rest transforms put it at the hinge (a translation to
    the pivot), so an animated jaw transform ``[R | pivot + forward z]`` makes UsdSkel's linear blend skinning
    ``lgi.solve.jaw.JawRig.skin`` exactly (:func:`lgi.export.rig_anim.jaw_joint_transform`). The offsets are
    then unskinned (the jaw closed), since UsdSkel applies blend shapes before skinning; each target carries
    its shape's jaw pose in ``lgi:jaw`` (open, yaw, roll in degrees, forward in cm) when ``jaw_parameters``
    is given.

    Parameters
    ----------
    neutral : (V, 3) float, cm
    names : list of str, K shape names
    deltas : (K, V, 3) float, cm: each target's offsets
    combinations : K entries: None for a control, its controls' names for a corrective
    jaw_rig : JawRig, optional
        Pivot (3,) cm and weights (V,).
    jaw_parameters : (K, 4) float, optional
        Each shape's jaw pose (metadata for a DCC that drives the joint from a control).
    convention : Convention, optional
        The up axis and units of the geometry, the joints and the stage (default lgi's: Y up, cm). The jaw
        poses in ``lgi:jaw`` stay lgi's parameters (degrees, cm), whatever the convention.
    """
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

    convention = convention or Convention()
    neutral = convention.points(neutral)
    deltas = convention.points(deltas)
    stage = Usd.Stage.CreateInMemory()
    _stage_convention(stage, convention)
    root = UsdSkel.Root.Define(stage, "/Rig")
    stage.SetDefaultPrim(root.GetPrim())
    skel = UsdSkel.Skeleton.Define(stage, "/Rig/Skel")
    tokens = [usd_name(n) for n in names]
    if len(set(tokens)) != len(tokens):
        raise InputError("shape names collide once made valid USD names")
    anim = UsdSkel.Animation.Define(stage, "/Rig/Skel/Anim")
    anim.CreateBlendShapesAttr(Vt.TokenArray(tokens))
    anim.CreateBlendShapeWeightsAttr(Vt.FloatArray([0.0] * len(tokens)))
    if jaw_rig is None:
        skel.CreateJointsAttr(Vt.TokenArray(["root"]))
        skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
        skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
        # blend-shape weights only; the joint stays at rest
    else:
        pivot = convention.points(jaw_rig.pivot, np.float64)
        at_hinge = Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(*pivot.tolist()))
        joints = Vt.TokenArray(["root", "root/jaw"])
        skel.CreateJointsAttr(joints)
        # The root is the head at the origin; the jaw's bind (world) and rest (local) transforms both sit at the
        # hinge, so its skinning transform inverse(bind) * animated is the hinge motion of lgi's jaw rig.
        skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0), at_hinge]))
        skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0), at_hinge]))
        anim.CreateJointsAttr(joints)
        anim.CreateTranslationsAttr(Vt.Vec3fArray([Gf.Vec3f(0.0), Gf.Vec3f(*pivot.tolist())]))
        anim.CreateRotationsAttr(Vt.QuatfArray([Gf.Quatf(1.0), Gf.Quatf(1.0)]))
        anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1.0), Gf.Vec3h(1.0)]))
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])

    mesh = UsdGeom.Mesh.Define(stage, "/Rig/Face")
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.diff(np.asarray(face_offsets)).astype(np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(face_vertices, np.int32)))
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(neutral)))
    mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([neutral.min(0), neutral.max(0)])))
    if uvs is not None and face_uvs is not None:
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                     UsdGeom.Tokens.faceVarying)
        st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(uvs, np.float32)))
        st.SetIndices(Vt.IntArray.FromNumpy(np.asarray(face_uvs, np.int32)))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    if jaw_rig is None:
        # Rigidly bound to the one joint (identity): the mesh moves only by its blend shapes.
        binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
        binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
    else:
        w = np.asarray(jaw_rig.weights, np.float64)
        if w.shape != (len(neutral),):
            raise ValueError(f"{w.shape} jaw weights for {len(neutral)} vertices")
        binding.CreateJointIndicesPrimvar(False, 2).Set(
            Vt.IntArray.FromNumpy(np.tile(np.array([0, 1], np.int32), len(w))))
        binding.CreateJointWeightsPrimvar(False, 2).Set(
            Vt.FloatArray.FromNumpy(np.stack([1.0 - w, w], axis=1).astype(np.float32).ravel()))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    binding.CreateBlendShapesAttr(Vt.TokenArray(tokens))
    targets = []
    poses = [None] * len(names) if jaw_parameters is None else np.asarray(jaw_parameters, np.float64)
    for name, token, delta, combo, pose in zip(names, tokens, np.asarray(deltas, np.float32), combinations, poses,
                                               strict=True):
        bs = UsdSkel.BlendShape.Define(stage, f"/Rig/Face/{token}")
        bs.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(delta)))
        prim = bs.GetPrim()
        prim.CreateAttribute("lgi:name", Sdf.ValueTypeNames.String).Set(name)
        prim.CreateAttribute("lgi:kind", Sdf.ValueTypeNames.Token).Set("control" if combo is None else "corrective")
        if combo is not None:
            prim.CreateAttribute("lgi:combination", Sdf.ValueTypeNames.TokenArray).Set(
                Vt.TokenArray([usd_name(c) for c in combo]))
        if pose is not None:
            prim.CreateAttribute("lgi:jaw", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*pose.tolist()))
        targets.append(bs.GetPath())
    binding.CreateBlendShapeTargetsRel().SetTargets(targets)
    path = Path(path)
    with atomic_file(path, suffix=path.suffix or ".usda") as tmp:
        stage.GetRootLayer().Export(str(tmp))
    return path
