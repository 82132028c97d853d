"""Frame-to-frame jumps of a sequential animation render.

Each rendered frame leaves its first hits (the object and the world point each pixel's
centre ray hits first); the next frame of the same sequence (the frame ``frame_step``
after it, same file, scene, view layer and size) measures how far they moved: over the
pixels whose first hit is on the same object in both frames, the p95 of the move in
pixels of the multiscale image. A pixel's size at its hit is the distance to its right
or lower neighbour's hit on the same object (the nearer of the two), so a move reads in
the pixels the picture shows there, whatever camera's scale holds it. A rig that moves
smoothly moves its hits by a fraction of a pixel or a few pixels a frame; a field that
re-snapped its layout between two frames shows as a jump well above its neighbours'.

Objects are told apart by an ordinal the sequence gives each object name, not by the
objects' pass index (0 on every object unless the user set it).
"""

from dataclasses import dataclass

import numpy as np

# Percentile of the per-pixel move that a frame's jump reports.
JUMP_PERCENTILE = 95


def pixel_size(index, hits):
    """(H, W) float64: the world distance from each pixel's first hit to its right or
    lower neighbour's (the nearer, among those on the same object); NaN where neither
    neighbour hit the same object. ``index`` (H, W) object index (0: no hit), ``hits``
    (H, W, 3) world points."""
    size = np.full(index.shape, np.inf)
    for axis in (0, 1):
        step = np.linalg.norm(np.diff(hits, axis=axis), axis=-1)
        same = (np.diff(index, axis=axis) == 0) & ((index[1:] if axis == 0 else index[:, 1:]) > 0)
        step = np.where(same & (step > 0), step, np.inf)
        lead = (slice(0, -1), slice(None)) if axis == 0 else (slice(None), slice(0, -1))
        size[lead] = np.minimum(size[lead], step)
    return np.where(np.isfinite(size), size, np.nan)


def jump_px(index0, hits0, index1, hits1, percentile=JUMP_PERCENTILE):
    """The ``percentile`` of the first-hit move between two frames, in pixels (of the
    second frame's hits), over the pixels whose first hit is on the same object in both
    and whose size is known; None when no pixel qualifies.

    index0, index1 : (H, W) int or float, object index (0: no hit).
    hits0, hits1 : (H, W, 3) float, world points.
    """
    size = pixel_size(index1, hits1)
    same = (index0 == index1) & (index1 > 0) & np.isfinite(size)
    if not same.any():
        return None
    move = np.linalg.norm(hits1[same] - hits0[same], axis=-1) / size[same]
    return float(np.percentile(move, percentile))


@dataclass
class Jump:
    """What ``Sequence.add`` measured: ``px`` the jump from the previous frame (None:
    the frame starts a sequence, or no pixel qualified), ``worst_px`` and
    ``worst_frame`` the worst of the sequence so far (None before any)."""

    px: float | None
    worst_px: float | None
    worst_frame: int | None

    def as_dict(self):
        return {
            "jump_p95_px": self.px,
            "worst_jump_p95_px": self.worst_px,
            "worst_jump_frame": self.worst_frame,
        }


# Renders (file, scene, view layer) whose last frame a Sequence keeps at once.
MAX_RENDERS = 8


class Sequence:
    """Per render (``key``: file, scene and view layer), the last frame's first hits and
    the worst jump of its sequence: view layers rendered in turn at each frame each
    follow their own sequence."""

    def __init__(self):
        self.last = {}  # key -> (frame, index, hits)
        self.worst = {}  # key -> (px, frame)
        self.ordinals = {}  # object name -> its ordinal (1, 2, ...) in this sequence

    def object_index(self, names, hit_object):
        """(H, W) float64: each pixel's object as the sequence's ordinal of its name
        (0: no hit). names : the frame's object names. hit_object : (H, W) the index of
        the hit object in ``names`` plus one (0: no hit)."""
        for name in names:
            self.ordinals.setdefault(name, len(self.ordinals) + 1)
        lookup = np.array([0] + [self.ordinals[n] for n in names], dtype=np.float64)
        return lookup[np.asarray(hit_object).astype(np.int64)]

    def add(self, key, frame, step, index, hits):
        """Measure frame ``frame`` of the render ``key`` (hashable: file, scene and view
        layer), ``step`` frames after the one before it in its sequence, against the
        last frame added under ``key``, keep it, and return its Jump.

        index : (H, W) object index (0: no hit; ``object_index``).
        hits : (H, W, 3) world points.
        """
        last = self.last.pop(key, None)
        self.last[key] = (frame, index, hits)
        while len(self.last) > MAX_RENDERS:  # the render added longest ago goes
            self.worst.pop(next(iter(self.last)), None)
            del self.last[next(iter(self.last))]
        follows = last is not None and last[0] + step == frame and last[1].shape == index.shape
        if not follows:
            self.worst[key] = (None, None)
            return Jump(None, None, None)
        px = jump_px(last[1], last[2], index, hits)
        worst = self.worst.get(key, (None, None))
        if px is not None and (worst[0] is None or px > worst[0]):
            worst = self.worst[key] = (px, frame)
        return Jump(px, *worst)
