"""A Blender scene's multiscale settings -> a checked core ``Rig``."""

import os
from dataclasses import replace

import bpy
import numpy as np

from ..core.errors import RigError
from ..core.geometry import Rig, resolve_conflicts
from ..core.methods import settings_for
from .cameras import pinhole_from_object, render_size
from .masks import animated_kind, mask_from_image, sequence_frame

EMPTY_LIST = (
    "The camera list is empty: add cameras in the 3D viewport's sidebar "
    "(Multiscale tab), largest scale first"
)


def processes_of(scene):
    """Worker processes the scene's Render > Performance > Threads asks for: its count
    when Fixed, else 0 (one per core), for a field's build and a render alike, with
    Blender's window open too: the workers start as fresh processes (``core.runtime``),
    not as forked copies of Blender, so they cannot inherit a lock that another of its
    threads held (forked copies of Blender 5.2's window once spun for good in its memory
    allocator)."""
    render = scene.render
    return int(render.threads) if render.threads_mode == "FIXED" else 0


UNSAVED_CACHE = (
    "The scene's field cache folder '{folder}' is relative to the .blend file, which is "
    "not saved yet: fields are kept in the extension's user folder until it is"
)


def cache_folder_of(scene):
    """(absolute folder or None, notice or None): the scene's own field cache folder
    (Multiscale > Preview and Cache > Cache Folder; '//' is the .blend's folder, so it
    travels with the file onto a render farm's shared storage). None: the default
    folder, also when a '//' path has no saved .blend to be relative to (the notice
    says so)."""
    folder = getattr(scene.multiscale, "cache_folder", "").strip()
    if not folder:
        return None, None
    if folder.startswith("//") and not bpy.data.filepath:
        return None, UNSAVED_CACHE.format(folder=folder)
    return os.path.normpath(bpy.path.abspath(folder)), None


def field_settings(scene):
    """The core ``Settings`` of the scene's quality, accuracy target and threads; a rig
    in motion asks for a steady layout (``rig_is_animated``), the same at every frame."""
    s = scene.multiscale
    settings = settings_for(s.quality, s.accuracy_px)
    return replace(settings, processes=processes_of(scene), steady=rig_is_animated(scene))


def _moves(block):
    """Whether an ID (object or camera data) has keys or drivers."""
    anim = getattr(block, "animation_data", None)
    return anim is not None and (anim.action is not None or len(anim.drivers) > 0)


def rig_is_animated(scene):
    """Whether any camera of the list can change from frame to frame: it, its camera
    data or a parent has keys or drivers, or it or a parent has constraints. Read from
    the original objects, so every frame (and every process of a farm) answers alike."""
    for item in scene.multiscale.cameras:
        obj = item.camera
        obj = getattr(obj, "original", None) or obj
        if obj is not None and _moves(getattr(obj, "data", None)):
            return True
        while obj is not None:
            if _moves(obj) or len(getattr(obj, "constraints", ())) > 0:
                return True
            obj = obj.parent
    return False


def rig_from_scene(scene, depsgraph=None, pixels=None, frames=None):
    """Build the rig from ``scene.multiscale``.

    ``pixels`` : dict, image name -> flat float32 buffer of that still mask's pixels
    just read (``Image.pixels.foreach_get``), used instead of reading them again.
    ``frames`` : ``adapters.masks.MaskFrames``, the decoded frames of mask sequences
    (the field service's), so that a sequence's frame file is loaded once.

    With ``depsgraph`` (a render's, or any evaluated depsgraph) every camera is read as
    that depsgraph evaluated it: its transform, lens, sensor, shift and clipping at the
    depsgraph's frame. The list's pointers name the original objects, whose state is the
    one of the last frame the main window evaluated, not the frame being rendered.

    Returns
    -------
    Rig, whose ``notices`` say what was adjusted (resampled masks, shared pixels).

    Raises
    ------
    RigError with a message naming the list item or camera and what to change.
    """
    settings = scene.multiscale
    if len(settings.cameras) == 0:
        raise RigError(EMPTY_LIST)
    width, height = render_size(scene)
    cameras, masks, notices = [], [], []
    for number, item in enumerate(settings.cameras, start=1):
        obj = item.camera
        if obj is None:
            raise RigError(
                f"Camera list item {number} has no camera (none was set, or it was deleted): "
                "pick a camera for it or remove the item"
            )
        if obj.type != "CAMERA":
            raise RigError(
                f"Camera list item {number}: '{obj.name}' is not a camera but a "
                f"{obj.type.lower()}; pick a camera object"
            )
        cameras.append(pinhole_from_object(evaluated(obj, depsgraph), scene))
        buf = None if pixels is None or item.mask is None else pixels.get(item.mask.name)
        frame = mask_frame(item, scene)
        mask, said = mask_from_image(item.mask, width, height, frame, buf, frames)
        masks.append(mask)
        notices += said
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise RigError("A camera appears twice in the camera list; each camera may appear once")
    masks, said = resolve_conflicts(np.stack(masks), names)
    return Rig(tuple(cameras), masks, beta=float(settings.beta), notices=tuple(notices + said))


def mask_frame(item, scene):
    """The frame number of ``item``'s mask sequence or movie at ``scene``'s frame (the
    item keeps frames, start, offset and cyclic as an image user does); None when the
    mask is still."""
    if animated_kind(item.mask) is None:
        return None
    return sequence_frame(
        scene.frame_current,
        item.mask_frames,
        item.mask_frame_start,
        item.mask_frame_offset,
        item.mask_cyclic,
    )


def evaluated(obj, depsgraph):
    """``obj`` as ``depsgraph`` evaluated it (``obj`` itself without a depsgraph, or when
    the depsgraph does not hold it: a camera outside the view layer keeps its own
    state)."""
    if depsgraph is None or obj.is_evaluated:
        return obj
    return obj.evaluated_get(depsgraph)
