"""The artist's mask tools headless: New Mask keeps a painted mask to put back, the guide
is remade when the camera moves, masks from the selected objects' silhouette and from
soft shapes."""

import math

import bpy
import numpy as np
import pytest

from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.ui.mask_ops import guide_state, painted


def operator_error(op, **kw):
    with pytest.raises(RuntimeError) as info:
        op(**kw)
    return str(info.value)


def pixels(image):
    """(h, w, 4) float32 of ``image``, row 0 at the top."""
    w, h = image.size
    buf = np.empty(w * h * 4, np.float32)
    image.pixels.foreach_get(buf)
    return buf.reshape(h, w, 4)[::-1]


def straight_cast(scene, cam, width, height, wanted):
    """Independent reference: (height, width) bool, True where Blender's own
    scene.ray_cast from ``cam``'s eye through the pixel centre on its view frame hits
    one of the objects ``wanted`` first (row 0 at the top)."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    frame = [cam.matrix_world @ v for v in cam.data.view_frame(scene=scene)]
    tr, br, bl, tl = frame  # view_frame: top-right, bottom-right, bottom-left, top-left
    eye = cam.matrix_world.translation
    out = np.zeros((height, width), bool)
    for y in range(height):
        for x in range(width):
            u, v = (x + 0.5) / width, (y + 0.5) / height
            point = tl.lerp(tr, u).lerp(bl.lerp(br, u), v)
            hit, _loc, _n, _i, obj, _m = scene.ray_cast(depsgraph, eye, (point - eye).normalized())
            out[y, x] = hit and obj.name in wanted
    return out


def distance_to(mask):
    """(h, w) Euclidean distance in pixels from each pixel centre to the nearest True
    pixel centre of ``mask`` (brute force over its pixels)."""
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    gy, gx = np.mgrid[0:h, 0:w]
    d = np.full((h, w), np.inf)
    for y, x in zip(ys, xs):
        d = np.minimum(d, np.hypot(gx - x, gy - y))
    return d


# --- New Mask keeps a painted mask ---------------------------------------------------


def test_new_mask_keeps_a_painted_mask_recoverable(empty_scene):
    scene = empty_scene
    two_camera_scene(scene)  # camera 2's mask, "C2 mask", is a painted disk
    scene.multiscale.active_index = 1
    item = scene.multiscale.cameras[1]
    painted_before = pixels(item.mask).copy()
    assert painted(item.mask) and painted_before[..., 0].max() == 1.0
    assert bpy.ops.multiscale.mask_new(guide=False) == {"FINISHED"}
    assert item.mask.name == "C2 mask" and pixels(item.mask)[..., :3].max() == 0.0
    kept = item.previous_mask
    assert kept is not None and kept.name == "C2 mask (previous)" and kept.use_fake_user
    np.testing.assert_array_equal(pixels(kept), painted_before)
    # New Mask on the blank mask replaces it without keeping anything more
    assert not painted(item.mask)
    assert bpy.ops.multiscale.mask_new(guide=False) == {"FINISHED"}
    assert item.previous_mask == kept
    # put back: the painted mask is the mask again, the blank one kept in its place
    assert bpy.ops.multiscale.mask_restore() == {"FINISHED"}
    assert item.mask.name == "C2 mask" and item.previous_mask.name == "C2 mask (previous)"
    np.testing.assert_array_equal(pixels(item.mask), painted_before)
    assert pixels(item.previous_mask)[..., :3].max() == 0.0


def test_kept_mask_survives_save_and_reload(empty_scene, tmp_path):
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.active_index = 1
    before = pixels(scene.multiscale.cameras[1].mask).copy()
    bpy.ops.multiscale.mask_new(guide=False)
    path = tmp_path / "kept.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    item = bpy.context.scene.multiscale.cameras[1]
    np.testing.assert_array_equal(pixels(item.previous_mask), before)


def test_mask_restore_needs_a_replaced_mask(empty_scene):
    two_camera_scene(empty_scene)
    msg = "This camera has no replaced mask to put back"
    assert msg in operator_error(bpy.ops.multiscale.mask_restore)


# --- the guide ------------------------------------------------------------------------


def test_guide_is_remade_after_the_camera_moves(empty_scene):
    scene = empty_scene
    _c1, c2 = two_camera_scene(scene)
    scene.multiscale.active_index = 1
    item = scene.multiscale.cameras[1]
    assert guide_state(item, scene) == "missing"  # a mask not made by New Mask
    assert bpy.ops.multiscale.guide_update() == {"FINISHED"}
    assert guide_state(item, scene) == "ok"
    before = pixels(item.guide).copy()
    c2.location.x += 0.6  # the sphere moves left in camera 2's view
    bpy.context.view_layer.update()
    assert guide_state(item, scene) == "stale"
    assert bpy.ops.multiscale.guide_update() == {"FINISHED"}
    assert guide_state(item, scene) == "ok"
    after = pixels(item.guide)
    gh, gw = after.shape[:2]
    # the sphere (blue) in the remade guide is where Blender's own ray_cast sees it now
    blue = after[..., 2] > after[..., 0] + 0.05
    sphere = straight_cast(scene, c2, gw, gh, {"Sphere"})
    assert sphere.sum() > 20
    assert (blue == sphere).mean() > 0.97, (blue.sum(), sphere.sum())
    assert not np.array_equal(before, after)
    scene.render.resolution_percentage = 50
    assert guide_state(item, scene) == "stale"
    c2.data.lens = 35.0
    bpy.ops.multiscale.guide_update()
    assert guide_state(item, scene) == "ok"


# --- masks from the scene -------------------------------------------------------------


@pytest.mark.parametrize("margin", [0, 2])
def test_mask_from_selected_matches_a_straight_cast_silhouette(empty_scene, margin):
    scene = empty_scene
    _c1, c2 = two_camera_scene(scene, 40, 30)
    scene.multiscale.active_index = 1
    item = scene.multiscale.cameras[1]
    item.mask = None  # made from the silhouette alone
    sphere = bpy.data.objects["Sphere"]
    bpy.ops.object.select_all(action="DESELECT")
    sphere.select_set(True)
    assert bpy.ops.multiscale.mask_from_selected(margin=margin) == {"FINISHED"}
    got = pixels(item.mask)[..., 0] >= 0.5
    assert item.mask.name == "C2 mask" and got.shape == (30, 40)
    want = straight_cast(scene, c2, 40, 30, {"Sphere"})
    assert want.sum() > 30
    # within 1 px (plus the margin) of the reference silhouette, and covering it
    # but for its 1 px rim
    assert distance_to(want)[got].max() <= margin + 1.0 + 1e-9
    assert distance_to(got)[want].max() <= 1.0 + 1e-9
    if margin:
        assert got.sum() > want.sum()


def test_mask_from_selected_extends_the_mask(empty_scene):
    scene = empty_scene
    two_camera_scene(scene, 40, 30)
    scene.multiscale.active_index = 1
    item = scene.multiscale.cameras[1]
    before = pixels(item.mask)[..., 0] >= 0.5
    bpy.ops.object.select_all(action="DESELECT")
    bpy.data.objects["Cube"].select_set(True)
    assert bpy.ops.multiscale.mask_from_selected(margin=0) == {"FINISHED"}
    after = pixels(item.mask)[..., 0] >= 0.5
    assert after[before].all() and after.sum() > before.sum()


def test_mask_from_selected_says_what_is_missing(empty_scene):
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.active_index = 1
    bpy.ops.object.select_all(action="DESELECT")
    msg = "Select the objects whose silhouette makes the mask"
    assert msg in operator_error(bpy.ops.multiscale.mask_from_selected)
    scene.multiscale.cameras.add()
    scene.multiscale.active_index = 2
    assert "Pick a camera in the Multiscale list first" in operator_error(
        bpy.ops.multiscale.mask_from_selected
    )


def _soft_reference(kind, w, h, cx, cy, sw, sh, radius, feather):
    """Per-pixel reference of a feathered shape, written from its definition."""
    out = np.zeros((h, w))
    a, b = sw / 2, sh / 2
    for y in range(h):
        for x in range(w):
            px, py = x + 0.5 - cx, y + 0.5 - cy
            if kind == "CIRCLE":
                d = math.hypot(px, py) - min(a, b)
            elif kind == "ELLIPSE":
                # along the line from the centre: to the edge point in that direction
                r = math.hypot(px, py)
                edge = 1.0 / math.sqrt((px / r / a) ** 2 + (py / r / b) ** 2) if r else 0
                d = r - edge if r else -min(a, b)
            else:
                qx, qy = abs(px) - (a - radius), abs(py) - (b - radius)
                if qx > 0 and qy > 0:
                    d = math.hypot(qx, qy) - radius
                else:
                    d = max(qx, qy) - radius
            t = min(max(0.5 - d / feather, 0.0), 1.0)
            out[y, x] = t * t * (3 - 2 * t)
    return out


@pytest.mark.parametrize("kind", ["CIRCLE", "ELLIPSE", "ROUNDED_RECT"])
def test_soft_shapes_write_the_feathered_shape(empty_scene, kind):
    scene = empty_scene
    two_camera_scene(scene, 40, 30)
    scene.multiscale.active_index = 0
    item = scene.multiscale.cameras[0]
    bpy.ops.multiscale.mask_new(guide=False)  # black; camera 1's painted one kept
    assert bpy.ops.multiscale.mask_shape(
        shape=kind, centre=(0.45, 0.6), size=(0.5, 0.6), corner_radius=4.0, feather=5.0
    ) == {"FINISHED"}
    got = pixels(item.mask)[..., 0]
    # centre 0.6 from the bottom: 0.4 of the height from the top
    want = _soft_reference(kind, 40, 30, 0.45 * 40, 0.4 * 30, 20, 18, 4.0, 5.0)
    assert np.abs(got - want).max() <= 1 / 255 + 1e-6
    assert (want > 0.99).sum() > 50 and ((want > 0.01) & (want < 0.99)).sum() > 20
    # subtracting the same shape leaves no pixel of the mask claimed
    bpy.ops.multiscale.mask_shape(
        shape=kind,
        centre=(0.45, 0.6),
        size=(0.5, 0.6),
        corner_radius=4.0,
        feather=5.0,
        mode="SUBTRACT",
    )
    assert pixels(item.mask)[..., 0].max() <= 0.5 + 1 / 255


# --- the Image Editor's overlay ---------------------------------------------------------


def test_overlay_reads_every_listed_mask_and_finds_the_shown_one(empty_scene):
    from multiscale_camera.ui.mask_overlay import rig_masks, shown_index

    scene = empty_scene
    two_camera_scene(scene, 40, 30)
    items = scene.multiscale.cameras
    assert shown_index(scene, items[1].mask) == 1
    assert shown_index(scene, bpy.data.images.new("other", 4, 4)) == -1
    masks = rig_masks(scene, (20, 15))  # half size: pixel centres 1, 3, 5, ...
    for item, mask in zip(items, masks):
        full = pixels(item.mask)[..., 0] >= 0.5
        np.testing.assert_array_equal(mask, full[1::2, 1::2])
    items.add()  # an item without a mask: an empty one
    assert len(rig_masks(scene, (20, 15))) == 3 and not rig_masks(scene, (20, 15))[2].any()


def test_guides_due_are_the_shown_masks_with_a_missing_or_stale_guide(empty_scene):
    from multiscale_camera.ui.mask_ops import guide_key
    from multiscale_camera.ui.mask_overlay import guides_due

    scene = empty_scene
    c1, c2 = two_camera_scene(scene)
    items = scene.multiscale.cameras
    shown = [items[1].mask]
    assert list(guides_due(scene, shown)) == [items[1]]  # missing
    scene.multiscale.active_index = 1
    bpy.ops.multiscale.guide_update()
    assert guides_due(scene, shown) == []
    c2.rotation_euler.z += 0.05
    c1.location.z += 1.0  # camera 1's mask is not shown: not due
    bpy.context.view_layer.update()
    assert list(guides_due(scene, shown)) == [items[1]]  # stale
    failed = {"C2": guide_key(c2, scene)}  # failed for this very state: not again
    assert guides_due(scene, shown, failed) == []
    assert list(guides_due(scene, shown + [items[0].mask])) == [items[0], items[1]]


def test_pixel_window_bounds_the_projected_points(empty_scene):
    from multiscale_camera.adapters.cameras import pinhole_from_object
    from multiscale_camera.render.guide import pixel_window

    scene = empty_scene
    _c1, c2 = two_camera_scene(scene, 40, 30)
    cam = pinhole_from_object(c2, scene)
    rng = np.random.default_rng(5)
    points = np.array([0.6, -0.6, 2.3]) + rng.normal(0, 0.1, (50, 3))  # about the sphere
    pix, depth = cam.project(points)
    assert (depth > 0).all()
    for size in [(40, 30), (20, 15)]:
        x0, y0, x1, y1 = pixel_window(cam, points, size, pad=0)
        scaled = pix * (size[0] / 40)
        # every point's pixel is inside, and the box is no bigger than one pixel more
        assert (scaled[:, 0] >= x0).all() and (scaled[:, 0] <= x1).all()
        assert (scaled[:, 1] >= y0).all() and (scaled[:, 1] <= y1).all()
        assert x1 - x0 <= np.ptp(scaled[:, 0]) + 2 and y1 - y0 <= np.ptp(scaled[:, 1]) + 2
    behind = np.array(c2.matrix_world.translation) - 3 * np.array(cam.forward)
    assert pixel_window(cam, np.vstack([points, behind]), (40, 30)) == (0, 0, 40, 30)
    aside = cam.eye + 5 * cam.forward + 50 * np.cross(cam.forward, [0, 0, 1])
    assert pixel_window(cam, aside[None], (40, 30)) is None
    assert pixel_window(cam, np.zeros((0, 3)), (40, 30)) is None


def test_overlay_reads_the_shown_mask_each_time_the_others_every_few_seconds(empty_scene):
    from multiscale_camera.adapters.masks import write_mask_values
    from multiscale_camera.ui.mask_overlay import OTHERS_SECONDS, MaskOverlay, rig_masks

    scene = empty_scene
    two_camera_scene(scene, 40, 30)
    items = scene.multiscale.cameras
    overlay = MaskOverlay()
    first = overlay.masks_for(scene, 1, (40, 30), 100.0)
    for got, want in zip(first, rig_masks(scene, (40, 30))):
        np.testing.assert_array_equal(got, want)
    for item in items:  # both masks painted all white
        write_mask_values(item.mask, np.ones((30, 40), np.float32))
    again = overlay.masks_for(scene, 1, (40, 30), 101.0)
    assert again[1].all()  # the shown one: read again
    np.testing.assert_array_equal(again[0], first[0])  # the other: kept
    later = overlay.masks_for(scene, 1, (40, 30), 101.0 + OTHERS_SECONDS)
    assert later[0].all() and later[1].all()
    assert overlay.masks_for(scene, 0, (20, 15), 102.0 + OTHERS_SECONDS)[1].shape == (15, 20)
