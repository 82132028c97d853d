"""Blender images -> boolean masks at the render size (row 0 at the top).

A mask that is an image sequence or a movie is read at a frame: the number Blender's
own image user gives for the scene's frame (``sequence_frame``: frames, start, offset,
cyclic, kept on the camera's list item). A sequence's frame is the file ``frame_path``
names, loaded for its pixels; a movie's is decoded by Blender's own FFmpeg
(``adapters.movies.movie_frame``). Each frame is read once, on the main thread, through
temporary Blender data removed at once (loading changes Blender's data, which redraws
every view and may not happen on a render thread); its pixels are kept (``MaskFrames``,
one owned by the field service, keyed by the file's absolute path, modification time,
colour space and, for a movie, the frame number), so reading the rig again, as the
Rendered viewport does while it draws, changes nothing in Blender's data.
"""

import os
import re
import threading
from collections import OrderedDict

import bpy
import numpy as np

from ..core.errors import RigError
from .movies import movie_frame

# Rec. 709 luminance weights: white (preserved) is luminance >= 0.5.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
THRESHOLD = 0.5
# Image sources whose pixels change with the frame.
ANIMATED_SOURCES = {"SEQUENCE": "an image sequence", "MOVIE": "a movie"}
ANIMATED_MASK = (
    "Mask '{name}' is {kind}, read here without a frame number; treated as preserving nothing"
)
# A frame of a mask sequence whose file cannot be read.
MISSING_FRAME = (
    "Mask '{name}' has no frame {number} ('{path}' is missing or unreadable); treated as "
    "empty at this frame: check the sequence's files, or the camera's mask Frames, "
    "Start and Offset"
)
# A movie mask whose file Blender cannot play.
MOVIE_UNREADABLE = (
    "Mask '{name}' is a movie Blender cannot read ('{path}' is missing, or not a video "
    "its FFmpeg decodes); treated as empty: check the file, or pick it again in the "
    "Image Editor (Image > Replace)"
)
# A frame of a mask sequence or movie first needed off the main thread (a render's thread).
FRAME_NOT_LOADED = (
    "Mask '{name}' frame {number} ('{path}') was not loaded before the render started "
    "and cannot be loaded during it; treated as empty at this frame: show that frame "
    "in the viewport once, or render again"
)
# Decoded frames of mask sequences and movies kept by a ``MaskFrames``.
FRAMES_KEPT = 8


def animated_kind(image):
    """'an image sequence' or 'a movie' when ``image``'s pixels change with the frame,
    else None."""
    return None if image is None else ANIMATED_SOURCES.get(getattr(image, "source", ""))


def sequence_frame(frame, frames, start=1, offset=0, cyclic=False):
    """The frame number of an image sequence shown at scene frame ``frame``, as
    Blender's image user maps it: the sequence plays ``frames`` frames from scene frame
    ``start`` (held on its last frame after it, or repeated when ``cyclic``), numbered
    from 1 plus ``offset``; before ``start`` (not cyclic) Blender gives frame 0 plus
    ``offset``. 0 frames: 0 (Blender's answer).

    All ints; returns int."""
    if frames <= 0:
        return 0
    number = frame - start + 1
    if cyclic:
        number %= frames
        if number == 0:
            number = frames
    number = min(max(number, 0), frames)
    return number + offset


def frame_path(filepath, number):
    """``filepath`` with the last run of digits in its file name replaced by
    ``number``, zero-padded to that run's length (the numbering of Blender's image
    sequences); unchanged when the name has no digits."""
    folder, name = os.path.split(filepath)
    stem, ext = os.path.splitext(name)
    runs = list(re.finditer(r"\d+", stem))
    if not runs:
        return filepath
    run = runs[-1]
    digits = f"{number:0{len(run.group())}d}"
    return os.path.join(folder, stem[: run.start()] + digits + stem[run.end() :] + ext)


class MaskFrames:
    """Decoded frames of mask image sequences and movies: (absolute path, mtime, colour
    space, movie frame number or None) -> (H, W, 4) float32 RGBA, the ``kept`` most
    recent; one is owned by the field service (``render.fields.SERVICE.mask_frames``)
    and passed to ``rig_from_scene``. A frame is read on the main thread only; the files
    first wanted off it are remembered."""

    def __init__(self, kept=FRAMES_KEPT):
        self.kept = kept
        self.decoded = OrderedDict()
        self.not_loaded = set()
        self.lock = threading.Lock()

    def clear(self):
        with self.lock:
            self.decoded.clear()
            self.not_loaded.clear()

    def wanted_off_main_thread(self, path):
        """Whether the frame file ``path`` was wanted off the main thread, not loaded."""
        return path in self.not_loaded

    def pixels(self, image, number):
        """(H, W, 4) float32 RGBA (row 0 at the top, read-only) of frame ``number`` of
        the image sequence or movie ``image``, and the absolute path of the file read
        (the frame's file for a sequence, the movie's); (None, path) when it cannot be
        read. A frame is read once (main thread only) and then taken from here; first
        wanted off the main thread, it is not read: (None, path), with
        ``wanted_off_main_thread(path)`` true."""
        movie = image.source == "MOVIE"
        name = image.filepath if movie else frame_path(image.filepath, number)
        path = bpy.path.abspath(name, library=image.library)
        try:
            mtime = os.stat(path).st_mtime_ns
        except OSError:
            return None, path
        colorspace = image.colorspace_settings.name
        key = (os.path.normpath(path), mtime, colorspace, number if movie else None)
        with self.lock:
            rgba = self.decoded.get(key)
            if rgba is not None:
                self.decoded.move_to_end(key)
                return rgba, path
            if threading.current_thread() is not threading.main_thread():
                self.not_loaded.add(path)
                return None, path
        rgba = movie_frame(path, number) if movie else still_frame(path, colorspace)
        if rgba is None:
            return None, path
        rgba = np.ascontiguousarray(rgba)
        rgba.flags.writeable = False
        with self.lock:
            self.decoded[key] = rgba
            self.not_loaded.discard(path)
            while len(self.decoded) > self.kept:
                self.decoded.popitem(last=False)
        return rgba, path


def still_frame(path, colorspace):
    """(H, W, 4) float32 RGBA (row 0 at the top) of the image file ``path`` read in
    ``colorspace``, through a temporary Blender image removed at once (main thread
    only); None when Blender cannot read it."""
    try:
        still = bpy.data.images.load(path, check_existing=False)
    except RuntimeError:
        return None
    try:
        still.colorspace_settings.name = colorspace
        return image_pixels(still)
    finally:
        bpy.data.images.remove(still)


def image_pixels(image, buf=None):
    """(H, W, 4) float32 RGBA of a Blender image, row 0 at the top.

    ``buf`` : flat float32 array of the image's pixels as ``Image.pixels`` gives them,
    already read (used as it is, not read again, when its size fits).

    Returns None when the image has no pixels (missing file, empty buffer).
    """
    w, h = image.size
    if w == 0 or h == 0:
        return None
    if buf is None or buf.size != w * h * image.channels:
        buf = np.empty(w * h * image.channels, dtype=np.float32)
        image.pixels.foreach_get(buf)
    rgba = buf.reshape(h, w, image.channels)[::-1]
    if image.channels < 3:
        rgba = np.repeat(rgba[..., :1], 3, axis=-1)
    return rgba


def resample_nearest(mask, width, height):
    """Nearest-neighbour resampling of an (h, w) array to (height, width), centres aligned."""
    h, w = mask.shape
    ys = ((np.arange(height) + 0.5) * (h / height)).astype(int).clip(0, h - 1)
    xs = ((np.arange(width) + 0.5) * (w / width)).astype(int).clip(0, w - 1)
    return mask[ys][:, xs]


def mask_from_image(image, width, height, frame=None, buf=None, frames=None):
    """A bool (height, width) mask from a Blender image, and notices about it.

    ``frame`` : int, the frame number to read when ``image`` is an image sequence or
    a movie (``sequence_frame``); without it such a mask reads as empty, with a notice.
    ``buf`` : a still image's pixels already read (``image_pixels``).
    ``frames`` : the ``MaskFrames`` that keeps decoded frames (without it, a frame is
    read for this call alone).

    Returns
    -------
    mask : (height, width) bool array, True where luminance >= 0.5.
    notices : list of str.
    """
    if image is None:
        return np.zeros((height, width), dtype=bool), []
    kind = animated_kind(image)
    if kind is not None and frame is None:
        notice = ANIMATED_MASK.format(name=image.name, kind=kind)
        return np.zeros((height, width), dtype=bool), [notice]
    if kind is not None:
        frames = frames if frames is not None else MaskFrames()
        rgba, path = frames.pixels(image, frame)
        if rgba is None:
            if frames.wanted_off_main_thread(path):
                message = FRAME_NOT_LOADED
            else:
                message = MOVIE_UNREADABLE if image.source == "MOVIE" else MISSING_FRAME
            notice = message.format(name=image.name, number=frame, path=path)
            return np.zeros((height, width), dtype=bool), [notice]
    else:
        rgba = image_pixels(image, buf)
    if rgba is None:
        return np.zeros((height, width), dtype=bool), [
            f"Mask '{image.name}' has no pixels (is its file missing?); treated as empty"
        ]
    mask = rgba[..., :3] @ LUMINANCE >= THRESHOLD
    if not mask.any() and image.channels == 4:
        alpha = rgba[..., 3] >= THRESHOLD
        if alpha.any() and not alpha.all():
            raise RigError(ALPHA_ONLY.format(name=image.name))
    notices = []
    if mask.shape != (height, width):
        notices.append(
            f"Mask '{image.name}' is {mask.shape[1]}x{mask.shape[0]}, the render is "
            f"{width}x{height}: resampled to the render size"
        )
        kept = mask.any()
        mask = resample_nearest(mask, width, height)
        if kept and not mask.any():
            raise RigError(LOST_AT_SIZE.format(name=image.name, width=width, height=height))
    return mask, notices


# A mask whose shape is in its alpha alone (its colour all black).
ALPHA_ONLY = (
    "Mask '{name}' is black in colour and holds its shape in alpha only; masks are read "
    "from their colour (white: kept), not from alpha: paint the kept area white (Image "
    "editor, Paint mode), or save the image without alpha"
)
# A mask whose white area vanishes at the render size.
LOST_AT_SIZE = (
    "Mask '{name}' keeps no pixel at the render size {width}x{height}: its white area is "
    "smaller than a pixel there; raise Output Properties > Format > Resolution (or its %), "
    "or widen the white area"
)


def image_from_rgba(name, rgba, colorspace=None, pack=True):
    """A Blender image (replacing one of the same name) from (H, W, 4) float RGBA, row 0 at
    the top, packed into the .blend file so it survives save and reload."""
    h, w = rgba.shape[:2]
    old = bpy.data.images.get(name)
    if old is not None:
        bpy.data.images.remove(old)
    img = bpy.data.images.new(name, w, h, alpha=False, float_buffer=False)
    if colorspace is not None:
        try:
            img.colorspace_settings.name = colorspace
        except TypeError:  # a colour space this Blender does not know
            pass
    img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1], dtype=np.float32).ravel())
    if pack:
        img.pack()
    return img


def new_mask_image(name, width, height):
    """A black (nothing preserved) mask of ``width`` x ``height``, Non-Color, packed.
    An image of that name is replaced."""
    rgba = np.zeros((height, width, 4), dtype=np.float32)
    rgba[..., 3] = 1.0
    return image_from_rgba(name, rgba, colorspace="Non-Color")


def mask_values(image):
    """(H, W) float32 luminance of a mask image in [0, 1], row 0 at the top; None when
    the image has no pixels."""
    rgba = image_pixels(image)
    if rgba is None:
        return None
    return np.clip(rgba[..., :3] @ LUMINANCE, 0.0, 1.0).astype(np.float32)


def write_mask_values(image, grey):
    """Write (H, W) grey values in [0, 1] (row 0 at the top, the image's size) into every
    colour channel of ``image``, alpha 1; packed again if it was packed or generated, so
    the change survives save and reload."""
    w, h = image.size
    if grey.shape != (h, w):
        raise ValueError(f"Mask values are {grey.shape[1]}x{grey.shape[0]}, the image {w}x{h}")
    rgba = np.ones((h, w, image.channels), dtype=np.float32)
    rgba[..., : min(3, image.channels)] = grey[..., None]
    image.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())
    image.update()
    if image.packed_file is not None or image.source == "GENERATED":
        image.pack()
