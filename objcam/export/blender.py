"""A Blender Python script that builds the exported scene: the world (the envmap as an Environment Texture,
whose default equirectangular mapping is the standard convention objcam writes, looked up without interpolation:
objcam's texels are constant over their cell), the object and support (the OBJ files, each given a Lambertian
``Diffuse BSDF`` of its linear albedo: the ``<name>_albedo.exr`` texture, or the constant), one camera per target,
and Cycles set up as objcam renders (box pixel filter, no denoising or clamping, ``max_depth`` - 2 bounces: 0 for
a direct-light transport). Run it with ``blender --python blender_scene.py``; ``blender -b --python
blender_scene.py -- --render OUT.exr`` renders the first camera headless into OUT.exr (linear). Measured against
Mitsuba's render of the same export by bench/blender_check.py (``make bench-blender``).

Everything the script needs is in its ``DATA`` dictionary (paths relative to the script): camera matrices are
Blender's ``matrix_world`` (world_from_camera @ diag(1, -1, -1, 1): Blender's camera looks down its -z with +y up),
focal length and shift from the intrinsics for a 36 mm wide sensor fitted horizontally.
"""

from __future__ import annotations

import pprint
from pathlib import Path

import numpy as np

from objcam.camera import Camera
from objcam.image_io import atomic_write_text

BLENDER_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
SENSOR_MM = 36.0

SCRIPT = '''"""objcam export: build the recovered scene in Blender (>= 3.0). Run: blender --python {name}
Headless render of the first camera (linear EXR): blender -b --python {name} -- --render OUT.exr [--seed N]"""
import os
import sys

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
    tex.interpolation = "Closest"  # objcam's texels are constant over their cell
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


def diffuse(name, m):
    """A Lambertian material of the linear albedo (texture or constant), as objcam and Mitsuba model it."""
    mat = bpy.data.materials.new(name + "_albedo")
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    bsdf = nodes.new("ShaderNodeBsdfDiffuse")
    bsdf.inputs["Roughness"].default_value = 0.0  # Lambert
    if m["texture"]:
        tex = nodes.new("ShaderNodeTexImage")
        tex.image = bpy.data.images.load(path(m["texture"]))
        tex.image.colorspace_settings.name = "Non-Color"  # linear albedo
        tex.interpolation = "Closest" if m["nearest"] else "Linear"
        tex.extension = "EXTEND"  # clamped, as Mitsuba's lookup
        links.new(tex.outputs["Color"], bsdf.inputs["Color"])
    else:
        bsdf.inputs["Color"].default_value = (*m["rgb"], 1.0)
    out = nodes.new("ShaderNodeOutputMaterial")
    links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return mat


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


def render_settings(scene, r):
    scene.render.engine = "CYCLES"
    scene.cycles.samples = r["samples"]
    scene.cycles.use_denoising = False
    scene.cycles.pixel_filter_type = "BOX"  # objcam's pixels average their square
    scene.cycles.filter_width = 1.0
    bounces = max(0, r["max_depth"] - 2)  # Mitsuba's depth 2 (direct light) is Cycles' 0 bounces
    scene.cycles.max_bounces = scene.cycles.diffuse_bounces = bounces
    scene.cycles.glossy_bounces = scene.cycles.transmission_bounces = scene.cycles.volume_bounces = 0
    scene.cycles.sample_clamp_direct = scene.cycles.sample_clamp_indirect = 0.0  # no clamping: unbiased
    scene.view_settings.view_transform = "Standard"


def main():
    scene = bpy.context.scene
    for o in list(bpy.data.objects):  # the default cube, camera and light
        bpy.data.objects.remove(o)
    scene.unit_settings.system = "METRIC"
    world(DATA["envmap"])
    for m in DATA["meshes"]:
        name = os.path.splitext(os.path.basename(m["obj"]))[0]
        mat = diffuse(name, m)
        for o in import_obj(m["obj"]):
            o.name = name
            o.data.materials.clear()
            o.data.materials.append(mat)
    first = None
    for name, c in DATA["cameras"].items():
        obj = camera(name, c)
        first = first or (obj, c)
    render_settings(scene, DATA["render"])
    if first:
        scene.camera = first[0]
        scene.render.resolution_x, scene.render.resolution_y = first[1]["width"], first[1]["height"]
        scene.render.resolution_percentage = 100
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    if "--seed" in argv:
        scene.cycles.seed = int(argv[argv.index("--seed") + 1])
    if "--render" in argv:  # headless: the first camera's linear render
        scene.render.image_settings.file_format = "OPEN_EXR"
        scene.render.image_settings.color_depth = "32"
        scene.render.filepath = os.path.abspath(argv[argv.index("--render") + 1])
        bpy.ops.render.render(write_still=True)


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


def write_blender_script(path: Path, envmap: str, meshes: list[dict], cameras: dict[str, Camera],
                        max_depth: int, samples: int = 256) -> Path:
    """``meshes``: per surface {"obj": OBJ path, "texture": linear albedo EXR path or None, "rgb": [r, g, b] or None,
    "nearest": look the texture up without interpolation}; paths relative to ``path``'s folder. ``max_depth``:
    Mitsuba's path depth the render should match (2: direct light)."""
    data = {"envmap": envmap, "meshes": meshes, "cameras": {n: blender_camera(c) for n, c in cameras.items()},
            "render": {"max_depth": int(max_depth), "samples": int(samples)}}
    # a Python literal (None, True), not JSON (null, true): the script reads DATA as code
    atomic_write_text(path, SCRIPT.format(name=path.name, data=pprint.pformat(data, width=116, sort_dicts=False)))
    return path


def script_data(path: Path) -> dict:
    """The ``DATA`` dictionary of a script written by :func:`write_blender_script`."""
    import ast

    tree = ast.parse(Path(path).read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "DATA":
            return ast.literal_eval(node.value)
    raise ValueError(f"{path}: no DATA")
