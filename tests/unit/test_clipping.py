"""Far clipping (``clip_end``) of the renderer's rays: camera i's own far plane in its
preserved region, as Cycles clips a pinhole camera (at depth ``clip_end`` along the view
axis), and a blend of the planes, continuous in the membership, in transitions."""

import warnings

import numpy as np
import pytest

from fixtures.rigs import camera
from multiscale_camera.core.sampling import (
    clip_far,
    far_planes,
    last_segments,
    reach_to_far_planes,
    segments_from_points,
)
from multiscale_camera.core.sampling import (
    ray_ends as core_ray_ends,
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
    """(R, 3): where each ray ends, ray by ray: the far end of its own last segment of
    non-zero length, or its start when every one of its segments is empty."""
    ends = np.empty((len(seg), 3))
    for r in range(len(seg)):
        own = range(seg.offsets[r], seg.offsets[r + 1])
        kept = [s for s in own if seg.length[s] > 0]
        s = kept[-1] if kept else own[0]
        ends[r] = seg.origin[s] + seg.direction[s] * seg.length[s]
    return ends


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


def test_reach_meets_the_far_plane_in_every_corner_of_a_shifted_camera():
    """A shifted camera's widest corner is off the middle: every one of its four corners
    (and its pixel centres at the edges) needs clip_end / cos(angle off axis)."""
    for shift in ((0.3, 0.0), (0.0, -0.4), (-0.5, 0.25)):
        cam = camera("S", (0, -16, 8), (0, 0, 0), clip_end=30.0, shift_x=shift[0], shift_y=shift[1])
        plain = camera("P", (0, -16, 8), (0, 0, 0), clip_end=30.0)
        reach = reach_to_far_planes((cam,))
        px = np.array([0.0, 64.0, 0.0, 64.0, 0.5, 63.5, 32.0, 32.0])
        py = np.array([0.0, 0.0, 48.0, 48.0, 24.0, 24.0, 0.5, 47.5])
        d = cam.directions(px, py)
        need = cam.clip_end / (d @ cam.forward)
        assert reach >= need.max() - 1e-9
        assert reach <= need.max() + 1e-9  # the widest corner sets it, no more
        # the shift matters: the unshifted camera's reach is too short for this one
        assert reach_to_far_planes((plain,)) < need.max() - 1e-3


def two_rays(first_start, second_start, d0, d1, reach=10.0):
    """Two straight rays of two unit segments each, from the given starts."""
    starts = (first_start, second_start)
    points = np.array([[s + d * k for k in range(3)] for s, d in zip(starts, (d0, d1))])
    ray = np.repeat(np.arange(2), 3)
    return segments_from_points(
        points.reshape(-1, 3), ray, 2, np.full(2, reach), np.zeros(2), np.ones(2)
    )


def test_a_ray_that_starts_beyond_its_far_plane_ends_at_its_own_start():
    """Ray 1 starts 0.5 past camera N's far plane: all its segments are empty, and it
    ends where it starts (not on ray 0's segment)."""
    near = camera("N", (0, -4, 0), (0, 0, 0), clip_start=1.0, clip_end=1.2)
    d = near.directions(np.array([32.0, 10.0]), np.array([24.0, 5.0]))
    s0 = near.eye + d[0] * (1.0 / (d[0] @ near.forward))
    s1 = near.eye + d[1] * (1.7 / (d[1] @ near.forward))
    out = clip_far(two_rays(s0, s1, d[0], d[1]), (near,))
    assert out.clipped.tolist() == [True, True]
    assert np.all(out.length[3:] == 0.0)
    end0 = near.eye + d[0] * (1.2 / (d[0] @ near.forward))
    expected = np.array([end0, s1])
    np.testing.assert_allclose(ray_ends(out), expected, atol=1e-12)
    end, direction = core_ray_ends(out)
    np.testing.assert_allclose(end, expected, atol=1e-12)
    np.testing.assert_allclose(direction, d, atol=1e-12)
    assert last_segments(out).tolist() == [0, out.offsets[1]]  # ray 1's own first segment


def test_a_ray_cut_mid_bend_ends_on_its_far_plane_along_its_bent_direction():
    """A ray whose first (turned) segment crosses the far plane ends there, heading the
    turned way; its later segments are empty."""
    cam = camera("B", (0, -4, 0), (0, 0, 0), clip_start=1.0, clip_end=1.2)
    px, py = np.array([20.0, 40.0]), np.array([30.0, 10.0])
    seg = pinhole_segments(cam, px, py, np.ones(2), bend=True)
    out = clip_far(seg, (cam,))
    d = cam.directions(px, py)
    start = cam.eye + d * (cam.clip_start / (d @ cam.forward))[:, None]
    turned = d + np.array([0.01, 0.0, 0.0])
    turned /= np.linalg.norm(turned, axis=1, keepdims=True)
    # forward . (start + s turned - eye) = clip_end
    s = (cam.clip_end - (start - cam.eye) @ cam.forward) / (turned @ cam.forward)
    assert np.all((s > 0) & (s < 0.5))  # the cut falls within the turned segment
    expected = start + turned * s[:, None]
    np.testing.assert_allclose(ray_ends(out), expected, atol=1e-9)
    end, direction = core_ray_ends(out)
    np.testing.assert_allclose(end, expected, atol=1e-9)
    np.testing.assert_allclose(direction, turned, atol=1e-9)
    assert out.clipped.all()
    np.testing.assert_array_equal(out.length.reshape(2, 2)[:, 1], 0.0)


@pytest.mark.parametrize("tilt", [1e-15, -1e-15, 0.0, 1e-9, -1e-9])
def test_a_ray_nearly_parallel_to_its_far_plane_is_cut_only_if_it_starts_beyond(tilt):
    """Rays running along the far plane (forward . direction = tilt ~ 0, either sign):
    the one a unit before the plane keeps its whole length (it would cross the plane only
    ~1/tilt away, past its reach); the one a unit beyond is empty from its start. No
    NaN, no warning."""
    cam = camera("P", (0, -16, 8), (0, 0, 0), clip_end=30.0)
    across = np.cross(cam.forward, (0.0, 0.0, 1.0))
    across /= np.linalg.norm(across)
    u = across + tilt * cam.forward
    u /= np.linalg.norm(u)
    before = cam.eye + cam.forward * (cam.clip_end - 1.0)
    beyond = cam.eye + cam.forward * (cam.clip_end + 1.0)
    seg = two_rays(before, beyond, u, u)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = clip_far(seg, (cam,))
        end, direction = core_ray_ends(out)
    assert out.clipped.tolist() == [False, True]
    np.testing.assert_array_equal(out.length[:2], seg.length[:2])
    np.testing.assert_array_equal(out.length[2:], 0.0)
    assert np.isfinite(out.length).all() and np.isfinite(end).all()
    np.testing.assert_allclose(end[1], beyond, atol=1e-12)
    np.testing.assert_allclose(direction, [u, u], atol=1e-12)
