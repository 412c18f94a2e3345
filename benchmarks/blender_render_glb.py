"""Import a fitme GLB into Blender headless and render it with Blender's own renderer (Cycles, CPU).

Runs inside Blender's Python (not the venv):

    blender -b --factory-startup --python benchmarks/blender_render_glb.py -- head.glb out.png [SIZE] [SAMPLES]

Three panels side by side: front, three-quarter, and front with the imported shape keys jawOpen = 0.5
and mouthSmileLeft/Right = 0.6 (the glTF morph targets, as Blender's glTF importer names them from
mesh.extras.targetNames). Three-point lighting on a grey world. Prints one line ``FITME_BLENDER {json}``
with what the importer made (vertices, shape keys, material nodes), for `make verify-export` and the
docs. Cycles runs on the CPU (EEVEE needs a GPU context that a headless machine lacks).
"""

import json
import math
import sys

import bpy
import numpy as np
from mathutils import Vector

argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
if len(argv) < 2:
    sys.exit("usage: blender -b --python blender_render_glb.py -- IN.glb OUT.png [SIZE] [SAMPLES]")
glb, out_png = argv[0], argv[1]
size = int(argv[2]) if len(argv) > 2 else 512
samples = int(argv[3]) if len(argv) > 3 else 32

bpy.ops.wm.read_factory_settings(use_empty=True)
# SMOOTH: the importer's default ("NORMALS") uses np.bool, gone from the numpy that Debian ships with Blender 3.4
bpy.ops.import_scene.gltf(filepath=glb, import_shading="SMOOTH")
meshes = [o for o in bpy.context.scene.objects if o.type == "MESH"]
if len(meshes) != 1:
    sys.exit(f"expected one mesh in {glb}, got {len(meshes)}")
head = meshes[0]
keys = head.data.shape_keys.key_blocks if head.data.shape_keys else []
mat = head.active_material
nodes = sorted({n.bl_idname for n in mat.node_tree.nodes}) if mat and mat.use_nodes else []
info = {"vertices": len(head.data.vertices), "polygons": len(head.data.polygons),
        "shape_keys": [k.name for k in keys if k.name != "Basis"], "material": mat.name if mat else None,
        "material_nodes": nodes, "images": sorted(i.name for i in bpy.data.images)}

# frame the head: the importer turned glTF's +Y up into Blender's +Z up, the face looks along -Y
corners = [head.matrix_world @ Vector(c) for c in head.bound_box]
lo = Vector([min(c[i] for c in corners) for i in range(3)])
hi = Vector([max(c[i] for c in corners) for i in range(3)])
centre = (lo + hi) / 2
height = hi.z - lo.z

scene = bpy.context.scene
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = samples
scene.cycles.use_denoising = False  # OpenImageDenoise may be missing from distribution builds
scene.render.resolution_x = scene.render.resolution_y = size
scene.render.film_transparent = False
scene.view_settings.view_transform = "Standard"  # plain sRGB, comparable with fitme render
world = bpy.data.worlds.new("grey")
world.use_nodes = True
world.node_tree.nodes["Background"].inputs[0].default_value = (0.05, 0.05, 0.055, 1.0)
scene.world = world

cam_data = bpy.data.cameras.new("cam")
cam_data.lens = 85
cam = bpy.data.objects.new("cam", cam_data)
scene.collection.objects.link(cam)
scene.camera = cam
dist = height * 85 / 36 * 1.25  # the head's height fills ~80 % of a 36 mm frame at 85 mm


def light(name, kind, energy, direction, colour=(1, 1, 1), size_m=0.3):
    d = bpy.data.lights.new(name, kind)
    d.energy = energy
    d.color = colour
    if kind == "AREA":
        d.size = size_m
    o = bpy.data.objects.new(name, d)
    o.location = centre + Vector(direction).normalized() * dist
    o.rotation_euler = (centre - o.location).to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(o)


light("key", "AREA", 10.0 * dist**2, (-0.6, -1.0, 0.5), (1.0, 0.96, 0.9))
light("fill", "AREA", 3.0 * dist**2, (0.9, -0.8, 0.1), (0.9, 0.95, 1.0))
light("rim", "AREA", 6.0 * dist**2, (0.3, 1.0, 0.8))


def shot(yaw_deg, path):
    a = math.radians(yaw_deg)
    cam.location = centre + Vector((math.sin(a), -math.cos(a), 0.08)) * dist
    cam.rotation_euler = (centre - cam.location).to_track_quat("-Z", "Y").to_euler()
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(path)
    px = np.array(img.pixels[:], np.float32).reshape(size, size, 4)[::-1, :, :3]
    bpy.data.images.remove(img)
    return px


panels = [shot(0, out_png + ".front.png"), shot(35, out_png + ".side.png")]
names = {k.name: k for k in keys}
for k, v in (("jawOpen", 0.5), ("mouthSmileLeft", 0.6), ("mouthSmileRight", 0.6)):
    if k in names:
        names[k].value = v
panels.append(shot(0, out_png + ".expr.png"))

sheet = np.concatenate(panels, 1)
out = bpy.data.images.new("sheet", sheet.shape[1], sheet.shape[0])
out.pixels = np.concatenate([sheet[::-1], np.ones(sheet.shape[:2] + (1,), np.float32)], -1).ravel()
out.filepath_raw = out_png
out.file_format = "PNG"
out.save()
import os

for suffix in (".front.png", ".side.png", ".expr.png"):
    os.remove(out_png + suffix)
print("FITME_BLENDER " + json.dumps(info))
