"""Run inside Blender's Python (bpy): import a USD through the script lgi wrote beside it, and report what Blender
shows, as JSON. tests/test_blender.py runs it and compares the figures with lgi's own.

    python blender_check.py SCRIPT FRAMES OUT_JSON [CONTROL]

FRAMES: comma-separated frames. With CONTROL (a control shape key of a rig): its animation is muted, its value
set to 1 and then 0.5 at the first frame, and every shape key's value read after each, to show whether the
correctives follow it.
"""

import json
import sys

import bpy
import numpy as np


def evaluated_keys(ob, dg):
    keys = ob.evaluated_get(dg).data.shape_keys or ob.data.shape_keys
    return {k.name: float(k.value) for k in keys.key_blocks[1:]} if keys else {}


def main():
    script, frames, out = sys.argv[1], [int(f) for f in sys.argv[2].split(",")], sys.argv[3]
    control = sys.argv[4] if len(sys.argv) > 4 else None
    bpy.ops.wm.read_factory_settings(use_empty=True)
    code = compile(open(script).read(), script, "exec")
    exec(code, {"__file__": script, "__name__": "__main__"})
    scene = bpy.context.scene
    mesh = [o for o in bpy.data.objects if o.type == "MESH"][0]
    arm = [o for o in bpy.data.objects if o.type == "ARMATURE"]
    report = {"fps": scene.render.fps / scene.render.fps_base, "range": [scene.frame_start, scene.frame_end],
              "scale": list(mesh.matrix_world.to_scale()), "frames": {}}
    if arm and arm[0].animation_data and arm[0].animation_data.action:
        report["bone_curves"] = sorted({fc.data_path.split('"')[1] for fc in arm[0].animation_data.action.fcurves
                                        if fc.data_path.startswith("pose.bones")})
    for f in frames:
        scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        ev = mesh.evaluated_get(dg)
        me = ev.to_mesh()
        co = np.empty(len(me.vertices) * 3)
        me.vertices.foreach_get("co", co)
        mw = np.array(ev.matrix_world)
        ev.to_mesh_clear()
        row = {"vertices": (co.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3]).tolist(), "keys": evaluated_keys(mesh, dg)}
        if arm:
            pb = arm[0].evaluated_get(dg).pose.bones.get("jaw")
            if pb is not None:
                rest = pb.bone.matrix_local.to_3x3()
                posed = pb.matrix.to_3x3()
                row["jaw_rotation"] = [list(r) for r in (rest.inverted() @ posed)]
        report["frames"][f] = row
    if control:
        keys = mesh.data.shape_keys
        action = keys.animation_data.action
        for fc in action.fcurves:
            if fc.data_path == f'key_blocks["{control}"].value':
                fc.mute = True
        report["follow"] = []
        for value in (1.0, 0.5):
            keys.key_blocks[control].value = value
            scene.frame_set(frames[0])
            keys.key_blocks[control].value = value
            dg = bpy.context.evaluated_depsgraph_get()
            dg.update()
            report["follow"].append({"value": value, "keys": evaluated_keys(mesh, dg)})
    with open(out, "w") as fh:
        json.dump(report, fh)


main()
