"""Checks of a rig that explain, before a build, what would go wrong and what to change,
and the warnings that say where a build put something else in place of the field
(claims two masks both make, Newton's failures, stalled and unfinished rays)."""

import numpy as np

from ..errors import RigError
from ..field import StopReason, choose_grid
from ..geometry import DEFAULT_SEGMENTS, build_guides, curved_rays
from .entries import crossing_entry_messages
from .samples import MAX_CHECK_RAYS, MIN_SHARE, sample_pixels

# Consecutive cameras may turn at most this much: beyond it the guides of neighbouring
# pixels cross (paper, section 6).
MAX_TURN_DEG = 90.0


def turn_deg(a, b):
    """Angle between two cameras' view axes, degrees."""
    return float(np.degrees(np.arccos(np.clip(a.forward @ b.forward, -1.0, 1.0))))


def check_rig(rig):
    """Raise ``RigError`` for a rig that cannot give coherent rays; return warnings.

    Checks: consecutive cameras turned more than 90 degrees apart; a camera's near plane
    behind the previous camera's eye (the order of scales reversed).

    Returns
    -------
    list of str, warnings that do not stop a build.
    """
    cams = rig.cameras
    warnings = []
    for a, b in zip(cams, cams[1:]):
        angle = turn_deg(a, b)
        if angle > MAX_TURN_DEG:
            raise RigError(
                f"Cameras '{a.name}' and '{b.name}' look {angle:.0f} degrees apart; consecutive "
                f"cameras must turn less than {MAX_TURN_DEG:.0f} degrees (add a camera between "
                "them to bend the rays in stages)"
            )
        depth = (b.eye + b.forward * b.clip_start - a.eye) @ a.forward
        if depth < a.clip_start:
            warnings.append(
                f"The near plane of '{b.name}' lies before the near plane of '{a.name}': the "
                "list should run from the largest scale to the smallest (move it down the list, "
                "or move the camera)"
            )
    return warnings


def conflict_messages(names, overlaps):
    """Warnings for voxels that preserved rays of two cameras both claim.

    Parameters
    ----------
    names : list of N str. overlaps : (N, N) int, voxels claimed by both i and j.
    """
    out = []
    n = len(names)
    for i in range(n):
        for j in range(i + 1, n):
            count = int(overlaps[i, j])
            if not count:
                continue
            if j == i + 1:
                out.append(
                    f"{count} voxels lie on preserved rays of both '{names[i]}' and '{names[j]}': "
                    "their masks contradict each other there and those voxels were left free "
                    "(widen the gap between the two masks, or move a near plane)"
                )
            else:
                out.append(
                    f"The preserved views of '{names[i]}' and '{names[j]}', which are not "
                    f"neighbours in the list, cross in {count} voxels: rays there cannot be "
                    "coherent (move one of the cameras, or shrink its mask)"
                )
    return out


# --- checks before a build (``preflight``) -----------------------------------------------

# Pixels per side of the lattice the guard check samples (cheap enough for a panel redraw).
GUARD_LATTICE = 9
# Points sampled along each straight preserved ray by the crossing check.
CROSSING_SAMPLES = 48


def guard_pairs(cameras, beta, size):
    """Indices j of consecutive pairs (j, j+1) whose guides the guard shortens: the
    paper's handle beta L reaches behind camera j+1's eye (beta L >= d_{j+1}).

    Parameters
    ----------
    cameras : sequence of PinholeCamera. beta : float. size : (width, height) pixels.

    Returns
    -------
    list of int.
    """
    if len(cameras) < 2:
        return []
    w, h = size
    cx, cy = np.meshgrid(
        np.linspace(0.5, w - 0.5, GUARD_LATTICE), np.linspace(0.5, h - 0.5, GUARD_LATTICE)
    )
    shortened = build_guides(cameras, cx.ravel(), cy.ravel(), beta).shortened
    return [j for j, count in enumerate(shortened) if count]


def guard_message(a, b):
    """The guard warning for cameras ``a`` -> ``b`` (PinholeCamera)."""
    return (
        f"Guides from '{a.name}' into '{b.name}' were shortened to keep them in front of "
        f"'{b.name}' (beta x distance between near planes exceeds its near distance "
        f"{b.clip_start:g}); move its near plane (Clip Start) farther from its eye"
    )


def guard_messages(rig):
    """Guard warnings of a rig (one per shortened pair)."""
    cams = rig.cameras
    return [guard_message(cams[j], cams[j + 1]) for j in guard_pairs(cams, rig.beta, rig.size)]


def empty_mask_messages(rig):
    """Notes for intermediate cameras with an empty mask: legitimate (they only bend
    rays), but worth a word in case the mask was forgotten."""
    out = []
    for i, cam in enumerate(rig.cameras[:-1]):
        if i > 0 and not rig.masks[i].any():
            out.append(
                f"The mask of '{cam.name}' is empty: it only bends rays and shows nowhere "
                "(paint it white where its view should be kept, if that was the intent)"
            )
    return out


def _bending_box(rig):
    """(lo, hi) world box of the bending stretch (the field grid's box)."""
    grid = choose_grid(rig, 2.0, 32**3).grid
    return grid.bounds


def crossing_messages(rig):
    """Warnings for cameras i and j >= i + 2 whose preserved views cross inside the
    bending stretch's box: a point on a straight preserved ray of camera j (beyond its
    near plane) that camera i also sees, beyond its own near plane, through a pixel of
    its mask. Rays there would have to follow both cameras at once.

    Returns
    -------
    list of str, one per crossing pair.
    """
    cams = rig.cameras
    n = len(cams)
    if n < 3:
        return []
    lo, hi = _bending_box(rig)
    w, h = rig.size
    out = []
    for j in range(2, n):
        ix, iy = sample_pixels(rig.masks[j])
        if len(ix) == 0:
            continue
        cam = cams[j]
        d = cam.directions(ix + 0.5, iy + 0.5)
        start = cam.near_points(d)
        # distance along each ray to where it leaves the box (slab method)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - start) / d
            t2 = (hi - start) / d
        t_exit = np.nanmin(np.where(np.isnan(np.maximum(t1, t2)), np.inf, np.maximum(t1, t2)), 1)
        t_exit = np.clip(t_exit, 0.0, cam.clip_end)
        s = np.linspace(0.0, 1.0, CROSSING_SAMPLES)
        pts = start[:, None] + d[:, None] * (t_exit[:, None, None] * s[None, :, None])
        inside = ((pts >= lo) & (pts <= hi)).all(-1)
        for i in range(j - 1):
            pix, depth = cams[i].project(pts.reshape(-1, 3))
            pix = pix.reshape(len(ix), CROSSING_SAMPLES, 2)
            depth = depth.reshape(len(ix), CROSSING_SAMPLES)
            px, py = np.floor(pix[..., 0]).astype(int), np.floor(pix[..., 1]).astype(int)
            seen = inside & (depth > cams[i].clip_start) & (px >= 0) & (px < w)
            seen &= (py >= 0) & (py < h)
            seen[seen] = rig.masks[i][py[seen], px[seen]]
            crossing = seen.any(axis=1)
            if crossing.sum() > max(1, MIN_SHARE * len(ix)):
                out.append(
                    f"The preserved views of '{cams[i].name}' and '{cam.name}', which are "
                    f"not neighbours in the list, cross ({100 * crossing.mean():.0f}% of the "
                    f"checked rays of '{cam.name}'): rays there cannot follow both (shrink the "
                    f"mask of '{cams[i].name}' away from where '{cam.name}' looks, or move "
                    "one of the cameras)"
                )
    return out


def bending_paths(rig, i, limit=MAX_CHECK_RAYS):
    """The preserved rays of camera i (0-based, i >= 1) through the bending stretch.

    Returns
    -------
    ix, iy : (P,) int, sampled pixels of camera i's mask.
    stages : list of i arrays (P, S + 1, 3) float64, world units: the rays R_i from
        camera j's near plane to camera j+1's, for j = 0 .. i-1 (S vertices a stage).
    """
    ix, iy = sample_pixels(rig.masks[i], limit)
    if len(ix) == 0:
        return ix, iy, []
    g = build_guides(rig.cameras, ix + 0.5, iy + 0.5, rig.beta)
    rays = curved_rays(g, DEFAULT_SEGMENTS)[i]
    s = DEFAULT_SEGMENTS
    return ix, iy, [rays[:, j * s : (j + 1) * s + 1] for j in range(i)]


def obstruction_messages(rig, cast):
    """Warnings for geometry that stands on preserved rays between consecutive near
    planes: it would hide the smaller camera's view in the multiscale image.

    Parameters
    ----------
    rig : Rig.
    cast : callable ``cast(vertices) -> (hit, names)``: for polylines ``vertices``
        (P, K, 3) float64, ``hit`` (P,) bool, whether a polyline meets geometry, and
        ``names`` a list of the names of the objects met.

    Returns
    -------
    list of str, at most one per camera: the first stage its rays are blocked in.
    """
    cams = rig.cameras
    out = []
    for i in range(1, len(cams)):
        ix, _iy, stages = bending_paths(rig, i)
        for j, verts in enumerate(stages):
            hit, names = cast(verts)
            if hit.sum() > max(0, MIN_SHARE * len(ix)):
                what = ", ".join(f"'{n}'" for n in sorted(set(names))[:3]) or "Geometry"
                out.append(
                    f"{what} stands between the near planes of '{cams[j].name}' and "
                    f"'{cams[j + 1].name}' on {100 * hit.mean():.0f}% of the preserved rays "
                    f"of '{cams[i].name}': it hides what '{cams[i].name}' sees there (lower "
                    f"the Clip Start of '{cams[j + 1].name}' so its near plane lies before "
                    "the object, or move the camera or the object)"
                )
                break
    return out


def preflight(rig):
    """The checks that need no scene geometry, for ``multiscale.validate`` and before a
    build: raises ``RigError`` (turns over 90 degrees); returns warnings (order of
    scales, guard, empty masks, crossing frusta, kept views that must cross), each
    naming the camera and the fix."""
    return (
        check_rig(rig)
        + guard_messages(rig)
        + empty_mask_messages(rig)
        + crossing_messages(rig)
        + crossing_entry_messages(rig)
    )


def _pixel_span(x, y):
    """'pixels x a-b, y c-d' of pixel coordinates ((n,) arrays, camera 1's pixels)."""
    x, y = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    return f"pixels x {x.min()}-{x.max()}, y {y.min()}-{y.max()}"


def substitution_messages(rig, traced, index, lost):
    """Warnings for what the trace put in place of the field, saying where.

    Parameters
    ----------
    rig : Rig. traced : field.Traced, every traced ray. index : (H, W) int32, the
    traced ray of each pixel or -1. lost : list of (camera index, (n, 2) float32
    camera-1 pixels) for every tangent evaluation where Newton's inversion of a ray
    family failed (``FieldTracer.lost``).

    Returns
    -------
    list of str: per camera whose family Newton lost points of, and for stalled and
    unfinished rays, how many and the pixels they cover.
    """
    out = []
    names = [c.name for c in rig.cameras]
    for i in sorted({cam for cam, _at in lost}):
        at = np.concatenate([a for cam, a in lost if cam == i])
        rays = np.unique(at[np.isfinite(at).all(axis=1)], axis=0)
        where = f" ({_pixel_span(rays[:, 0], rays[:, 1])})" if len(rays) else ""
        out.append(
            f"Newton's inversion of camera '{names[i]}''s curved rays failed at {len(at)} "
            f"points of {len(rays)} traced rays{where}: there the field took camera "
            f"'{names[0]}''s direction instead of '{names[i]}''s, so rays there may bend wrongly"
        )
    py, px = np.nonzero(index >= 0)
    rows = index[py, px]
    for reason, text in (
        (StopReason.STALLED, "stalled (the blended field vanished) before leaving the grid"),
        (StopReason.REACHED_LIMIT, "reached the step limit inside the grid and ran straight on"),
    ):
        hit = traced.reason[rows] == reason
        if hit.any():
            out.append(
                f"{int(hit.sum())} traced rays {text} ({_pixel_span(px[hit] + 0.5, py[hit] + 0.5)})"
            )
    return out
