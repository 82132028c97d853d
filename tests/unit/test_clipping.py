"""Far clipping (``clip_end``) of the renderer's rays: camera i's own far plane in its
preserved region, as Cycles clips a pinhole camera (at depth ``clip_end`` along the view
axis), and a blend of the planes, continuous in the membership, in transitions."""

import numpy as np

from fixtures.rigs import camera
from multiscale_camera.core.sampling import (
    clip_far,
    far_planes,
    reach_to_far_planes,
    segments_from_points,
)

C1 = camera("C1", (0, -16, 8), (0, 0, 0), clip_start=4.0, clip_end=30.0)
C2 = camera("C2", (0.5, -4, 2), (0.2, 0, 0), clip_start=1.5, clip_end=6.0)


def pinhole_segments(cam, px, py, membership, bend=False):
    """Camera ``cam``'s pinhole rays through pixels (px, py) as Segments: from its near
    plane, one short segment (or, with ``bend``, two: the first one turned a little),
    then run on by the reach."""
    d = cam.directions(px, py)
    cos = d @ cam.forward
    start = cam.eye + d * (cam.clip_start / cos)[:, None]
    mid = start + d * 0.5
    if bend:
        mid = start + (d + np.array([0.01, 0.0, 0.0])) * 0.5
    end = mid + d * 0.5
    n = len(d)
    points = np.stack([start, mid, end], axis=1).reshape(-1, 3)
    ray = np.repeat(np.arange(n), 3)
    reach = np.full(n, reach_to_far_planes((C1, C2)))
    return segments_from_points(points, ray, n, reach, np.zeros(n), membership)


def ray_ends(seg):
    """(R, 3): where each ray ends (the far end of its last segment of non-zero length)."""
    ends = seg.origin + seg.direction * seg.length[:, None]
    last = np.zeros(len(seg), dtype=np.int64)
    np.maximum.at(last, seg.ray, np.where(seg.length > 0, np.arange(len(seg.ray)), 0))
    return ends[last]


def test_a_preserved_ray_ends_on_its_cameras_far_plane_as_a_pinhole_camera_clips():
    """The reference: Cycles' perspective camera runs a ray from the eye for
    clip_end / cos(angle off axis), so it ends at depth clip_end along the axis."""
    px = np.array([0.5, 10.5, 32.0, 63.5])
    py = np.array([0.5, 40.5, 24.0, 47.5])
    for number, cam in enumerate((C1, C2), start=1):
        seg = clip_far(pinhole_segments(cam, px, py, np.full(4, float(number))), (C1, C2))
        d = cam.directions(px, py)
        expected = cam.eye + d * (cam.clip_end / (d @ cam.forward))[:, None]
        np.testing.assert_allclose(ray_ends(seg), expected, atol=1e-9)
        assert seg.clipped.all()
        total = np.bincount(seg.ray, weights=seg.length)
        np.testing.assert_allclose(
            total, (cam.clip_end - cam.clip_start) / (d @ cam.forward), rtol=1e-12
        )


def test_segments_past_the_far_plane_are_not_cast():
    """A far plane crossed on the first segment leaves the rest of the ray uncast."""
    near = camera("N", (0, -4, 0), (0, 0, 0), clip_start=1.0, clip_end=1.2)
    seg = pinhole_segments(near, np.array([32.0]), np.array([24.0]), np.array([1.0]))
    out = clip_far(seg, (near,))
    np.testing.assert_allclose(out.length, [0.2, 0.0])
    assert out.castable.tolist() == [True, False]
    assert out.clipped.tolist() == [True]


def test_a_ray_that_ends_before_its_far_plane_is_not_clipped():
    far = camera("F", (0, -4, 0), (0, 0, 0), clip_start=1.0, clip_end=1e6)
    seg = pinhole_segments(far, np.array([32.0]), np.array([24.0]), np.array([1.0]))
    out = clip_far(seg, (far,))
    np.testing.assert_array_equal(out.length, seg.length)
    assert out.clipped.tolist() == [False]


def test_membership_between_two_cameras_blends_their_far_planes_with_the_rays_weights():
    """At membership 1 + t the ray ends where (1 - t) g1 + t g2 = 0, g_i being the
    depth along camera i's axis beyond its clip_end."""
    px, py = np.full(5, 30.0), np.full(5, 20.0)
    t = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    seg = clip_far(pinhole_segments(C2, px, py, 1.0 + t), (C1, C2))
    p = ray_ends(seg)
    g1 = (p - C1.eye) @ C1.forward - C1.clip_end
    g2 = (p - C2.eye) @ C2.forward - C2.clip_end
    np.testing.assert_allclose((1 - t) * g1 + t * g2, 0.0, atol=1e-9)
    normal, offset = far_planes((C1, C2), 1.0 + t)
    np.testing.assert_allclose(np.einsum("ij,ij->i", normal, p) - offset, 0.0, atol=1e-9)


def test_a_transition_has_no_hard_cut_at_a_masks_edge():
    """Across a transition (membership from 1 to 2 over 200 neighbouring rays) the rays'
    ends move by small steps; a hard cut (each ray clipped by its nearest camera's plane)
    moves them all at once by the planes' gap."""
    n = 200
    m = np.linspace(1.0, 2.0, n)
    px, py = np.full(n, 30.0), np.full(n, 20.0)
    seg = pinhole_segments(C2, px, py, m, bend=True)
    ends = ray_ends(clip_far(seg, (C1, C2)))
    steps = np.linalg.norm(np.diff(ends, axis=0), axis=1)
    hard = ray_ends(clip_far(pinhole_segments(C2, px, py, np.round(m), bend=True), (C1, C2)))
    gap = np.linalg.norm(hard[-1] - hard[0])
    assert gap > 5.0  # the two cameras' planes lie far apart along these rays
    assert np.linalg.norm(np.diff(hard, axis=0), axis=1).max() > 0.9 * gap
    assert steps.max() < 2.0 * gap / n
    # and the ends run monotonically from camera 1's plane to camera 2's
    depth = (ends - C2.eye) @ C2.forward
    assert np.all(np.diff(depth) <= 1e-9)


def test_reach_meets_every_cameras_far_plane_even_in_the_corners():
    """A corner ray from the eye has to run clip_end / cos(corner) to reach the plane."""
    reach = reach_to_far_planes((C1, C2))
    for cam in (C1, C2):
        d = cam.directions(np.array([0.0]), np.array([0.0]))[0]
        assert reach >= cam.clip_end / (d @ cam.forward) - 1e-9
