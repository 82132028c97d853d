"""First-hit segment tables from hand-made polylines on a hand-made BVH."""

import numpy as np
from mathutils.bvhtree import BVHTree

from fixtures.rigs import camera
from multiscale_camera.core.geometry import RayBundle
from multiscale_camera.core.sampling import clip_far, segments_from_points
from multiscale_camera.render.raycast import march
from multiscale_camera.render.tables import clipped_misses, first_hit_segments, past_box

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


def test_a_clipped_miss_is_handed_on_from_its_own_end_not_another_rays():
    """Ray 0 is cut at its far plane mid-way; ray 1 starts beyond its far plane (every
    segment empty). Both miss, both are marked, and each is handed on from where it
    itself ends (ray 1: its own start, not ray 0's segment), along its own direction
    there, run on past the box."""
    near = camera("N", (0, -4, 0), (0, 0, 0), clip_start=1.0, clip_end=1.2)
    d = near.directions(np.array([32.0, 10.0]), np.array([24.0, 5.0]))
    s0 = near.eye + d[0] * (1.0 / (d[0] @ near.forward))
    s1 = near.eye + d[1] * (1.7 / (d[1] @ near.forward))
    turned = d[0] + np.array([0.3, 0.0, 0.0])
    turned /= np.linalg.norm(turned)
    # ray 0: a short straight stretch, then turned; cut on the turned segment
    points = np.array(
        [s0, s0 + d[0] * 0.05, s0 + d[0] * 0.05 + turned, s1, s1 + d[1], s1 + 2 * d[1]]
    )
    seg = clip_far(
        segments_from_points(
            points, np.repeat(np.arange(2), 3), 2, np.full(2, 10.0), np.zeros(2), np.ones(2)
        ),
        (near,),
    )
    hits = march(PLANE, seg)
    assert not hits.hit.any()
    # a box both lines run into past their ends, and one neither meets
    lo, hi = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 5.0, 1.0])
    miss, cut, start, end, direction = clipped_misses(seg, hits, (lo, hi))
    assert miss.tolist() == [True, True] and cut.tolist() == [True, True]
    # written out: ray 0 ends where its turned segment crosses depth 1.2 along the axis
    a = s0 + d[0] * 0.05
    t = (1.2 - (a - near.eye) @ near.forward) / (turned @ near.forward)
    assert 0 < t < 1
    np.testing.assert_allclose(start[0], a, atol=1e-9)
    np.testing.assert_allclose(end[0], a + turned * t, atol=1e-9)
    np.testing.assert_allclose(direction[0], turned, atol=1e-9)
    np.testing.assert_allclose(start[1], s1, atol=1e-9)
    np.testing.assert_allclose(end[1], s1, atol=1e-9)
    np.testing.assert_allclose(direction[1], d[1], atol=1e-9)
    # past the box: nothing of the box lies ahead of the handed-on origin
    origin = past_box(end, direction, lo, hi, 0.5)
    for o, e, u in zip(origin, end, direction):
        ahead = o + u * np.linspace(0.0, 100.0, 10001)[:, None]
        assert not np.all((ahead >= lo) & (ahead <= hi), axis=1).any()
        # and the origin lies on the ray's own line, ahead of where it ends
        assert np.linalg.norm(np.cross(o - e, u)) < 1e-9 and (o - e) @ u > 0
    far = (np.array([50.0, 50.0, 50.0]), np.array([51.0, 51.0, 51.0]))
    miss, cut, *_ = clipped_misses(seg, hits, far)
    assert miss.tolist() == [True, True] and cut.tolist() == [False, False]
