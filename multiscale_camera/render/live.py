"""The live picture's work: a PREVIEW field of the rig at a small size and a render of
it, on a worker thread, cancelled by the next change (``ui/live_picture.py`` drives it).

What needs Blender is read on the main thread when a job is made (``LiveJob.of``): the
rig at the picture's size (``small_rig``), the field request (``fields.SERVICE``, at
PREVIEW), the scene's triangles (the BVH tree is the frame's, kept by the field
service), lights, world and volumes. The thread then gets the field through the field
service (cached, or built in its worker processes), simplifies its rays and renders
the picture in its own process (at 480x270, 130k rays: fewer than sending them to
render workers pays for, ``workers.MIN_RAYS``), one ray per pixel through its centre,
volumes left out. The field is the rig's at half the picture's width
(``LIVE_FIELD_WIDTH``): the picture's rays run between the field's pixels, as a
sub-pixel sample's do: a field without a traced lattice of its own (IMAGE_BLEND) has
every pixel's ray simplified once (``core.sampling.PixelRays``), so that the picture's
rays gather their kept vertices rather than being blended and simplified one by one.
Its cancel check stops the build, the simplification and the casts; a cancelled job
ends without a picture.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np

from ..adapters.lights import scene_lights, scene_world
from ..adapters.masks import resample_nearest
from ..adapters.meshes import scene_geometry
from ..adapters.scene import processes_of, rig_from_scene
from ..core.diagnostics import Diagnostics
from ..core.errors import Cancelled
from ..core.geometry import Rig
from ..core.sampling import DEFAULT_TOLERANCE_PX
from . import pipeline
from .fields import LIVE_THREAD, SERVICE

# The live picture is at most this many pixels wide (the render's aspect kept).
LIVE_MAX_WIDTH = 480
# Its field is built for the rig at half that width (the build's seconds fall with the
# rays traced: on the demo 4.3 CPU seconds at 240 wide against 7.3 at 480, in one
# process) and at PREVIEW quality; the picture casts the field's rays between its
# pixels.
LIVE_FIELD_WIDTH = 240
LIVE_QUALITY = "PREVIEW"


def live_size(width, height, max_width=LIVE_MAX_WIDTH):
    """(w, h) of the live picture for a render of ``width`` x ``height`` pixels: at most
    ``max_width`` wide, the aspect kept (h rounded, at least 1)."""
    w = min(int(width), int(max_width))
    return w, max(1, round(height * w / width))


def small_rig(rig: Rig, size) -> Rig:
    """``rig`` at ``size`` = (w, h) pixels: every camera renders that size (its frustum
    kept: the view plane scales with the pixel count) and every mask is resampled to it
    (nearest pixel). A mask whose white area vanishes at that size keeps its nearest
    pixel to its centre of mass, so a small camera still shows.

    Raises RigError when the rig cannot be built at that size."""
    w, h = size
    if rig.size == (w, h):
        return rig
    cameras = tuple(replace(cam, width=w, height=h) for cam in rig.cameras)
    masks = np.stack([resample_nearest(m, w, h) for m in rig.masks])
    for small, full in zip(masks, rig.masks):
        if full.any() and not small.any():
            ys, xs = np.nonzero(full)
            y = min(int(ys.mean() * h / full.shape[0]), h - 1)
            x = min(int(xs.mean() * w / full.shape[1]), w - 1)
            small[y, x] = True
    taken = np.cumsum(masks[::-1], axis=0)[::-1]  # the smaller scale keeps a shared pixel
    masks[:-1] &= ~taken[1:].astype(bool)
    return Rig(cameras, masks, beta=rig.beta, notices=rig.notices)


class LiveJob:
    """One live picture on a worker thread (numpy, the field service and the BVH tree;
    no bpy).

    Attributes
    ----------
    key : object, what the picture was asked for (the caller's change key).
    size : (w, h) pixels of the picture; the field's rig is smaller (``field_size``).
    started : float, ``time.perf_counter`` of the change it answers.
    rgba : (h, w, 4) float32 linear RGBA, row 0 at the top, once done; else None.
    error : Exception or None. cancelled : bool. built : bool, the field was built
    (not cached). seconds : dict, wall seconds of the stages (field, simplify, render).
    """

    def __init__(self, key, request, parts, size, started=None):
        self.key = key
        self.request = request
        self.parts = parts  # Frame fields read on the main thread
        self.size = tuple(size)
        self.field_size = request.rig.size
        self.started = time.perf_counter() if started is None else started
        self.rgba = None
        self.error = None
        self.cancelled = False
        self.built = False
        self.seconds = {}
        self._stop = threading.Event()
        self.diag = Diagnostics(should_stop=self._stop.is_set)
        self._thread = threading.Thread(target=self._run, name=LIVE_THREAD, daemon=True)

    @classmethod
    def of(
        cls,
        scene,
        depsgraph,
        key=None,
        started=None,
        max_width=LIVE_MAX_WIDTH,
        field_width=LIVE_FIELD_WIDTH,
        pixels=None,
    ):
        """The job of ``scene`` as ``depsgraph`` evaluates it (main thread), not yet
        started: a picture at most ``max_width`` wide from a field at most
        ``field_width`` wide. Raises RigError (and what reading the scene raises) when
        the rig cannot render. ``pixels``: the masks' pixels just read
        (``adapters.scene.rig_from_scene``), not read again."""
        rig = rig_from_scene(scene, depsgraph, pixels, SERVICE.mask_frames)
        size = live_size(*rig.size, max_width)
        rig = small_rig(rig, live_size(*rig.size, min(field_width, max_width)))
        # asked as the scene changes, and its own build: no stepping through the frames
        # for a shot's layout, and the render's frame reuse (SERVICE.reuse) is left alone
        request = SERVICE.request(
            scene, rig=rig, quality=LIVE_QUALITY, step_frames=False, steady=False
        )
        geometry = scene_geometry(depsgraph)
        tree, bounds, occupancy, scale = None, None, None, 1.0
        if len(geometry):
            tree, bounds, occupancy, scale = pipeline.scene_tree(geometry)
        parts = {
            "geometry": geometry,
            "tree": tree,
            "bounds": bounds,
            "occupancy": occupancy,
            "scale": max(scale, 1e-6),
            "lights": scene_lights(depsgraph),
            "world": scene_world(scene, []),
            "transparent": bool(scene.render.film_transparent),
            "tol": getattr(scene.multiscale, "simplify_px", DEFAULT_TOLERANCE_PX),
            "processes": processes_of(scene),
        }
        return cls(key, request, parts, size, started)

    def launch(self) -> LiveJob:
        self._thread.start()
        return self

    def alive(self) -> bool:
        return self._thread.is_alive()

    def cancel(self) -> None:
        self._stop.set()

    def stopped(self) -> bool:
        """Whether it was asked to stop (its picture, if it made one, is not wanted)."""
        return self._stop.is_set()

    def join(self, timeout=None) -> None:
        self._thread.join(timeout)

    def _run(self):
        try:
            self.rgba = self.render()
        except Cancelled:
            self.cancelled = True
        except Exception as err:  # handed to the main thread, shown in the panel
            self.error = err

    def render(self):
        """(h, w, 4) float32 RGBA of the picture, row 0 at the top (in the calling
        thread). Raises Cancelled when cancelled."""
        diag, p = self.diag, self.parts
        with diag.stage("field"):
            result = SERVICE.get(self.request, diag)
        self.built = result.built
        with diag.stage("simplify"):
            # in this thread: the field's 32k rays cost less here than the round trip
            # to the worker processes (on the demo, 0.24 s against 0.31 s, median of 6
            # strokes, two cores at load 3)
            sampler = pipeline.sampler_for(
                result.field,
                p["tol"],
                p["bounds"],
                diag.should_stop,
                p["occupancy"],
                1,
                pixel_rays=True,
            )
        frame = pipeline.Frame(
            rig=result.field.rig,
            field=result.field,
            geometry=p["geometry"],
            tree=p["tree"],
            lights=p["lights"],
            world=p["world"],
            transparent=p["transparent"],
            scale=p["scale"],
            diag=diag,
            sampler=sampler,
            bounds=p["bounds"],
            processes=p["processes"],
            occupancy=p["occupancy"],
        )
        w, h = self.size
        fw, fh = self.field_size
        out = np.empty((h, w, 4), np.float32)
        with diag.stage("render"):
            rows = pipeline.rows_per_tile(w)
            for row0 in range(0, h, rows):
                diag.check()
                iy, ix = np.mgrid[row0 : min(row0 + rows, h), 0:w]
                # the picture's pixel centres in the field's pixels
                sx = (ix.ravel() + 0.5) * (fw / w)
                sy = (iy.ravel() + 0.5) * (fh / h)
                seg = sampler.segments(sx, sy)
                hits, shaded = pipeline._cast_and_shade(frame, seg, diag.should_stop)
                out[row0 : row0 + iy.shape[0]] = pipeline._rgba(frame, hits, shaded).reshape(
                    iy.shape[0], w, 4
                )
        self.seconds = dict(diag.seconds)
        return out


__all__ = [
    "LIVE_FIELD_WIDTH",
    "LIVE_MAX_WIDTH",
    "LIVE_QUALITY",
    "LiveJob",
    "live_size",
    "small_rig",
]
