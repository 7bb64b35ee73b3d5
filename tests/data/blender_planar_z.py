"""Renders tests/data/blender_planar_z.exr: a tiny Cycles multilayer EXR with Blender's planar Z pass.

    blender -b --factory-startup --python tests/data/blender_planar_z.py -- tests/data/blender_planar_z.exr

64x36, 4 samples, no denoising: a wall facing the camera 6 units away (its Z is 6 at every pixel: distance
along the camera's axis), a sphere in front of it, sky (Z 1e10) around. The camera's lens is 30 mm on a
36 mm sensor (horizontal field of view 2 atan(18 / 30) = 61.93 degrees), stamped into the header as `Lens`.
"""

import math
import sys

import bpy

scene = bpy.context.scene
for thing in list(bpy.data.objects):
    bpy.data.objects.remove(thing)
scene.render.engine = "CYCLES"
scene.cycles.samples = 4
scene.cycles.device = "CPU"
scene.cycles.use_denoising = False
for view_layer in scene.view_layers:
    view_layer.cycles.use_denoising = False
    view_layer.use_pass_z = True
scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 64, 36, 100
lens = bpy.data.cameras.new("camera")
lens.lens, lens.sensor_width, lens.sensor_fit = 30.0, 36.0, "HORIZONTAL"
camera = bpy.data.objects.new("camera", lens)
scene.collection.objects.link(camera)
scene.camera = camera
camera.location, camera.rotation_euler = (0.0, -6.0, 1.0), (math.radians(90), 0.0, 0.0)
bpy.ops.mesh.primitive_plane_add(size=4, location=(0.0, 0.0, 1.0), rotation=(math.radians(90), 0.0, 0.0))
bpy.ops.mesh.primitive_uv_sphere_add(radius=0.7, location=(1.5, -2.0, 0.5))
scene.render.use_stamp_lens = True
scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
scene.render.image_settings.color_depth = "32"
scene.render.filepath = sys.argv[-1]
bpy.ops.render.render(write_still=True)
