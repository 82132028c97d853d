"""Sample scenes for Multiscale Camera, built with bpy into the current file.

``build_demo(scene)`` makes a town square with a market stall and a teapot on it,
seen by three cameras at three scales; ``build_galleon(scene)`` a ship, the pirate in
its crow's nest and the lettered teapot in his hand, about 1000x from end to end.
``build_two_camera(scene)`` makes the small scene the hidden-surface acceptance test
renders. All fill ``scene.multiscale``,
so the package's properties must be registered first.

Every camera here looks at its subject from above, and its ``clip_start`` puts its
near plane in open air, so the space between consecutive near planes (where the
rays bend) holds no geometry.
"""

import math

import bmesh
import bpy
import numpy as np
from mathutils import Vector

LUMA = (0.2126, 0.7152, 0.0722)  # Rec. 709 weights; masks are pure black and white anyway


# --- masks -----------------------------------------------------------------


def make_mask(name, width, height, fn):
    """Create a packed black-and-white Image from a function of pixel centres.

    Parameters
    ----------
    name : str
    width, height : int
        Size in pixels; use the render resolution.
    fn : callable
        ``fn(xc, yc) -> bool array (height, width)``, where ``xc`` and ``yc`` are
        float arrays (height, width) of pixel-centre coordinates in pixels,
        ``x + 0.5`` and ``y + 0.5`` with the origin at the top-left corner.
        True (white) marks the pixels where the camera's view is preserved.

    Returns
    -------
    bpy.types.Image
        Packed into the .blend file, colour space Non-Color.
    """
    yc, xc = np.mgrid[0:height, 0:width] + 0.5
    white = np.asarray(fn(xc, yc), dtype=bool)
    rgba = np.ones((height, width, 4), dtype=np.float32)
    rgba[..., :3] = white[..., None]
    img = bpy.data.images.new(name, width, height, alpha=False)
    img.colorspace_settings.name = "Non-Color"
    img.pixels.foreach_set(rgba[::-1].ravel())  # Blender stores the bottom row first
    img.pack()
    return img


def read_mask(img):
    """The mask of an Image as bool (height, width), row 0 at the top (luminance >= 0.5)."""
    width, height = img.size
    px = np.empty(width * height * 4, dtype=np.float32)
    img.pixels.foreach_get(px)
    rgb = px.reshape(height, width, 4)[::-1, :, :3]
    return rgb @ np.array(LUMA, dtype=np.float32) >= 0.5


def _radius(width, height):
    """fn(xc, yc) -> distance in pixels from the image centre."""
    return lambda xc, yc: np.hypot(xc - width / 2, yc - height / 2)


# --- objects ---------------------------------------------------------------


def _material(name, rgb):
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5 creates materials without nodes
        mat.use_nodes = True
    color = (*rgb, 1.0)
    mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = color
    mat.diffuse_color = color  # what Workbench and the Solid viewport show
    return mat


def _mesh_object(
    scene,
    name,
    build,
    rgb,
    pass_index,
    location=(0, 0, 0),
    rotation=(0, 0, 0),
    scale=(1, 1, 1),
    smooth=False,
):
    """Link a new mesh object; ``build(bm)`` fills a bmesh."""
    bm = bmesh.new()
    build(bm)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    if smooth:
        mesh.polygons.foreach_set("use_smooth", [True] * len(mesh.polygons))
    mesh.materials.append(_material(name, rgb))
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    obj.rotation_euler = [math.radians(a) for a in rotation]
    obj.scale = scale
    obj.pass_index = pass_index
    scene.collection.objects.link(obj)
    return obj


def _box(bm):
    bmesh.ops.create_cube(bm, size=1.0)  # unit cube; size it with the object scale


def _sphere(bm):
    bmesh.ops.create_uvsphere(bm, u_segments=32, v_segments=16, radius=1.0)


def _cylinder(radius_bottom=1.0, radius_top=1.0, segments=32):
    """A capped cone or cylinder of depth 1 centred on the origin, along z."""
    return lambda bm: bmesh.ops.create_cone(
        bm, cap_ends=True, segments=segments, radius1=radius_bottom, radius2=radius_top, depth=1.0
    )


def _torus(major, minor, segments=32, ring=12):
    """A torus around the z axis."""

    def build(bm):
        u = np.linspace(0, 2 * np.pi, segments, endpoint=False)[:, None]
        v = np.linspace(0, 2 * np.pi, ring, endpoint=False)[None, :]
        r = major + minor * np.cos(v)
        xyz = np.stack(np.broadcast_arrays(r * np.cos(u), r * np.sin(u), minor * np.sin(v)), -1)
        verts = [bm.verts.new(p) for p in xyz.reshape(-1, 3).tolist()]
        for i in range(segments):
            for j in range(ring):
                a, b = i * ring + j, i * ring + (j + 1) % ring
                c, d = ((i + 1) % segments) * ring + (j + 1) % ring, ((i + 1) % segments) * ring + j
                bm.faces.new((verts[a], verts[d], verts[c], verts[b]))

    return build


def _camera(scene, name, target, distance, azimuth, elevation, clip_start, lens=50.0):
    """A perspective camera ``distance`` from ``target``, aimed at it.

    ``azimuth`` (degrees) turns the camera about z from the -y side of the target;
    ``elevation`` (degrees) raises it above the horizontal.
    """
    az, el = math.radians(azimuth), math.radians(elevation)
    target = Vector(target)
    offset = Vector((math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)))
    data = bpy.data.cameras.new(name)
    data.lens = lens
    data.sensor_fit = "AUTO"
    data.clip_start = clip_start
    data.clip_end = 1000.0
    obj = bpy.data.objects.new(name, data)
    obj.location = target + distance * offset
    obj.rotation_euler = (-offset).to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(obj)
    return obj


def _light(scene, name, kind, energy, location, rotation=(0, 0, 0), rgb=(1, 1, 1)):
    data = bpy.data.lights.new(name, kind)
    data.energy = energy
    data.color = rgb
    obj = bpy.data.objects.new(name, data)
    obj.location = location
    obj.rotation_euler = [math.radians(a) for a in rotation]
    scene.collection.objects.link(obj)
    return obj


def _world(scene, rgb):
    world = bpy.data.worlds.new("Sky")
    if world.node_tree is None:  # Blender < 5 creates worlds without nodes
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (*rgb, 1.0)
    world.color = rgb
    scene.world = world


def _setup_render(scene, width, height):
    scene.render.resolution_x = width
    scene.render.resolution_y = height
    scene.render.resolution_percentage = 100
    for layer in scene.view_layers:
        layer.use_pass_z = True
        layer.use_pass_normal = True
        layer.use_pass_object_index = True


def _ring_masks(cams, width, height, radii):
    """Masks "Mask <camera name>" for three cameras about the image centre: the last owns
    the disk of radius ``radii["cam3"]`` pixels, the middle one the ring between
    ``cam2_inner`` and ``cam2_outer``, the first everything beyond ``cam1``."""
    r = _radius(width, height)
    inside = {
        0: lambda x, y: r(x, y) >= radii["cam1"],
        1: lambda x, y: (r(x, y) >= radii["cam2_inner"]) & (r(x, y) <= radii["cam2_outer"]),
        2: lambda x, y: r(x, y) <= radii["cam3"],
    }
    return [make_mask(f"Mask {c.name}", width, height, inside[i]) for i, c in enumerate(cams)]


def _add_cameras(scene, cameras_and_masks):
    """Fill ``scene.multiscale.cameras`` (largest scale first) and pick the engine."""
    for cam, mask in cameras_and_masks:
        item = scene.multiscale.cameras.add()
        item.camera = cam
        item.mask = mask
    scene.camera = cameras_and_masks[0][0]
    try:
        scene.render.engine = "MULTISCALE"
    except TypeError:
        pass  # the engine is not registered here; the render script sets it


# --- demo: square, stall, teapot --------------------------------------------

DEMO_SIZE = (640, 360)
TEAPOT = (0.0, 0.0, 1.08)  # where every demo camera looks
# Mask radii in pixels from the image centre: camera 3 owns the disk, camera 2 the
# ring, camera 1 the outside; the gaps between them are the transitions.
DEMO_RADII = {"cam3": 72, "cam2_inner": 108, "cam2_outer": 150, "cam1": 190}


def _build_square(scene):
    _mesh_object(scene, "Ground", _box, (0.55, 0.52, 0.47), 1, (0, 0, -0.05), scale=(80, 80, 0.1))
    buildings = [  # centre x, y; size x, y, z; colour
        ((-15, 16), (8, 7, 11), (0.75, 0.35, 0.25)),
        ((-5, 18), (9, 6, 8), (0.85, 0.75, 0.45)),
        ((5, 17), (8, 7, 13), (0.45, 0.55, 0.75)),
        ((15, 15), (7, 8, 9), (0.9, 0.6, 0.6)),
        ((-16, 4), (7, 9, 7), (0.5, 0.7, 0.45)),
        ((-16, -8), (7, 8, 10), (0.8, 0.8, 0.8)),
        ((16, 3), (7, 10, 12), (0.65, 0.45, 0.7)),
        ((16, -9), (7, 8, 6), (0.95, 0.85, 0.3)),
    ]
    for i, ((x, y), (sx, sy, sz), rgb) in enumerate(buildings):
        _mesh_object(
            scene, f"Building {i + 1}", _box, rgb, 10 + i, (x, y, sz / 2), scale=(sx, sy, sz)
        )
    # A fountain and some crates, so the square has something at its own scale.
    _mesh_object(
        scene,
        "Fountain Basin",
        _cylinder(),
        (0.6, 0.6, 0.65),
        20,
        (-6, 7, 0.3),
        scale=(2.5, 2.5, 0.6),
    )
    _mesh_object(
        scene,
        "Fountain Water",
        _cylinder(),
        (0.3, 0.5, 0.9),
        21,
        (-6, 7, 0.55),
        scale=(2.2, 2.2, 0.1),
    )
    _mesh_object(
        scene,
        "Fountain Column",
        _cylinder(0.5, 0.3),
        (0.6, 0.6, 0.65),
        22,
        (-6, 7, 1.5),
        scale=(1, 1, 2),
    )
    for i, (x, y) in enumerate([(6, 6), (6.9, 6.2), (6.4, 7.1)]):
        _mesh_object(
            scene,
            f"Crate {i + 1}",
            _box,
            (0.6, 0.42, 0.25),
            23 + i,
            (x, y, 0.4),
            (0, 0, 15 * i),
            (0.8, 0.8, 0.8),
        )


def _build_stall(scene):
    wood, cloth = (0.45, 0.3, 0.18), (0.8, 0.15, 0.15)
    _mesh_object(
        scene, "Stall Table", _box, (0.7, 0.55, 0.35), 30, (0, 0.1, 0.975), scale=(1.8, 0.8, 0.05)
    )
    for i, (x, y) in enumerate([(-0.85, -0.25), (0.85, -0.25), (-0.85, 0.45), (0.85, 0.45)]):
        _mesh_object(
            scene, f"Table Leg {i + 1}", _box, wood, 31, (x, y, 0.475), scale=(0.05, 0.05, 0.95)
        )
    for i, (x, y) in enumerate([(-1.1, -0.6), (1.1, -0.6), (-1.1, 0.7), (1.1, 0.7)]):
        _mesh_object(
            scene, f"Stall Post {i + 1}", _box, wood, 32 + i, (x, y, 1.25), scale=(0.08, 0.08, 2.5)
        )
    # Canopy: striped cloth sloping down toward the back, high enough at the front
    # that the cameras look under it at the teapot.
    for i in range(5):
        rgb = cloth if i % 2 == 0 else (0.95, 0.95, 0.9)
        _mesh_object(
            scene,
            f"Canopy Stripe {i + 1}",
            _box,
            rgb,
            36 + i % 2,
            (-0.96 + 0.48 * i, 0.05, 2.5),
            (-10, 0, 0),
            (0.48, 1.6, 0.03),
        )
    _mesh_object(
        scene, "Stall Back", _box, (0.3, 0.45, 0.3), 38, (0, 0.72, 1.6), scale=(2.2, 0.04, 1.3)
    )
    for i, (x, rgb) in enumerate(
        [(-0.65, (0.95, 0.5, 0.1)), (-0.5, (0.9, 0.85, 0.2)), (0.55, (0.3, 0.75, 0.2))]
    ):
        _mesh_object(
            scene,
            f"Fruit Pile {i + 1}",
            _sphere,
            rgb,
            40 + i,
            (x, 0.2, 1.06),
            scale=(0.09, 0.09, 0.06),
            smooth=True,
        )
    _mesh_object(
        scene,
        "Basket",
        _cylinder(0.16, 0.2),
        (0.6, 0.45, 0.2),
        43,
        (0.7, 0.3, 1.06),
        scale=(1, 1, 0.12),
    )


def _build_teapot(scene):
    x, y, z = TEAPOT
    porcelain, blue, gold = (0.2, 0.45, 0.85), (0.1, 0.2, 0.55), (0.95, 0.75, 0.2)
    _mesh_object(
        scene,
        "Teapot Body",
        _sphere,
        porcelain,
        50,
        (x, y, z),
        scale=(0.08, 0.08, 0.06),
        smooth=True,
    )
    _mesh_object(
        scene, "Teapot Band", _cylinder(), gold, 51, (x, y, z), scale=(0.081, 0.081, 0.012)
    )
    _mesh_object(
        scene,
        "Teapot Lid",
        _cylinder(0.05, 0.035),
        blue,
        52,
        (x, y, z + 0.064),
        scale=(1, 1, 0.015),
    )
    _mesh_object(
        scene,
        "Teapot Knob",
        _sphere,
        gold,
        53,
        (x, y, z + 0.08),
        scale=(0.012, 0.012, 0.012),
        smooth=True,
    )
    _mesh_object(
        scene,
        "Teapot Spout",
        _cylinder(0.018, 0.009),
        blue,
        54,
        (x - 0.1, y, z + 0.015),
        (0, -50, 0),
        (1, 1, 0.09),
    )
    _mesh_object(
        scene,
        "Teapot Handle",
        _torus(0.035, 0.008),
        blue,
        55,
        (x + 0.085, y, z + 0.005),
        (90, 0, 0),
    )
    _mesh_object(
        scene, "Teapot Foot", _cylinder(), blue, 56, (x, y, z - 0.06), scale=(0.045, 0.045, 0.01)
    )
    for i, (dx, rgb) in enumerate([(-0.2, (0.85, 0.2, 0.3)), (0.2, (0.2, 0.7, 0.5))]):
        _mesh_object(
            scene,
            f"Cup {i + 1}",
            _cylinder(0.022, 0.03),
            rgb,
            57 + i,
            (x + dx, y - 0.05, 1.025),
            scale=(1, 1, 0.05),
        )
        _mesh_object(
            scene,
            f"Saucer {i + 1}",
            _cylinder(),
            (0.95, 0.95, 0.95),
            59 + i,
            (x + dx, y - 0.05, 1.002),
            scale=(0.05, 0.05, 0.004),
        )


def build_demo(scene):
    """Fill an empty ``scene`` with the three-scale demo.

    Cameras, largest scale first, all aimed at the teapot from the front (-y) and
    above: "Cam1 Square" 35 m away, "Cam2 Stall" 8 m, "Cam3 Object" 2 m (50 mm
    lenses, about 4-5x zoom per step). The near planes sit 10 m, 4.5 m and 1.4 m from
    the eyes: the smallest camera's near plane is then a seventh of the first one's
    width, which one uniform grid resolves; and camera 2's near distance exceeds beta
    times the 21 m between the first two near planes, so no guide is shortened.
    """
    width, height = DEMO_SIZE
    _setup_render(scene, width, height)
    _world(scene, (0.45, 0.65, 0.9))
    _build_square(scene)
    _build_stall(scene)
    _build_teapot(scene)
    _light(scene, "Sun", "SUN", 3.0, (0, 0, 30), (40, 10, 30))
    _light(scene, "Stall Lamp", "POINT", 60.0, (0.3, -0.2, 2.1), rgb=(1.0, 0.9, 0.75))

    cams = [
        _camera(scene, "Cam1 Square", TEAPOT, 35.0, 0.0, 35.0, clip_start=10.0),
        _camera(scene, "Cam2 Stall", TEAPOT, 8.0, 6.0, 33.0, clip_start=4.5),
        _camera(scene, "Cam3 Object", TEAPOT, 2.0, 12.0, 30.0, clip_start=1.4),
    ]
    # three scales 17x apart on one uniform grid: HIGH keeps every camera within 0.5 px
    scene.multiscale.quality = "HIGH"
    _add_cameras(scene, list(zip(cams, _ring_masks(cams, width, height, DEMO_RADII))))


# --- galleon: a ship, the pirate in its crow's nest, the teapot in his hand ---

GALLEON_SIZE = (640, 360)
# The teapot the pirate holds out over the rail of the crow's nest: every camera looks here.
GALLEON_TEAPOT = (1.1, -0.35, 19.55)
# Mask radii as fractions of the image width: camera 3 owns the disk, camera 2 the
# ring, camera 1 the outside.
GALLEON_RADII = {"cam3": 0.08, "cam2_inner": 0.14, "cam2_outer": 0.22, "cam1": 0.3}


def _text_object(scene, name, body, size, rgb, pass_index, location, rotation):
    """A flat mesh of ``body`` in Blender's built-in font (a text curve turned into a
    mesh, so every renderer sees triangles)."""
    curve = bpy.data.curves.new(name, type="FONT")
    curve.body = body
    curve.size = size
    curve.align_x = "CENTER"
    curve.align_y = "CENTER"
    curve.extrude = size * 0.04
    tmp = bpy.data.objects.new(name + " (text)", curve)
    scene.collection.objects.link(tmp)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    mesh = bpy.data.meshes.new_from_object(tmp.evaluated_get(depsgraph))
    bpy.data.objects.remove(tmp)
    bpy.data.curves.remove(curve)
    mesh.materials.append(_material(name, rgb))
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    obj.rotation_euler = [math.radians(a) for a in rotation]
    obj.pass_index = pass_index
    scene.collection.objects.link(obj)
    return obj


def build_galleon(scene):
    """Fill an empty ``scene`` with the paper's galleon, about 1000x from end to end.

    A 60 m ship with three masts; in the crow's nest of the main mast, 18 m up, a
    pirate holds a 12 cm teapot out over the rail, its band lettered in 8 mm type.
    Cameras, largest scale first, all aimed at the teapot: "Cam1 Galleon" 90 m away
    with a 35 mm lens (near plane 36 m from its eye, 37 m wide), "Cam2 Pirate" 4 m away
    (near plane 1.62 m, 1.17 m wide), "Cam3 Teapot" 13 cm away (near plane 5.1 cm,
    3.7 cm wide): about 31.6x per step, 1000x from the first near plane to the last.
    One uniform grid cannot hold that; SCALAR_FIELD builds nested grids for it.
    """
    width, height = GALLEON_SIZE
    _setup_render(scene, width, height)
    _world(scene, (0.55, 0.7, 0.9))
    wood, dark, sail, cloth = (
        (0.45, 0.28, 0.14),
        (0.25, 0.15, 0.08),
        (0.92, 0.9, 0.82),
        (0.7, 0.1, 0.1),
    )
    skin, porcelain, gold = (0.85, 0.62, 0.48), (0.93, 0.93, 0.97), (0.95, 0.75, 0.2)
    # the sea and the ship
    _mesh_object(scene, "Sea", _box, (0.1, 0.3, 0.45), 1, (0, 0, -1.0), scale=(400, 400, 1))
    _mesh_object(scene, "Hull", _sphere, wood, 10, (0, 0, 2.0), scale=(30, 8, 4), smooth=True)
    _mesh_object(scene, "Deck", _box, dark, 11, (0, 0, 4.6), scale=(52, 12, 0.4))
    _mesh_object(scene, "Stern Castle", _box, wood, 12, (-22, 0, 7.0), scale=(10, 11, 5))
    for n, (x, height_m) in enumerate(((-13.0, 15.0), (0.0, 18.0), (13.0, 13.0))):
        _mesh_object(
            scene,
            f"Mast {n + 1}",
            _cylinder(0.35, 0.25),
            dark,
            20 + n,
            (x, 0, 4.6 + height_m / 2),
            scale=(1, 1, height_m),
        )
        for k, frac in enumerate((0.35, 0.7)):
            _mesh_object(
                scene,
                f"Sail {n + 1}.{k + 1}",
                _box,
                sail,
                30 + n,
                (x + 0.6, 0, 4.6 + frac * height_m),
                scale=(0.2, 10 - 3 * k, 0.28 * height_m),
            )
    # the crow's nest on the main mast and the pirate in it
    _mesh_object(scene, "Crow's Nest", _torus(1.0, 0.08), dark, 40, (0, 0, 18.6))
    _mesh_object(scene, "Nest Floor", _cylinder(), dark, 40, (0, 0, 17.6), scale=(1.0, 1.0, 0.1))
    _mesh_object(
        scene, "Pirate Body", _cylinder(0.22, 0.18), cloth, 41, (0.2, 0, 18.3), scale=(1, 1, 1.3)
    )
    _mesh_object(
        scene, "Pirate Head", _sphere, skin, 42, (0.2, 0, 19.15), scale=(0.13,) * 3, smooth=True
    )
    _mesh_object(
        scene,
        "Pirate Hat",
        _cylinder(0.2, 0.05),
        (0.05, 0.05, 0.05),
        43,
        (0.2, 0, 19.32),
        scale=(1, 1, 0.15),
    )
    x, y, z = GALLEON_TEAPOT
    _mesh_object(
        scene,
        "Pirate Arm",
        _cylinder(0.05, 0.045),
        skin,
        44,
        ((0.2 + x) / 2, y / 2, (18.7 + z - 0.08) / 2),
        rotation=(0, 62, -18),
        scale=(1, 1, 1.05),
    )
    # the teapot, its band lettered
    _mesh_object(
        scene, "Teapot", _sphere, porcelain, 50, (x, y, z), scale=(0.06, 0.06, 0.045), smooth=True
    )
    _mesh_object(
        scene, "Teapot Band", _cylinder(), gold, 51, (x, y, z), scale=(0.061, 0.061, 0.012)
    )
    _mesh_object(
        scene,
        "Teapot Spout",
        _cylinder(0.012, 0.006),
        porcelain,
        52,
        (x + 0.07, y, z + 0.015),
        rotation=(0, 55, 0),
        scale=(1, 1, 0.05),
    )
    _text_object(
        scene,
        "Teapot Letters",
        "MULTISCALE",
        0.008,
        (0.1, 0.1, 0.3),
        53,
        (x, y - 0.0615, z),
        rotation=(90, 0, 0),
    )
    _light(scene, "Sun", "SUN", 3.0, (0, 0, 60), (40, 10, 30))

    target = GALLEON_TEAPOT
    cams = [
        _camera(scene, "Cam1 Galleon", target, 90.0, 0.0, 10.0, clip_start=36.0, lens=35.0),
        _camera(scene, "Cam2 Pirate", target, 4.0, 10.0, 15.0, clip_start=1.62),
        _camera(scene, "Cam3 Teapot", target, 0.13, 20.0, 15.0, clip_start=0.051),
    ]
    radii = {k: v * width for k, v in GALLEON_RADII.items()}
    _add_cameras(scene, list(zip(cams, _ring_masks(cams, width, height, radii))))


# --- two cameras: the hidden-surface acceptance test -------------------------

TWO_CAMERA_SIZE = (160, 120)
TWO_CAMERA_RADII = {"cam2": 30, "cam1": 50}


def build_two_camera(scene):
    """Fill an empty ``scene`` with the two-camera test scene.

    A ground plane and a cluster of shapes with distinct ``pass_index`` values (0
    is the sky). "Cam1 Wide" is 16 m from the cluster; "Cam2 Close" is 4 m from
    it, turned 18 degrees about z. Camera 2 owns a central disk, camera 1 the
    outside of a larger circle.
    """
    width, height = TWO_CAMERA_SIZE
    _setup_render(scene, width, height)
    _world(scene, (0.5, 0.7, 0.95))
    _mesh_object(scene, "Ground", _box, (0.5, 0.5, 0.45), 1, (0, 0, -0.05), scale=(40, 40, 0.1))
    _mesh_object(
        scene,
        "Sphere",
        _sphere,
        (0.8, 0.2, 0.2),
        2,
        (0, 0, 0.4),
        scale=(0.4, 0.4, 0.4),
        smooth=True,
    )
    _mesh_object(
        scene,
        "Small Cube",
        _box,
        (0.2, 0.7, 0.3),
        3,
        (0.55, -0.35, 0.15),
        (0, 0, 30),
        (0.3, 0.3, 0.3),
    )
    _mesh_object(
        scene,
        "Small Cone",
        _cylinder(0.15, 0.0),
        (0.9, 0.8, 0.2),
        4,
        (-0.55, -0.25, 0.2),
        scale=(1, 1, 0.4),
    )
    _mesh_object(
        scene, "Ring", _torus(0.25, 0.06), (0.3, 0.4, 0.9), 5, (0.1, 0.6, 0.3), (70, 0, 20)
    )
    _mesh_object(scene, "Big Box", _box, (0.7, 0.5, 0.8), 6, (-4, 3, 1.0), (0, 0, 20), (2, 2, 2))
    _mesh_object(
        scene, "Tall Cylinder", _cylinder(), (0.3, 0.8, 0.8), 7, (4, 2, 1.5), scale=(0.8, 0.8, 3)
    )
    _mesh_object(scene, "Wall", _box, (0.9, 0.6, 0.4), 8, (0, 7, 1.5), scale=(12, 0.4, 3))
    _mesh_object(
        scene, "Cone", _cylinder(1.0, 0.0), (0.6, 0.3, 0.2), 9, (3.5, -2.5, 1.0), scale=(1, 1, 2)
    )
    _light(scene, "Sun", "SUN", 3.0, (0, 0, 20), (35, 0, 40))

    target = (0.0, 0.0, 0.3)
    cams = [
        _camera(scene, "Cam1 Wide", target, 16.0, 0.0, 40.0, clip_start=8.0, lens=35.0),
        _camera(scene, "Cam2 Close", target, 4.0, 18.0, 35.0, clip_start=2.0, lens=35.0),
    ]
    r, radii = _radius(width, height), TWO_CAMERA_RADII
    masks = [
        make_mask("Mask Cam1 Wide", width, height, lambda x, y: r(x, y) >= radii["cam1"]),
        make_mask("Mask Cam2 Close", width, height, lambda x, y: r(x, y) <= radii["cam2"]),
    ]
    _add_cameras(scene, list(zip(cams, masks)))


# --- volume demo: a body, an organ inside it, vessels inside that ------------------

VOLUME_DEMO_SIZE = (640, 360)
VOLUME_FILE = "volume_demo_phantom.nrrd"
VOLUME_VOXELS = 192


def _transfer_function(name, points):
    tex = bpy.data.textures.new(f"TF {name}", type="BLEND")
    tex.use_color_ramp = True
    ramp = tex.color_ramp
    ramp.interpolation = "LINEAR"
    els = ramp.elements
    while len(els) > 1:
        els.remove(els[-1])
    for i, (pos, colour) in enumerate(points):
        el = els[0] if i == 0 else els.new(pos)
        el.position, el.color = pos, colour
    return tex


def build_volume_demo(scene, out_dir):
    """Fill an empty ``scene`` with the volume demo and write its volume file.

    The phantom of ``fixtures/phantom.py`` (192^3, gzip NRRD next to the .blend) fills a 2-unit
    empty cube centred 1 m above the origin. "Cam1 Body" sees the whole body from 4.6 m,
    "Cam2 Organ" the organ from 1.7 m, "Cam3 Vessels" the vessel tree from 0.9 m; each has its
    own transfer function: the skin is opaque at the first scale, clear at the second
    (where the organ wall is a red veil) and the third shows only the vessels.
    """
    import os

    from fixtures import phantom
    from multiscale_camera.io.volume_files import write_nrrd

    width, height = VOLUME_DEMO_SIZE
    _setup_render(scene, width, height)
    _world(scene, (0.02, 0.02, 0.03))
    values = phantom.phantom(VOLUME_VOXELS)
    write_nrrd(os.path.join(out_dir, VOLUME_FILE), np.round(values * 255).astype(np.uint8))
    box = bpy.data.objects.new("Body Volume", None)
    box.empty_display_type = "CUBE"
    box.empty_display_size = 1.0
    scene.collection.objects.link(box)
    box.multiscale_volume.use = True
    box.multiscale_volume.filepath = "//" + VOLUME_FILE
    box.multiscale_volume.auto_range = False
    box.multiscale_volume.range_min, box.multiscale_volume.range_max = 0.0, 255.0

    box.location = phantom.BODY_CENTRE
    cams = [
        _camera(scene, name, target, distance, az, el, clip_start=clip)
        for name, target, distance, az, el, clip in phantom.DEMO_CAMERAS
    ]
    scene.multiscale.quality = "STANDARD"
    scene.multiscale.volume_step = phantom.DEMO_STEP
    r, radii = _radius(width, height), phantom.DEMO_RADII
    masks = [
        make_mask("Mask Cam1 Body", width, height, lambda x, y: r(x, y) >= radii["cam1"]),
        make_mask(
            "Mask Cam2 Organ",
            width,
            height,
            lambda x, y: (r(x, y) >= radii["cam2_inner"]) & (r(x, y) <= radii["cam2_outer"]),
        ),
        make_mask("Mask Cam3 Vessels", width, height, lambda x, y: r(x, y) <= radii["cam3"]),
    ]
    _add_cameras(scene, list(zip(cams, masks)))
    for item, (name, points) in zip(scene.multiscale.cameras, phantom.DEMO_TFS.items()):
        item.transfer_function = _transfer_function(name, points)
