"""A Blender Python script that builds the exported scene: the world (the envmap as an Environment Texture,
whose default equirectangular mapping is the standard convention objcam writes), the object and support (the
OBJ files with their albedo) and one camera per target. Run it with ``blender --python blender_scene.py``.

Everything the script needs is in its ``DATA`` dictionary (paths relative to the script): camera matrices are
Blender's ``matrix_world`` (world_from_camera @ diag(1, -1, -1, 1): Blender's camera looks down its -z with +y up),
focal length and shift from the intrinsics for a 36 mm wide sensor fitted horizontally.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from objcam.camera import Camera
from objcam.image_io import atomic_write_text

BLENDER_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
SENSOR_MM = 36.0

SCRIPT = '''"""objcam export: build the recovered scene in Blender (>= 3.0). Run: blender --python {name}"""
import os

import bpy
from mathutils import Matrix

HERE = os.path.dirname(os.path.abspath(__file__))
DATA = {data}


def path(rel):
    return os.path.join(HERE, rel)


def world(envmap, strength=1.0):
    w = bpy.data.worlds.new("objcam envmap")
    w.use_nodes = True
    nodes, links = w.node_tree.nodes, w.node_tree.links
    nodes.clear()
    tex = nodes.new("ShaderNodeTexEnvironment")
    tex.image = bpy.data.images.load(path(envmap))
    tex.image.colorspace_settings.name = "Non-Color"  # linear radiance
    bg = nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = strength
    out = nodes.new("ShaderNodeOutputWorld")
    links.new(tex.outputs["Color"], bg.inputs["Color"])
    links.new(bg.outputs["Background"], out.inputs["Surface"])
    bpy.context.scene.world = w


def import_obj(rel):
    before = set(bpy.data.objects)
    if hasattr(bpy.ops.wm, "obj_import"):  # Blender >= 3.2
        bpy.ops.wm.obj_import(filepath=path(rel), forward_axis="Y", up_axis="Z")
    else:
        bpy.ops.import_scene.obj(filepath=path(rel), axis_forward="Y", axis_up="Z")
    return [o for o in bpy.data.objects if o not in before]


def camera(name, c):
    cam = bpy.data.cameras.new(name)
    cam.sensor_fit = "HORIZONTAL"
    cam.sensor_width = c["sensor_width_mm"]
    cam.lens = c["lens_mm"]
    cam.shift_x, cam.shift_y = c["shift_x"], c["shift_y"]
    cam.clip_start = 0.001
    obj = bpy.data.objects.new(name, cam)
    obj.matrix_world = Matrix(c["matrix_world"])
    bpy.context.scene.collection.objects.link(obj)
    return obj


def main():
    scene = bpy.context.scene
    for o in list(bpy.data.objects):  # the default cube, camera and light
        bpy.data.objects.remove(o)
    scene.unit_settings.system = "METRIC"
    world(DATA["envmap"])
    for m in DATA["meshes"]:
        for o in import_obj(m):
            o.name = os.path.splitext(os.path.basename(m))[0]
    first = None
    for name, c in DATA["cameras"].items():
        obj = camera(name, c)
        first = first or (obj, c)
    if first:
        scene.camera = first[0]
        scene.render.resolution_x, scene.render.resolution_y = first[1]["width"], first[1]["height"]
        scene.render.resolution_percentage = 100


main()
'''


def blender_camera(cam: Camera) -> dict:
    """Blender camera settings reproducing ``cam`` (module docstring); shifts are fractions of the larger image
    side, positive x to the right and y up, the principal point's offset from the centre negated."""
    big = float(max(cam.width, cam.height))
    return {"matrix_world": (np.asarray(cam.world_from_camera, np.float64) @ BLENDER_FROM_OPENCV).tolist(),
            "sensor_width_mm": SENSOR_MM, "lens_mm": cam.fx * SENSOR_MM / cam.width,
            "shift_x": (cam.width / 2.0 - (cam.cx + 0.5)) / big, "shift_y": ((cam.cy + 0.5) - cam.height / 2.0) / big,
            "width": cam.width, "height": cam.height}


def write_blender_script(path: Path, envmap: str, meshes: list[str], cameras: dict[str, Camera]) -> Path:
    data = {"envmap": envmap, "meshes": meshes, "cameras": {n: blender_camera(c) for n, c in cameras.items()}}
    atomic_write_text(path, SCRIPT.format(name=path.name, data=json.dumps(data, indent=4)))
    return path


def script_data(path: Path) -> dict:
    """The ``DATA`` dictionary of a script written by :func:`write_blender_script`."""
    import ast

    tree = ast.parse(Path(path).read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "DATA":
            return ast.literal_eval(node.value)
    raise ValueError(f"{path}: no DATA")
