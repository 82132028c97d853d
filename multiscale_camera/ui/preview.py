"""Viewport previews drawn with the ``gpu`` module.

- In the 3D viewport (toggle ``scene.multiscale.show_preview``): the bent rays of a
  sparse pixel grid, from camera 1's near plane to where they leave the bending
  stretch, coloured by membership (camera 1 blue ... last camera orange), the chained
  frusta of the cameras (eye to near plane, near plane to the next near plane), and
  folds among the drawn rays marked in red. Redrawn from the newest field after each
  build.
- In the Image Editor: a camera's guide (its own view) over its mask at half opacity
  while the mask is shown, so the mask can be painted over the picture.

Lines are computed with numpy (``preview_lines``, no bpy); drawing needs a GPU
context, which background Blender lacks: there the lines are computed, nothing is
drawn, nothing fails.
"""

import numpy as np

from ..core.quality import bending_active, quad_folds

# Camera colours, first to last (a ray's colour blends them by its membership).
PALETTE = np.array(
    [
        (0.25, 0.55, 1.0),
        (0.3, 0.85, 0.45),
        (1.0, 0.6, 0.15),
        (0.85, 0.35, 0.9),
        (0.95, 0.9, 0.3),
    ],
    dtype=np.float32,
)
FOLD_COLOUR = (1.0, 0.1, 0.1, 1.0)
FRUSTUM_ALPHA = 0.8
RAY_ALPHA = 0.9
GUIDE_ALPHA = 0.5
# Drawn ray vertices per ray at most (every k-th vertex of long rays).
MAX_VERTICES = 96


def camera_colour(membership):
    """(..., 3) float32 colours for membership values (1-based camera numbers)."""
    m = np.clip(np.asarray(membership, dtype=np.float64) - 1.0, 0, len(PALETTE) - 1)
    lo = np.floor(m).astype(int)
    hi = np.minimum(lo + 1, len(PALETTE) - 1)
    t = (m - lo)[..., None]
    return ((1 - t) * PALETTE[lo] + t * PALETTE[hi]).astype(np.float32)


def frustum_lines(cameras):
    """Segments of the chained frusta.

    Returns
    -------
    pos : (S*2, 3) float32, world units, segment end points in pairs.
    colour : (S*2, 4) float32.
    """
    pos, col = [], []
    corners = []
    for i, cam in enumerate(cameras):
        w, h = cam.width, cam.height
        d = cam.directions(np.array([0.0, w, w, 0.0]), np.array([0.0, 0.0, h, h]))
        near = cam.near_points(d)
        corners.append(near)
        c = (*PALETTE[min(i, len(PALETTE) - 1)], FRUSTUM_ALPHA)
        for k in range(4):
            pos += [cam.eye, near[k], near[k], near[(k + 1) % 4]]
            col += [c] * 4
    for i in range(len(cameras) - 1):
        a, b = corners[i], corners[i + 1]
        ca = (*PALETTE[min(i, len(PALETTE) - 1)], 0.5 * FRUSTUM_ALPHA)
        cb = (*PALETTE[min(i + 1, len(PALETTE) - 1)], 0.5 * FRUSTUM_ALPHA)
        for k in range(4):
            pos += [a[k], b[k]]
            col += [ca, cb]
    return np.asarray(pos, dtype=np.float32).reshape(-1, 3), np.asarray(col, np.float32)


def preview_lines(fld, per_side=12):
    """Ray segments, their colours and fold marks for a sparse pixel grid of ``fld``.

    Parameters
    ----------
    fld : RayField. per_side : int, rays per image side.

    Returns
    -------
    dict with "rays" ((S*2, 3) float32 segment end points, world units), "ray_colours"
    ((S*2, 4) float32), "folds" ((F, 3) float32 points), "frusta" and
    "frustum_colours" (``frustum_lines``), "count" (rays drawn).
    """
    rig = fld.rig
    w, h = rig.size
    xs = np.unique(np.linspace(0, w - 1, per_side).round().astype(int))
    ys = np.unique(np.linspace(0, h - 1, max(2, round(per_side * h / w))).round().astype(int))
    iy, ix = np.meshgrid(ys, xs, indexing="ij")
    bundle = fld.rays(ix.ravel(), iy.ravel())
    verts, mem = bundle.vertices, bundle.membership
    r, k = verts.shape[:2]
    exit_index = fld.exit_index(ix.ravel(), iy.ravel())
    last = np.full(r, k - 1) if exit_index is None else np.clip(exit_index, 1, k - 1)
    step = max(1, int(np.ceil(k / MAX_VERTICES)))
    keep = np.arange(0, k, step)
    idx = np.arange(k - 1)
    seg = idx[None, :] < last[:, None]  # segments up to the exit vertex
    seg &= np.isin(idx, keep)[None, :] | (idx[None, :] == (last - 1)[:, None])
    rows, cols = np.nonzero(seg)
    nxt = np.minimum(cols + step, last[rows])
    a, b = verts[rows, cols], verts[rows, nxt]
    ca, cb = camera_colour(mem[rows, cols]), camera_colour(mem[rows, nxt])
    pos = np.stack([a, b], axis=1).reshape(-1, 3)
    col = np.concatenate(
        [np.stack([ca, cb], axis=1).reshape(-1, 3), np.full((len(pos), 1), RAY_ALPHA)], axis=1
    )
    grid_verts = verts.reshape(len(ys), len(xs), k, 3)
    counts = (last + 1).reshape(len(ys), len(xs))
    folds = np.zeros((0, 3), dtype=np.float32)
    if len(xs) > 1 and len(ys) > 1:
        folded = quad_folds(grid_verts, bending_active(grid_verts, rig.cameras[-1], counts))
        fy, fx = np.nonzero(folded)
        if len(fy):
            mid = (counts[fy, fx] // 2).clip(0, k - 1)
            folds = grid_verts[fy, fx, mid].astype(np.float32)
    frusta, frustum_colours = frustum_lines(rig.cameras)
    return {
        "rays": pos.astype(np.float32),
        "ray_colours": col.astype(np.float32),
        "folds": folds,
        "frusta": frusta,
        "frustum_colours": frustum_colours,
        "count": r,
    }


# --- Blender side ------------------------------------------------------------------------

# What the 3D viewport draws: preview_lines' dict (or frusta only), None when off.
# ``_on_load`` (a load_post handler) resets it for each file opened.
STATE = {"lines": None, "handler": None, "image_handler": None, "note": ""}


def _gpu_available():
    import bpy

    return not bpy.app.background


def update(scene, fld=None):
    """Recompute what the preview draws for ``scene`` (from ``fld``, else the newest
    cached field of the scene's rig) and add or remove the draw handler.

    Returns a short note for the user ("" when the rays are shown)."""
    settings = scene.multiscale
    if not settings.show_preview:
        STATE["lines"] = None
        _remove_handler()
        _redraw()
        return ""
    note = ""
    try:
        if fld is None:
            fld = _cached_field(scene)
        if fld is not None:
            STATE["lines"] = preview_lines(fld, settings.preview_rays)
        else:
            from ..adapters.scene import rig_from_scene

            rig = rig_from_scene(scene)
            pos, col = frustum_lines(rig.cameras)
            STATE["lines"] = {"frusta": pos, "frustum_colours": col, "count": 0}
            note = "Compute the field to see the rays; the frusta are shown"
    except Exception as err:  # a rig that cannot build: say so, draw nothing
        STATE["lines"] = None
        note = f"No preview: {err}"
    STATE["note"] = note
    _add_handler()
    _redraw()
    return note


def _cached_field(scene):
    from ..adapters.scene import field_settings, rig_from_scene
    from ..core.methods import field_key
    from ..io import cache

    s = scene.multiscale
    rig = rig_from_scene(scene)
    key = field_key(rig, s.method, field_settings(scene))
    return cache.CACHE.memory.get(key)


def _redraw():
    import bpy

    wm = getattr(bpy.context, "window_manager", None)
    for window in getattr(wm, "windows", []):
        for area in window.screen.areas:
            if area.type in {"VIEW_3D", "IMAGE_EDITOR"}:
                area.tag_redraw()


def _add_handler():
    import bpy

    if STATE["handler"] is None and _gpu_available():
        STATE["handler"] = bpy.types.SpaceView3D.draw_handler_add(
            _draw_view3d, (), "WINDOW", "POST_VIEW"
        )


def _remove_handler():
    import bpy

    if STATE["handler"] is not None:
        bpy.types.SpaceView3D.draw_handler_remove(STATE["handler"], "WINDOW")
        STATE["handler"] = None


def _line_shader():
    import gpu

    try:
        return gpu.shader.from_builtin("POLYLINE_SMOOTH_COLOR"), True
    except (ValueError, SystemError):
        return gpu.shader.from_builtin("SMOOTH_COLOR"), False


def _draw_lines(pos, col, width):
    import bpy
    from gpu_extras.batch import batch_for_shader

    if pos is None or len(pos) == 0:
        return
    shader, poly = _line_shader()
    batch = batch_for_shader(shader, "LINES", {"pos": pos.tolist(), "color": col.tolist()})
    shader.bind()
    if poly:
        region = bpy.context.region
        shader.uniform_float("viewportSize", (region.width, region.height))
        shader.uniform_float("lineWidth", width)
    batch.draw(shader)


def _draw_view3d():
    import gpu
    from gpu_extras.batch import batch_for_shader

    lines = STATE["lines"]
    if not lines:
        return
    gpu.state.blend_set("ALPHA")
    gpu.state.depth_test_set("LESS_EQUAL")
    _draw_lines(lines.get("frusta"), lines.get("frustum_colours"), 1.5)
    _draw_lines(lines.get("rays"), lines.get("ray_colours"), 1.5)
    folds = lines.get("folds")
    if folds is not None and len(folds):
        shader = gpu.shader.from_builtin(
            "POINT_UNIFORM_COLOR" if _has_shader("POINT_UNIFORM_COLOR") else "UNIFORM_COLOR"
        )
        batch = batch_for_shader(shader, "POINTS", {"pos": folds.tolist()})
        gpu.state.point_size_set(8.0)
        shader.bind()
        shader.uniform_float("color", FOLD_COLOUR)
        batch.draw(shader)
    gpu.state.depth_test_set("NONE")
    gpu.state.blend_set("NONE")


def _has_shader(name):
    import gpu

    try:
        gpu.shader.from_builtin(name)
        return True
    except (ValueError, SystemError):
        return False


# --- the guide under a mask in the Image Editor --------------------------------------------


def _guide_for(image, scene):
    for item in scene.multiscale.cameras:
        if item.mask is not None and item.mask == image:
            return item.guide
    return None


def _draw_image_guide():
    import bpy
    import gpu
    from gpu_extras.batch import batch_for_shader

    space, region = bpy.context.space_data, bpy.context.region
    scene = bpy.context.scene
    image = getattr(space, "image", None)
    if image is None or scene is None or not hasattr(scene, "multiscale"):
        return
    guide = _guide_for(image, scene)
    if guide is None or guide.size[0] == 0:
        return
    x0, y0 = region.view2d.view_to_region(0.0, 0.0, clip=False)
    x1, y1 = region.view2d.view_to_region(1.0, 1.0, clip=False)
    texture = gpu.texture.from_image(guide)
    name = "IMAGE_COLOR" if _has_shader("IMAGE_COLOR") else "IMAGE"
    shader = gpu.shader.from_builtin(name)
    batch = batch_for_shader(
        shader,
        "TRI_FAN",
        {
            "pos": ((x0, y0), (x1, y0), (x1, y1), (x0, y1)),
            "texCoord": ((0, 0), (1, 0), (1, 1), (0, 1)),
        },
    )
    gpu.state.blend_set("ALPHA")
    shader.bind()
    if name == "IMAGE_COLOR":
        shader.uniform_float("color", (1.0, 1.0, 1.0, GUIDE_ALPHA))
    shader.uniform_sampler("image", texture)
    batch.draw(shader)
    gpu.state.blend_set("NONE")


def _on_load(*_args):
    """After a file loads: forget the old file's lines; redraw for the new one if its
    preview is on."""
    import bpy

    STATE["lines"], STATE["note"] = None, ""
    scene = bpy.context.scene
    if scene is not None and hasattr(scene, "multiscale") and scene.multiscale.show_preview:
        update(scene)
    else:
        _remove_handler()


def register():
    import bpy

    if _on_load not in bpy.app.handlers.load_post:
        # persistent: kept across file loads (it is what runs after them)
        bpy.app.handlers.load_post.append(bpy.app.handlers.persistent(_on_load))
    if _gpu_available() and STATE["image_handler"] is None:
        STATE["image_handler"] = bpy.types.SpaceImageEditor.draw_handler_add(
            _draw_image_guide, (), "WINDOW", "POST_PIXEL"
        )


def unregister():
    import bpy

    if _on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_on_load)
    _remove_handler()
    if STATE["image_handler"] is not None:
        bpy.types.SpaceImageEditor.draw_handler_remove(STATE["image_handler"], "WINDOW")
        STATE["image_handler"] = None
    STATE["lines"] = None
