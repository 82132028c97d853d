"""Small scenes built in-process for bpy tests."""

import bpy
import numpy as np
from mathutils import Vector


def add_camera(scene, name, location, target, clip_start=1.0, clip_end=200.0, lens=50.0):
    data = bpy.data.cameras.new(name)
    data.clip_start, data.clip_end, data.lens = clip_start, clip_end, lens
    obj = bpy.data.objects.new(name, data)
    scene.collection.objects.link(obj)
    obj.location = location
    obj.rotation_euler = (Vector(target) - Vector(location)).to_track_quat("-Z", "Y").to_euler()
    return obj


def mask_image(name, mask):
    """A Blender image whose pixels are white where ``mask`` (H, W, row 0 at the top) is True."""
    h, w = mask.shape
    img = bpy.data.images.new(name, w, h)
    rgba = np.ones((h, w, 4), dtype=np.float32)
    rgba[..., :3] = mask[::-1, :, None]
    img.pixels.foreach_set(rgba.ravel())
    return img


def disk(width, height, radius, inside=True):
    yy, xx = np.mgrid[0:height, 0:width] + 0.5
    r = np.hypot(xx - width / 2, yy - height / 2)
    return r < radius if inside else r > radius


def add_mesh(kind, location, pass_index, colour=None, **kw):
    getattr(bpy.ops.mesh, f"primitive_{kind}_add")(location=location, **kw)
    obj = bpy.context.object
    obj.pass_index = pass_index
    if colour is not None:
        mat = bpy.data.materials.new(f"{obj.name}_mat")
        if bpy.app.version < (5, 0, 0):
            mat.use_nodes = True
        mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (*colour, 1.0)
        obj.data.materials.append(mat)
    return obj


def two_camera_scene(scene, width=48, height=36):
    """A ground, a cube and a small sphere; camera 2 looks at the sphere from close by."""
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    add_mesh("plane", (0, 0, 0), 1, (0.2, 0.6, 0.2), size=20)
    add_mesh("cube", (0, 0, 1), 2, (0.8, 0.2, 0.2))
    add_mesh("uv_sphere", (0.6, -0.6, 2.3), 3, (0.2, 0.3, 0.9), radius=0.3)
    bpy.ops.object.light_add(type="SUN", rotation=(0.5, 0.2, 0.0))
    bpy.context.object.data.energy = 3.0
    c1 = add_camera(scene, "C1", (0, -14, 9), (0, 0, 1), clip_start=5.0)
    c2 = add_camera(scene, "C2", (0.5, -3.5, 4), (0.6, -0.6, 2.3), clip_start=1.5)
    for cam, mask in (
        (c1, disk(width, height, 0.3 * width, inside=False)),
        (c2, disk(width, height, 0.15 * width)),
    ):
        item = scene.multiscale.cameras.add()
        item.camera = cam
        item.mask = mask_image(f"{cam.name} mask", mask)
    scene.camera = c1
    scene.render.engine = "MULTISCALE"
    bpy.context.view_layer.update()
    return c1, c2
