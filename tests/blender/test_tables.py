"""First-hit segment tables from hand-made polylines on a hand-made BVH."""

import numpy as np
from mathutils.bvhtree import BVHTree

from multiscale_camera.core.geometry import RayBundle
from multiscale_camera.render.raycast import march
from multiscale_camera.render.tables import first_hit_segments

# the plane z = 0, |x|, |y| < 10
PLANE = BVHTree.FromPolygons(
    [(-10, -10, 0), (10, -10, 0), (10, 10, 0), (-10, 10, 0)], [(0, 1, 2), (0, 2, 3)]
)


def bundle(*polylines, reach=50.0):
    v = np.array(polylines, dtype=np.float32)
    r, k = v.shape[:2]
    return RayBundle(
        vertices=v,
        membership=np.ones((r, k), np.float32),
        pixels=np.zeros((r, 2), np.int32),
        start_depth=np.ones(r, np.float32),
        reach=np.full(r, reach, np.float32),
    )


def test_hit_in_a_later_segment():
    """Down-right, then straight down onto the plane: the second segment holds the hit."""
    b = bundle([(0, 0, 4), (1, 0, 3), (1, 0, 2), (1, 0, 1)])
    hits = march(PLANE, b)
    origin, direction, distance = first_hit_segments(b, hits)
    np.testing.assert_allclose(origin[0], (1, 0, 3), atol=1e-6)
    np.testing.assert_allclose(direction[0], (0, 0, -1), atol=1e-6)
    assert distance[0] == np.float64(3.0)
    np.testing.assert_allclose(origin[0] + distance[0] * direction[0], hits.location[0])


def test_hit_at_a_vertex_starts_before_the_surface():
    """A polyline that bends exactly on the surface: the segment ending there holds the
    hit (the next one would start on the surface, and a renderer would skip it)."""
    b = bundle([(0, 0, 2), (0, 0, 0), (1, 0, -1)])
    hits = march(PLANE, b)
    assert hits.hit[0]
    origin, direction, distance = first_hit_segments(b, hits)
    np.testing.assert_allclose(origin[0], (0, 0, 2), atol=1e-6)
    np.testing.assert_allclose(direction[0], (0, 0, -1), atol=1e-6)
    assert abs(distance[0] - 2.0) < 1e-6


def test_origin_on_the_surface_is_moved_back():
    """A polyline that starts on the surface (BVHTree reports the hit at distance 0):
    the origin moves back by the margin."""
    b = bundle([(0, 0, 0), (0, 0, -1), (0, 0, -2)])
    hits = march(PLANE, b)
    assert hits.hit[0] and hits.distance[0] == 0.0
    origin, direction, distance = first_hit_segments(b, hits, margin=0.01)
    np.testing.assert_allclose(origin[0], (0, 0, 0.01), atol=1e-6)
    assert distance[0] == 0.01


def test_miss_gives_the_last_tangent():
    b = bundle([(0, 0, 1), (1, 0, 2), (2, 0, 4)], reach=5.0)
    hits = march(PLANE, b)
    origin, direction, distance = first_hit_segments(b, hits)
    assert not hits.hit[0] and np.isinf(distance[0])
    np.testing.assert_allclose(origin[0], (1, 0, 2), atol=1e-6)
    np.testing.assert_allclose(direction[0], np.array([1, 0, 2]) / np.sqrt(5), atol=1e-6)
