"""The occupancy grid the renderer culls segments with: never culls a segment that meets
a triangle, and does cull segments through empty space."""

import numpy as np
import pytest

from multiscale_camera.core.sampling import Occupancy


def segment_hits_triangle(p0, p1, a, b, c):
    """Exact segment-triangle test (Moller-Trumbore on the segment p0 -> p1)."""
    d = p1 - p0
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = e1 @ h
    if abs(det) < 1e-15:
        return False
    f = 1.0 / det
    s = p0 - a
    u = f * (s @ h)
    q = np.cross(s, e1)
    v = f * (d @ q)
    t = f * (e2 @ q)
    return u >= 0 and v >= 0 and u + v <= 1 and 0 <= t <= 1


@pytest.mark.slow
def test_segments_that_meet_a_triangle_are_never_culled():
    rng = np.random.default_rng(3)
    centres = rng.uniform(-4, 4, (80, 3))
    tris = centres[:, None, :] + rng.normal(scale=0.8, size=(80, 3, 3))
    vertices = tris.reshape(-1, 3)
    triangles = np.arange(len(vertices)).reshape(-1, 3)
    lo, hi = vertices.min(0), vertices.max(0)
    occ = Occupancy(vertices, triangles, lo, hi, cells=32, pad=1e-9)
    p0 = rng.uniform(lo, hi, (3000, 3))
    p1 = p0 + rng.normal(scale=0.8, size=(3000, 3))
    kept = occ.any_between(p0, p1)
    meets = np.array(
        [any(segment_hits_triangle(a, b, *t) for t in tris) for a, b in zip(p0, p1, strict=True)]
    )
    assert meets.sum() > 50
    assert kept[meets].all()
    assert (~kept).sum() > 300  # and empty space is culled


def test_ground_plane_grid_culls_above_the_ground_only():
    # a flat ground 20 x 20 at z = 0 and a box 3 high above it
    vertices = np.array([(-10, -10, 0), (10, -10, 0), (10, 10, 0), (-10, 10, 0)], float)
    triangles = np.array([(0, 1, 2), (0, 2, 3)])
    occ = Occupancy(vertices, triangles, (-10, -10, -0.01), (10, 10, 3.0), pad=1e-6)
    above = occ.any_between(np.array([[0.0, 0.0, 2.0]]), np.array([[1.0, 1.0, 1.0]]))
    down = occ.any_between(np.array([[0.0, 0.0, 2.0]]), np.array([[1.0, 1.0, -0.005]]))
    assert not above[0] and down[0]
    assert occ.occupied.shape[2] >= 2


def test_empty_geometry_culls_everything():
    occ = Occupancy(np.zeros((0, 3)), np.zeros((0, 3), int), (0, 0, 0), (1, 1, 1))
    assert not occ.any_between(np.zeros((2, 3)), np.ones((2, 3))).any()


def test_clearance_is_a_lower_bound_of_the_distance_to_geometry():
    rng = np.random.default_rng(5)
    # point-like triangles: the distance to each is exact
    points = rng.uniform(-3, 3, (25, 3))
    vertices = np.repeat(points, 3, axis=0)
    triangles = np.arange(len(vertices)).reshape(-1, 3)
    occ = Occupancy(vertices, triangles, (-3, -3, -3), (3, 3, 3), cells=24)
    query = rng.uniform(-6, 6, (4000, 3))
    true = np.linalg.norm(query[:, None] - points[None], axis=-1).min(1)
    bound = occ.clearance(query)
    assert (bound <= true + 1e-12).all()
    assert (bound > 0.5 * true).mean() > 0.3  # and a useful bound, not zero everywhere
