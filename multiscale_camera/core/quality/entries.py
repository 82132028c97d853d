"""Kept views that must cross: where a camera's kept rays begin, as an earlier camera
sees that place.

Camera i keeps its pinhole rays from its near plane on; an earlier camera j keeps its own
from its near plane on, and folds are counted along every ray until it enters the last
camera's view. Seen from camera j, camera i's kept pixels lie in a region of camera j's
image that camera j does not keep: a hole in camera j's kept pixels, or open to the
frame's edge. Take a plane across camera j's view behind camera i's near plane: camera
j's kept rays cross it where their pixels say (a pinhole image of camera j's kept
pixels), and a field whose rays cross it once, forward, and whose neighbouring rays
never cross maps the image onto the plane one to one, so the rays of the hole's pixels
cross it inside the image of the hole.
Camera i's kept rays therefore stay, seen from camera j, within the hole until they
enter camera i's view, and there they begin on camera i's near plane at their entries
``E_i + d_i v / (v . V_i)``. Where camera j sees an entry on its own kept pixels or
beyond them (in another region), the kept rays of i and j must pass through one
another on the way, and every field that keeps both exact folds between them, whatever
its method. docs/architecture.md, "Kept views that must cross", gives the argument and
the bench rig it explains.
"""

from dataclasses import dataclass

import numpy as np

from .samples import MAX_CHECK_RAYS, MIN_SHARE, sample_pixels

# The least Clip Start that clears a crossing is searched in steps of this factor, up
# to MAX_CLIP_FACTOR times the camera's own (or its Clip End).
CLIP_STEP = 1.05
MAX_CLIP_FACTOR = 20.0


@dataclass(frozen=True)
class Regions:
    """The 4-connected regions of an image's free pixels, the outside of the frame one
    region with those that touch its edge.

    runs : (R, 3) int64, each run of free pixels in a row: row, first column, end column.
    labels : (R + 1,) int64, each run's region (the last entry: the outside's).
    width, height : int, the image's size in pixels.
    """

    runs: np.ndarray
    labels: np.ndarray
    width: int
    height: int

    def label(self, x, y):
        """(P,) int64: the region of pixels (``x``, ``y``: (P,) int arrays, any value):
        -1 on a pixel that is not free, the outside's region off the frame."""
        x, y = np.asarray(x, dtype=np.int64), np.asarray(y, dtype=np.int64)
        out = np.full(x.shape, self.labels[-1], dtype=np.int64)
        inside = (x >= 0) & (x < self.width) & (y >= 0) & (y < self.height)
        if not len(self.runs):
            out[inside] = -1
            return out
        key = self.runs[:, 0] * (self.width + 1) + self.runs[:, 1]
        at = y[inside] * (self.width + 1) + x[inside]
        run = np.searchsorted(key, at, side="right") - 1
        ok = run >= 0
        ok[ok] = (self.runs[run[ok], 0] == y[inside][ok]) & (self.runs[run[ok], 2] > x[inside][ok])
        out[inside] = np.where(ok, self.labels[np.maximum(run, 0)], -1)
        return out


def free_regions(kept):
    """The regions of the pixels ``kept`` ((H, W) bool) leaves free (``Regions``).

    Runs of free pixels in consecutive rows that share a column are joined, and runs on
    the frame's edge join the outside; regions are found by min-label propagation over
    those joins with pointer jumping, a few numpy passes for a mask's few runs a row."""
    kept = np.asarray(kept, dtype=bool)
    h, w = kept.shape
    edge = np.zeros((h, w + 2), dtype=np.int8)
    edge[:, 1:-1] = ~kept
    step = np.diff(edge, axis=1)
    rows, first = np.nonzero(step == 1)
    _rows, end = np.nonzero(step == -1)
    runs = np.stack([rows, first, end], axis=1).astype(np.int64)
    n = len(runs)
    outside = n
    # runs of row r + 1 that share a column with each run of row r: [lo, hi)
    key_first = rows * (w + 1) + first
    key_end = rows * (w + 1) + end
    below = (rows + 1) * (w + 1)
    lo = np.searchsorted(key_end, below + first, side="right")
    hi = np.searchsorted(key_first, below + end, side="left")
    count = np.maximum(hi - lo, 0)
    a = np.repeat(np.arange(n), count)
    b = np.repeat(lo - np.cumsum(count) + count, count) + np.arange(count.sum())
    border = np.flatnonzero((rows == 0) | (rows == h - 1) | (first == 0) | (end == w))
    a = np.concatenate([a, border])
    b = np.concatenate([b, np.full(len(border), outside)])
    labels = np.arange(n + 1)
    while True:
        low = np.minimum(labels[a], labels[b])
        new = labels.copy()
        np.minimum.at(new, a, low)
        np.minimum.at(new, b, low)
        np.minimum.at(new, labels, new)  # hook each run's root too
        while True:
            jump = new[new]
            if np.array_equal(jump, new):
                break
            new = jump
        if np.array_equal(new, labels):
            return Regions(runs, labels, w, h)
        labels = new


@dataclass(frozen=True)
class CrossingEntry:
    """Camera ``inner``'s kept rays begin where camera ``outer`` (earlier in the list)
    sees them outside the region of its free pixels they lie in.

    inner, outer : int, 0-based camera indices. checked : int, sampled kept pixels of
    ``inner`` whose entry lies beyond ``outer``'s near plane. crossing : int, of them,
    those whose entry ``outer`` sees elsewhere; on_kept : int, of those, on ``outer``'s
    kept pixels. clip_start : float or None, the least Clip Start of ``inner`` (searched
    in steps of ``CLIP_STEP``) at which none crosses, None if none up to
    ``MAX_CLIP_FACTOR`` times its own does.
    """

    inner: int
    outer: int
    checked: int
    crossing: int
    on_kept: int
    clip_start: float | None


def _entries(cam, ix, iy, clip):
    """(P, 3) float64, world units: where the pinhole rays of pixels ``ix``, ``iy`` ((P,)
    int) of ``cam`` cross a near plane at distance ``clip`` (float); (C, P, 3) for
    ``clip`` a (C,) array of distances."""
    near = cam.near_points(cam.directions(ix + 0.5, iy + 0.5))  # at its own clip start
    ratio = np.asarray(clip, dtype=np.float64)[..., None, None] / cam.clip_start
    return cam.eye + (near - cam.eye) * ratio


def _crossing(outer, regions, own, points):
    """(crossing, on_kept, checked) bool arrays (..., P) for entry ``points`` (..., P, 3)
    of pixels whose region of ``outer``'s free pixels is ``own`` ((P,) int64)."""
    pix, depth = outer.project(points)
    with np.errstate(invalid="ignore"):
        x = np.floor(np.nan_to_num(pix[..., 0], nan=-1.0, posinf=-1.0, neginf=-1.0))
        y = np.floor(np.nan_to_num(pix[..., 1], nan=-1.0, posinf=-1.0, neginf=-1.0))
    x = np.clip(x, -1, regions.width).astype(np.int64)
    y = np.clip(y, -1, regions.height).astype(np.int64)
    where = regions.label(x.ravel(), y.ravel()).reshape(x.shape)
    checked = (depth > outer.clip_start) & (own >= 0)
    crossing = checked & (where != own)
    return crossing, crossing & (where < 0), checked


def crossing_entries(rig, limit=MAX_CHECK_RAYS):
    """Every pair of cameras whose kept views must cross (``CrossingEntry``), in the
    order of the inner camera, then the outer.

    For each camera i after the first and each earlier camera j with kept pixels: up to
    ``limit`` of i's kept pixels, where their
    rays cross i's near plane, projected into camera j; an entry beyond j's near plane
    that lands on j's kept pixels, or in another region of its free pixels than the
    pixel's own, crosses. A pair is reported once more than ``MIN_SHARE`` of the checked
    pixels (and more than one) cross, as the other checks before a build do.

    Returns
    -------
    list of CrossingEntry.
    """
    cams, masks = rig.cameras, np.asarray(rig.masks)
    out = []
    regions_of = {}  # each camera's regions, found once for every later camera
    for i in range(1, len(cams)):
        ix, iy = sample_pixels(masks[i], limit)
        if not len(ix):
            continue
        inner = cams[i]
        for j in range(i):
            if not masks[j].any():
                continue
            if j not in regions_of:
                regions_of[j] = free_regions(masks[j])
            regions = regions_of[j]
            own = regions.label(ix, iy)
            found = _crossing(cams[j], regions, own, _entries(inner, ix, iy, inner.clip_start))
            crossing, on_kept, checked = (int(f.sum()) for f in found)
            if crossing <= max(1, MIN_SHARE * checked):
                continue
            out.append(
                CrossingEntry(
                    i,
                    j,
                    checked,
                    crossing,
                    on_kept,
                    _clear_clip(cams[j], regions, own, inner, ix, iy),
                )
            )
    return out


def _clear_clip(outer, regions, own, inner, ix, iy):
    """The least Clip Start of ``inner``, in steps of ``CLIP_STEP`` above its own, at
    which no more than ``MIN_SHARE`` of its pixels ``ix``, ``iy`` enter where ``outer``
    sees them cross (``crossing_entries``); None if none up to ``MAX_CLIP_FACTOR`` times
    its own, nor before its Clip End, does."""
    steps = int(np.log(MAX_CLIP_FACTOR) / np.log(CLIP_STEP))
    clips = inner.clip_start * CLIP_STEP ** np.arange(1, steps + 1)
    clips = clips[clips < inner.clip_end]
    if not len(clips):
        return None
    crossing, _on, checked = _crossing(outer, regions, own, _entries(inner, ix, iy, clips))
    clear = crossing.sum(axis=1) <= np.maximum(1, MIN_SHARE * checked.sum(axis=1))
    return float(clips[np.argmax(clear)]) if clear.any() else None


def crossing_message(entry, cameras):
    """The warning for a ``CrossingEntry``: what crosses and what to change first (the
    report's panel shows a warning's first four lines), then why."""
    inner, outer = cameras[entry.inner].name, cameras[entry.outer].name
    if entry.on_kept == entry.crossing:
        where = "all on its kept pixels"
    elif entry.on_kept:
        where = f"{100 * entry.on_kept / entry.crossing:.0f}% on its kept pixels, the rest beyond"
    else:
        where = "all beyond its kept pixels"
    if entry.clip_start is not None:
        fix = (
            f"raise the Clip Start of '{inner}' to {entry.clip_start:.3g} or more (now "
            f"{cameras[entry.inner].clip_start:.3g}), or turn '{inner}' less"
        )
    else:
        fix = f"turn '{inner}' less, or move it nearer the centre of what '{outer}' sees"
    return (
        f"Kept rays of '{inner}' and '{outer}' must cross: {fix}; every method folds "
        f"there until then. The kept rays of '{inner}' begin on its near plane where "
        f"'{outer}' sees them outside the opening of its mask ({entry.crossing} of "
        f"{entry.checked} checked, {where}; docs/failures.md)."
    )


def crossing_entry_messages(rig):
    """``crossing_message`` of every pair ``crossing_entries`` finds (list of str)."""
    return [crossing_message(e, rig.cameras) for e in crossing_entries(rig)]
