"""A Blender import script beside a USD written in Blender's convention (Z up, metres).

Blender 4.2's USD importer reads the geometry, the skeleton and the blend shapes right, but not what USD cannot
say to it: the scene keeps its own frame rate (a 30 fps file plays at 24), and a corrective blend shape is
imported as one more baked curve, which a control moved by hand leaves behind (UsdSkel has no combination
driver; lgi writes the combination as ``lgi:combination``, which no importer reads). The script imports the file
with scale 1, sets the scene's frame rate and range, and drives each corrective shape key by the product of its
controls' values, as lgi's rig evaluates it (the drivers are simple expressions, which Blender evaluates
without running Python in the file).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from lgi.export.convention import DCC_PRESETS, Convention
from lgi.io.atomic import atomic_file

SUFFIX = ".blender.py"


def script_path(usd: str | os.PathLike[str]) -> Path:
    """The script beside ``usd``: ``NAME.blender.py`` (NAME without its extension)."""
    p = Path(usd)
    return p.with_name(p.stem + SUFFIX)


def for_blender(convention: Convention) -> bool:
    """True for Blender's convention (``--dcc blender``), whose USD files get a script."""
    return (convention.up, convention.units) == DCC_PRESETS["blender"]


_TEMPLATE = '''"""Import {name} into Blender as lgi wrote it: Scripting > Open this file > Run Script, or
    blender --python {script}
The file is imported with scale 1 (it is in metres, Z up), the scene's frame rate set to {fps:g} fps and its range
to the file's frames ({first}-{last}), a bone that never moves left unkeyed, and each corrective shape key driven by
the product of its controls'."""

import os

import bpy

USD = {usd!r}
FPS = {fps!r}
FIRST, LAST = {first}, {last}
# corrective shape key -> the control shape keys whose product drives it
CORRECTIVES = {correctives}


def _usd_path():
    here = globals().get("__file__")
    local = os.path.join(os.path.dirname(os.path.abspath(here)), os.path.basename(USD)) if here else None
    return local if local and os.path.isfile(local) else USD


def main():
    before = set(bpy.data.objects)
    bpy.ops.wm.usd_import(filepath=_usd_path(), scale=1.0, set_frame_range=True)
    scene = bpy.context.scene
    scene.render.fps = max(1, round(FPS))
    scene.render.fps_base = scene.render.fps / FPS
    scene.frame_start, scene.frame_end = FIRST, LAST
    for ob in set(bpy.data.objects) - before:
        action = ob.animation_data.action if ob.type == "ARMATURE" and ob.animation_data else None
        if action is not None:
            # The importer keys every bone on every frame; a bone that never moves (the head's root) keeps none.
            for fc in [fc for fc in action.fcurves if fc.data_path.startswith("pose.bones")]:
                values = [k.co[1] for k in fc.keyframe_points]
                if values and max(values) - min(values) == 0.0:
                    action.fcurves.remove(fc)
        keys = ob.data.shape_keys if ob.type == "MESH" else None
        if keys is None:
            continue
        for name, parts in CORRECTIVES.items():
            if name not in keys.key_blocks or any(p not in keys.key_blocks for p in parts):
                continue
            driver = keys.driver_add('key_blocks["%s"].value' % name).driver
            driver.type = "SCRIPTED"
            for i, part in enumerate(parts):
                var = driver.variables.new()
                var.name, var.type = "w%d" % i, "SINGLE_PROP"
                var.targets[0].id_type = "KEY"
                var.targets[0].id = keys
                var.targets[0].data_path = 'key_blocks["%s"].value' % part
            driver.expression = " * ".join("w%d" % i for i in range(len(parts)))


main()
'''


def usd_correctives(rig) -> dict[str, list[str]]:
    """Each corrective of ``rig`` (:class:`lgi.retarget.solve.BlendRig`) -> its controls, by their USD names."""
    from lgi.export.formats import usd_name

    return {usd_name(n): [usd_name(rig.controls[c]) for c in combo]
            for n, combo in zip(rig.corrective_names, rig.combinations, strict=True)}


def blender_script(usd: str | os.PathLike[str], fps: float, first: int, last: int,
                   correctives: dict[str, list[str]] | None = None) -> str:
    """The script's text for the USD file ``usd`` (found beside the script, else at its absolute path).

    Parameters
    ----------
    fps : frames per second of the shot
    first, last : the shot's first and last frame
    correctives : corrective blend shape -> its controls (USD names, as ``skel:blendShapes`` spells them)
    """
    usd = Path(usd)
    table = "".join(f"\n    {json.dumps(k)}: {json.dumps(list(v))}," for k, v in (correctives or {}).items())
    return _TEMPLATE.format(name=usd.name, script=script_path(usd).name, usd=str(usd.resolve()), fps=float(fps),
                            first=int(first), last=int(last), correctives="{" + table + ("\n}" if table else "}"))


def write_blender_script(usd: str | os.PathLike[str], fps: float, first: int, last: int,
                         correctives: dict[str, list[str]] | None = None,
                         path: str | os.PathLike[str] | None = None) -> Path:
    """Write :func:`blender_script` to ``path`` (default :func:`script_path` of ``usd``; a job's staging folder
    names its own), atomically; returns its path."""
    path = script_path(usd) if path is None else Path(path)
    with atomic_file(path, suffix=".py") as tmp:
        Path(tmp).write_text(blender_script(usd, fps, first, last, correctives))
    return path
