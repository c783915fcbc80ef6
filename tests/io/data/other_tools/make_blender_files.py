"""Writes small files with Blender's own exporters, and what Blender says they hold.

Run: blender --background --factory-startup --python make_files.py -- OUTDIR
"""
import json
import sys
from pathlib import Path

import addon_utils
import bpy

out = Path(sys.argv[sys.argv.index("--") + 1])
out.mkdir(parents=True, exist_ok=True)
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.render.fps = 24
scene.frame_start, scene.frame_end = 1, 8

bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=1, radius=1.0)
obj = bpy.context.active_object
obj.name = "Face"
obj.data.name = "FaceMesh"
obj.location = (0.5, -2.0, 3.0)
obj.rotation_euler = (0.3, 0.0, 0.7)
obj.scale = (2.0, 2.0, 2.0)
basis = obj.shape_key_add(name="Basis")
keys = {}
for name, axis in (("jawOpen", 2), ("smile", 0)):
    key = obj.shape_key_add(name=name, from_mix=False)
    for i, v in enumerate(key.data):
        co = list(basis.data[i].co)
        co[axis] += 0.1 * (i % 5) + 0.05
        v.co = co
    keys[name] = key
weights = {}
for f in range(1, 9):
    w = {"jawOpen": (f - 1) / 7.0, "smile": 1.0 - (f - 1) / 7.0 if f > 2 else 0.0}
    weights[f] = w
    for name, value in w.items():
        keys[name].value = value
        keys[name].keyframe_insert("value", frame=f)
scene.frame_set(1)


def evaluated(frame):
    scene.frame_set(frame)
    dg = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(dg)
    mesh = ev.to_mesh()
    m = obj.matrix_world
    pts = [list(m @ v.co) for v in mesh.vertices]
    ev.to_mesh_clear()
    return pts


def y_up(p):  # glTF / OBJ "Y up" convention of Blender's exporters: (x, z, -y)
    return [p[0], p[2], -p[1]]


truth = {
    "blender": bpy.app.version_string,
    "fps": scene.render.fps,
    "n_vertices": len(obj.data.vertices),
    "triangles": [list(p.vertices) for p in obj.data.polygons],
    "shape_names": ["jawOpen", "smile"],
    "weights": [[weights[f]["jawOpen"], weights[f]["smile"]] for f in range(1, 9)],
    "world_z_up": {str(f): evaluated(f) for f in range(1, 9)},
}
truth["world_y_up"] = {f: [y_up(p) for p in pts] for f, pts in truth["world_z_up"].items()}
for k in keys.values():
    k.value = 0.0
scene.frame_set(1)

bpy.ops.export_scene.gltf(filepath=str(out / "blender_face.glb"), export_format="GLB", export_morph=True, export_animations=True,
                          export_apply=False, export_yup=True)
bpy.ops.wm.obj_export(filepath=str(out / "blender_face.obj"), export_selected_objects=False, export_uv=False, export_normals=False,
                      export_materials=False, apply_modifiers=True, forward_axis="NEGATIVE_Z", up_axis="Y", export_animation=False)
bpy.ops.export_mesh.ply(filepath=str(out / "blender_face.ply"), use_normals=False, use_uv_coords=False, use_colors=False, axis_forward="-Z", axis_up="Y")
exported = {}
for module, op in (("io_export_pc2", "pc2"), ("io_shape_mdd", "mdd")):
    try:
        addon_utils.enable(module, default_set=True)
    except Exception as exc:  # not shipped with this Blender
        exported[op] = f"addon {module} unavailable: {exc}"
try:
    bpy.ops.export_shape.pc2(filepath=str(out / "blender_face.pc2"), world_space=True, rot_x90=True, range_start=1, range_end=8, sampling="1")
    exported["pc2"] = "ok"
except Exception as exc:
    exported["pc2"] = repr(exc)
try:
    bpy.ops.export_shape.mdd(filepath=str(out / "blender_face.mdd"), fps=24, frame_start=1, frame_end=8)
    exported["mdd"] = "ok"
except Exception as exc:
    exported["mdd"] = repr(exc)
truth["exported"] = exported
(out / "blender_face.truth.json").write_text(json.dumps(truth))

# head motion: the face keyframed in rotation and location, under a rotated, moved parent
bpy.ops.object.empty_add(location=(1.0, 2.0, 0.5), rotation=(0.0, 0.4, 0.2))
rig_parent = bpy.context.active_object
rig_parent.name = "Head"
obj.parent = rig_parent
for f in range(1, 9):
    scene.frame_set(f)
    obj.rotation_euler = (0.3 + 0.05 * f, 0.02 * f, 0.7)
    obj.location = (0.5 + 0.1 * f, -2.0, 3.0 - 0.05 * f)
    obj.keyframe_insert("rotation_euler", frame=f)
    obj.keyframe_insert("location", frame=f)
head = {"world_y_up": {str(f): [y_up(p) for p in evaluated(f)] for f in range(1, 9)}, "weights": truth["weights"], "fps": scene.render.fps}
scene.frame_set(1)
bpy.ops.export_scene.gltf(filepath=str(out / "blender_head.glb"), export_format="GLB", export_morph=True, export_animations=True,
                          export_apply=False, export_yup=True)
(out / "blender_head.truth.json").write_text(json.dumps(head))
print("WROTE", exported)
