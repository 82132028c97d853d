"""A procedural anatomy-like volume (numpy only, so Blender, tests and benchmarks share it).

In a cube [-1, 1]^3: a body (an upright ellipsoid of soft tissue with a skin), an organ
inside it (a heart-like ellipsoid with a thick wall), and a branching vessel tree
inside the organ. Boundaries are smooth over about a voxel, so trilinear sampling
shows no stairs. Each material has its own value band, which the transfer functions
pick apart:

    air 0, tissue ~0.15, skin ~0.3, organ wall ~0.55, vessels ~0.9
"""

import numpy as np

AIR, TISSUE, SKIN, ORGAN, VESSEL = 0.0, 0.15, 0.3, 0.55, 0.9
BODY_RADII = (0.62, 0.42, 0.92)
SKIN_THICKNESS = 0.035
ORGAN_CENTRE = (0.1, -0.04, 0.18)
ORGAN_RADII = (0.3, 0.26, 0.34)
ORGAN_WALL = 0.08


def _smooth_inside(signed, width):
    """1 inside (signed < 0), 0 outside, a smoothstep over ``width`` across the boundary."""
    t = np.clip(0.5 - signed / width, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _ellipsoid_distance(x, y, z, centre, radii):
    """Approximate signed distance to an ellipsoid (exact on a sphere)."""
    q = [(c - o) / r for c, o, r in zip((x, y, z), centre, radii)]
    k = np.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2)
    return (k - 1.0) * min(radii)


def vessel_tree(depth=5, seed=7):
    """Branches of a vessel tree: list of (start (3,), end (3,), radius), in [-1, 1]^3.

    The trunk enters the organ from above; every branch forks in two, turning away
    from its parent and getting thinner and shorter (``phantom`` clips the tree to the
    organ)."""
    rng = np.random.default_rng(seed)
    centre = np.array(ORGAN_CENTRE)
    out = []
    todo = [(centre + (0.0, 0.0, 0.3), np.array([0.05, 0.0, -1.0]), 0.16, 0.032, 0)]
    while todo:
        start, direction, length, radius, level = todo.pop()
        direction = direction / np.linalg.norm(direction)
        end = start + direction * length
        out.append((start, end, radius))
        if level < depth:
            turn = rng.normal(size=3)
            turn -= turn.dot(direction) * direction
            turn /= np.linalg.norm(turn)
            for side in (-1, 1):
                child = direction + side * 1.1 * turn + rng.normal(scale=0.2, size=3)
                todo.append((end, child, length * 0.78, radius * 0.74, level + 1))
    return out


def phantom(n=128, dtype=np.float32):
    """(n, n, n) array indexed [x, y, z] over the cube [-1, 1]^3 (voxel centres), values
    in [0, 1] (see the module docstring)."""
    ax = (np.arange(n, dtype=np.float32) + 0.5) / n * 2 - 1
    x, y, z = ax[:, None, None], ax[None, :, None], ax[None, None, :]
    voxel = 2.0 / n
    edge = 1.5 * voxel
    body = _ellipsoid_distance(x, y, z, (0, 0, 0), BODY_RADII)
    inside_body = _smooth_inside(body, edge)
    inner = _smooth_inside(body + SKIN_THICKNESS, edge)
    # tissue with a gentle texture, so the inside is not a flat colour
    texture = 0.02 * np.sin(9 * x + 2) * np.sin(7 * y + 1) * np.sin(8 * z)
    values = (TISSUE + texture) * inner + SKIN * (inside_body - inner)
    organ = _ellipsoid_distance(x, y, z, ORGAN_CENTRE, ORGAN_RADII)
    wall = _smooth_inside(organ, edge) - _smooth_inside(organ + ORGAN_WALL, edge)
    cavity = _smooth_inside(organ + ORGAN_WALL, edge)
    values = values * (1 - wall - cavity) + ORGAN * wall + (TISSUE + 0.08) * cavity
    vessels = np.zeros((n, n, n), dtype=np.float32)
    for a, b, radius in vessel_tree():
        lo = np.floor((np.minimum(a, b) - radius - 2 * edge + 1) / voxel).astype(int)
        hi = np.ceil((np.maximum(a, b) + radius + 2 * edge + 1) / voxel).astype(int)
        lo, hi = np.clip(lo, 0, n), np.clip(hi, 0, n)
        if (hi <= lo).any():
            continue
        px = ax[lo[0] : hi[0], None, None]
        py = ax[None, lo[1] : hi[1], None]
        pz = ax[None, None, lo[2] : hi[2]]
        ab = b - a
        t = ((px - a[0]) * ab[0] + (py - a[1]) * ab[1] + (pz - a[2]) * ab[2]) / ab.dot(ab)
        t = np.clip(t, 0, 1)
        d = np.sqrt(
            (px - a[0] - t * ab[0]) ** 2
            + (py - a[1] - t * ab[1]) ** 2
            + (pz - a[2] - t * ab[2]) ** 2
        )
        part = _smooth_inside(d - radius, edge)
        box = vessels[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        np.maximum(box, part, out=box)
    vessels *= _smooth_inside(organ, edge)  # the tree stays inside the organ
    values = values * (1 - vessels) + VESSEL * vessels
    return np.clip(values, 0, 1).astype(dtype)


# --- the volume demo's rig (sample_blends/scenes.py and bench/volume.py share it) ---

BODY_CENTRE = (0.0, 0.0, 1.0)  # the phantom's cube [-1, 1]^3 moved up by this (metres)
_ORGAN = tuple(b + o for b, o in zip(BODY_CENTRE, ORGAN_CENTRE))
_VESSELS = (_ORGAN[0], _ORGAN[1], _ORGAN[2] + 0.06)
# name, target, distance, azimuth and elevation (degrees, azimuth 0 looks along +y),
# near plane distance: the body, the organ, the vessel tree; camera 3 looks nearly along
# camera 2's axis, so their preserved frusta stay apart.
DEMO_CAMERAS = (
    ("Cam1 Body", BODY_CENTRE, 4.6, 0.0, 10.0, 2.0),
    ("Cam2 Organ", _ORGAN, 1.7, 8.0, 12.0, 0.8),
    ("Cam3 Vessels", _VESSELS, 0.9, 9.0, 12.0, 0.4),
)
# Mask radii in pixels of a 640-pixel-wide image (scale with the width): camera 3 owns
# the disk, camera 2 the ring, camera 1 the outside; the gaps are the transitions.
DEMO_RADII = {"cam3": 56, "cam2_inner": 92, "cam2_outer": 122, "cam1": 152}
# Samples half a voxel apart: camera 3 magnifies a voxel to several pixels.
DEMO_STEP = 0.5
# Transfer functions over the values above: position, (r, g, b, opacity per voxel).
DEMO_TFS = {
    # the body: an opaque skin hides the inside
    "Body": [
        (0.0, (0.0, 0.0, 0.0, 0.0)),
        (0.1, (0.6, 0.4, 0.35, 0.0)),
        (0.2, (0.8, 0.55, 0.45, 0.02)),
        (0.3, (0.95, 0.72, 0.58, 0.35)),
        (0.42, (0.9, 0.5, 0.45, 0.05)),
        (0.55, (0.8, 0.2, 0.2, 0.3)),
        (1.0, (1.0, 0.9, 0.8, 0.8)),
    ],
    # the organ: skin and tissue clear, a translucent red wall, bright vessels
    "Organ": [
        (0.0, (0.0, 0.0, 0.0, 0.0)),
        (0.4, (0.8, 0.2, 0.2, 0.0)),
        (0.55, (0.85, 0.15, 0.15, 0.12)),
        (0.7, (0.9, 0.5, 0.2, 0.02)),
        (0.9, (1.0, 0.9, 0.5, 0.7)),
        (1.0, (1.0, 1.0, 0.8, 0.9)),
    ],
    # the vessels alone, the wall a faint veil
    "Vessels": [
        (0.0, (0.0, 0.0, 0.0, 0.0)),
        (0.5, (0.6, 0.2, 0.3, 0.0)),
        (0.55, (0.6, 0.25, 0.3, 0.006)),
        (0.62, (0.6, 0.25, 0.3, 0.0)),
        (0.75, (0.7, 0.1, 0.15, 0.0)),
        (0.9, (0.95, 0.2, 0.25, 0.9)),
        (1.0, (1.0, 0.6, 0.6, 1.0)),
    ],
}
