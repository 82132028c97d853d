"""A shot: the frames a rig in motion is keyed over (else the scene's frame range). Its
layout (the grids of every frame, ``core.methods.plan_shot``) needs each frame's
cameras, and AUTO's one method for it (``core.methods.choose_shot_method``) a few
frames' rigs (``sampled_rigs``); they are read by stepping the scene through its frames
and back, which only Blender's main thread may do (a render started from the window
runs its engine on a thread of its own)."""

import hashlib
import threading

import numpy as np

from ..core.geometry import Rig
from ..core.methods import sample_frames
from .cameras import pinhole_from_object
from .masks import ANIMATED_SOURCES
from .scene import evaluated, rig_from_scene

try:  # Blender 4.4 and later: an action's curves live in the channel bag of a slot
    from bpy_extras.anim_utils import action_get_channelbag_for_slot
except ImportError:  # Blender 4.2, 4.3: the action holds them
    action_get_channelbag_for_slot = None

# Frames a shot's layout reads at most (evenly spread over the range, both ends kept): a
# frame between two read ones whose rig leaves the layout gets a layout of its own.
MAX_SHOT_FRAMES = 240


def _blocks(scene):
    """Every ID a list camera's state at a frame comes from: its camera data, the
    object and its parents (original data blocks)."""
    for item in scene.multiscale.cameras:
        obj = item.camera
        obj = getattr(obj, "original", None) or obj
        if obj is None:
            continue
        yield obj.data
        while obj is not None:
            yield obj
            obj = obj.parent


def shot_range(scene):
    """(first, last) frame of the shot: the span of the list cameras' keys (their data's
    and their parents' too), the same in every process whatever frames it was asked to
    render (``blender -s A -e B`` sets the scene's range); the scene's frame range where
    nothing is keyed (drivers or constraints alone)."""
    scene = getattr(scene, "original", None) or scene
    spans = [
        curve.range()
        for block in _blocks(scene)
        if getattr(block, "animation_data", None) is not None
        for curve in _fcurves(block.animation_data)
    ]
    if not spans:
        return int(scene.frame_start), int(scene.frame_end)
    return int(np.floor(min(a for a, _b in spans))), int(np.ceil(max(b for _a, b in spans)))


def shot_keys(scene):
    """The frames (floats, ascending, no repeats) of the list cameras' keys: their
    objects', parents' and camera data's F-curves."""
    scene = getattr(scene, "original", None) or scene
    keys = set()
    for block in _blocks(scene):
        anim = getattr(block, "animation_data", None)
        for curve in _fcurves(anim) if anim is not None else []:
            got = np.zeros(2 * len(curve.keyframe_points), dtype=np.float64)
            curve.keyframe_points.foreach_get("co", got)
            keys.update(got[0::2].tolist())
    return sorted(keys)


def shot_samples(scene):
    """The frames of the shot AUTO measures IMAGE_BLEND on (``core.methods.sample_frames``
    of ``shot_range`` and ``shot_keys``): the same in every process."""
    first, last = shot_range(scene)
    return sample_frames(first, last, shot_keys(scene))


def sampled_rigs(scene, frames, depsgraph=None, mask_frames=None):
    """[(frame, Rig)] of the scene at each of ``frames``: each frame's cameras as the view
    layer evaluates them there and each frame's masks (``rig_from_scene``, sequences
    read at that frame through ``mask_frames``, an ``adapters.masks.MaskFrames``). The
    scene is stepped and set back to its frame and subframe. None when this thread may
    not step frames (``can_step_frames``)."""
    return _at_frames(
        scene,
        frames,
        depsgraph,
        lambda s, f, graph: (int(f), rig_from_scene(s, graph, frames=mask_frames)),
    )


def masks_source_digest(scene, rig):
    """Hex digest of what the shot's masks are: ``rig``'s masks (the frame's) when every
    mask is still, else each list item's mask image, file and sequence mapping (frames,
    start, offset, cyclic), so that every frame of a shot with animated masks names the
    same shot."""
    scene = getattr(scene, "original", None) or scene
    items = list(scene.multiscale.cameras)
    images = [item.mask for item in items]
    h = hashlib.sha1()
    if not any(getattr(im, "source", "") in ANIMATED_SOURCES for im in images):
        h.update(np.packbits(np.ascontiguousarray(rig.masks)).tobytes())
        return h.hexdigest()
    for item, im in zip(items, images, strict=True):
        source = None if im is None else (im.name, im.source, im.filepath)
        mapping = tuple(
            getattr(item, k, None)
            for k in ("mask_frames", "mask_frame_start", "mask_frame_offset", "mask_cyclic")
        )
        h.update(repr((source, mapping)).encode())
    return h.hexdigest()


def _layer(scene, depsgraph):
    """The view layer of the render's ``depsgraph`` (else the scene's first)."""
    name = depsgraph.view_layer.name if depsgraph is not None else None
    layer = scene.view_layers.get(name) if name else None
    return layer if layer is not None else scene.view_layers[0]


def shot_frames(scene):
    """The frames of the shot (``shot_range``) its layout reads: every one, or
    MAX_SHOT_FRAMES evenly spread over a longer shot, both ends kept."""
    first, last = shot_range(scene)
    if last - first + 1 <= MAX_SHOT_FRAMES:
        return list(range(first, last + 1))
    return sorted({int(round(f)) for f in np.linspace(first, last, MAX_SHOT_FRAMES)})


def can_step_frames():
    """Whether this thread may step the scene through its frames (Blender's main one)."""
    return threading.current_thread() is threading.main_thread()


def shot_rigs(scene, rig, depsgraph=None):
    """``rig`` (the current frame's) at every frame of ``shot_frames``: its masks and
    beta, each frame's cameras as the view layer evaluates them there. The scene is
    stepped through the frames and set back to its frame and subframe.

    scene : bpy Scene (an evaluated one is followed to its original). depsgraph : the
    render's, to name the view layer (else the scene's first). Returns a list of Rig, or
    None when this thread may not step frames (``can_step_frames``).
    """

    def rig_at(s, _f, graph):
        cams = [
            pinhole_from_object(evaluated(item.camera, graph), s) for item in s.multiscale.cameras
        ]
        return Rig(tuple(cams), rig.masks, beta=rig.beta)

    original = getattr(scene, "original", None) or scene
    return _at_frames(original, shot_frames(original), depsgraph, rig_at)


def _at_frames(scene, frames, depsgraph, make):
    """[make(scene, frame, depsgraph) for each of ``frames``], the scene (an evaluated
    one is followed to its original) stepped to each frame and set back to its frame
    and subframe after; ``depsgraph`` (the render's, or None) names the view layer
    whose depsgraph ``make`` gets. None when this thread may not step frames
    (``can_step_frames``)."""
    if not can_step_frames():
        return None
    scene = getattr(scene, "original", None) or scene
    layer = _layer(scene, depsgraph)
    frame, subframe = scene.frame_current, scene.frame_subframe
    out = []
    try:
        for f in frames:
            scene.frame_set(f)
            out.append(make(scene, f, layer.depsgraph))
    finally:
        scene.frame_set(frame, subframe=subframe)
    return out


def _fcurves(anim):
    """The F-curves of an animation data block's action (none without one)."""
    action = anim.action
    if action is None:
        return []
    if action_get_channelbag_for_slot is None:
        return list(action.fcurves)
    bag = action_get_channelbag_for_slot(action, anim.action_slot)
    return list(bag.fcurves) if bag is not None else []


def _curve_bytes(curve):
    """A curve's path, index, keys (frame, value and handles) and extrapolation."""
    points = curve.keyframe_points
    values = []
    for attr in ("co", "handle_left", "handle_right"):
        got = np.zeros(2 * len(points), dtype=np.float32)
        points.foreach_get(attr, got)
        values.append(got.tobytes())
    kinds = [(k.interpolation, k.easing) for k in points]
    head = repr((curve.data_path, curve.array_index, curve.extrapolation, curve.mute, kinds))
    return head.encode() + b"".join(values)


def _block_bytes(block):
    """What of an ID (object or camera data) a frame's camera depends on: its keys and
    drivers, and its own values where nothing animates them."""
    out = [repr(block.name).encode()]
    anim = getattr(block, "animation_data", None)
    curves = _fcurves(anim) if anim is not None else []
    drivers = list(anim.drivers) if anim is not None else []
    out += [_curve_bytes(c) for c in curves]
    for d in drivers:
        out.append(repr((d.data_path, d.array_index, d.driver.expression)).encode())
        for var in d.driver.variables:
            targets = [(t.id.name if t.id else None, t.data_path) for t in var.targets]
            out.append(repr((var.name, var.type, targets)).encode())
    if not curves and not drivers:  # its own values hold at every frame
        if hasattr(block, "matrix_basis"):
            out.append(np.array(block.matrix_basis, dtype=np.float64).tobytes())
        else:
            keys = ("lens", "sensor_width", "sensor_height", "shift_x", "shift_y")
            keys += ("clip_start", "clip_end", "sensor_fit", "type")
            out.append(repr([getattr(block, k, None) for k in keys]).encode())
    for con in getattr(block, "constraints", ()):
        target = getattr(con, "target", None)
        out.append(repr((con.type, con.influence, con.mute, target and target.name)).encode())
    return b"".join(out)


def animation_digest(scene):
    """Hex digest of what the list's cameras do over the shot: its range
    (``shot_range``), and for each camera, its data and its parents, their keys,
    drivers and constraints (and their own values where nothing animates them).
    Objects that drive or constrain a camera from elsewhere are named, not followed: a
    frame whose rig left a stale layout gets one of its own."""
    scene = getattr(scene, "original", None) or scene
    h = hashlib.sha1(repr(shot_range(scene)).encode())
    for block in _blocks(scene):
        h.update(_block_bytes(block))
        if hasattr(block, "matrix_parent_inverse"):
            h.update(np.array(block.matrix_parent_inverse, dtype=np.float64).tobytes())
    return h.hexdigest()
