import numpy as np

from fixtures.rigs import camera, three_camera_rig, two_camera_rig
from multiscale_camera.core.geometry import (
    GUARD_FRACTION,
    bezier,
    blended_planes,
    build_guides,
    curved_rays,
)


def test_bezier_endpoints_and_tangents():
    q = [
        np.array([[0.0, 0, 0]]),
        np.array([[1.0, 0, 0]]),
        np.array([[2.0, 1, 0]]),
        np.array([[3.0, 1, 0]]),
    ]
    t = np.array([0.0, 1e-6, 1 - 1e-6, 1.0])
    b = bezier(*q, t)[0]
    np.testing.assert_allclose(b[0], q[0][0])
    np.testing.assert_allclose(b[-1], q[3][0])
    np.testing.assert_allclose((b[1] - b[0]) / 1e-6, 3 * (q[1][0] - q[0][0]), atol=1e-4)
    np.testing.assert_allclose((b[-1] - b[-2]) / 1e-6, 3 * (q[3][0] - q[2][0]), atol=1e-4)


def test_curved_rays_start_on_camera1_and_reach_each_camera():
    cams, _ = two_camera_rig()
    px = np.array([3.5, 30.5, 60.5])
    py = np.array([2.5, 20.5, 40.5])
    g = build_guides(cams, px, py)
    rays = curved_rays(g, segments=8)
    assert rays.shape == (2, 3, 1 + 8 + 1, 3)
    np.testing.assert_allclose(rays[:, :, 0], np.broadcast_to(g.points[0], (2, 3, 3)))
    # R_2 passes through p_2 and leaves along v_2: camera 2's own pinhole ray
    np.testing.assert_allclose(rays[1, :, 8], g.points[1], atol=1e-9)
    tail = rays[1, :, -1] - rays[1, :, -2]
    np.testing.assert_allclose(
        tail / np.linalg.norm(tail, axis=-1, keepdims=True), g.directions[1], atol=1e-9
    )
    # R_1 never bends: every vertex lies on camera 1's pinhole ray
    pix, _ = cams[0].project(rays[0])
    np.testing.assert_allclose(pix[..., 0], np.broadcast_to(px[:, None], pix.shape[:2]), atol=1e-6)
    np.testing.assert_allclose(pix[..., 1], np.broadcast_to(py[:, None], pix.shape[:2]), atol=1e-6)


def test_guard_shortens_handles_that_reach_behind_the_next_eye():
    c1 = camera("C1", (0, -20, 0), (0, 0, 0), clip_start=1.0)
    close = camera("C2", (0, -2, 0), (0, 0, 0), clip_start=0.1)
    far = camera("C3", (0, -2, 0), (0, 0, 0), clip_start=1.5)
    px, py = np.array([32.0]), np.array([24.0])
    g = build_guides((c1, close), px, py, beta=0.2)
    assert g.shortened.tolist() == [1]
    np.testing.assert_allclose(g.handles_in, GUARD_FRACTION * 0.1)
    near_c1 = camera("C1", (0, -20, 0), (0, 0, 0), clip_start=17.0)
    g = build_guides((near_c1, far), px, py, beta=0.2)
    assert g.shortened.tolist() == [0]
    np.testing.assert_allclose(g.handles_in, g.handles_out)
    # between GUARD_FRACTION * d and d the handle is clamped (continuously), not reported
    mid_c1 = camera("C1", (0, -20, 0), (0, 0, 0), clip_start=13.5)
    g = build_guides((mid_c1, far), px, py, beta=0.2)
    assert g.shortened.tolist() == [0]
    np.testing.assert_allclose(g.handles_in, GUARD_FRACTION * 1.5)


def test_blended_planes_are_einsums_blend_of_the_curves_bit_for_bit():
    """IMAGE_BLEND's rays: the blend made on planes against the plain weighted sum of
    every pixel's curves (einsum's accumulation from +0.0 in camera order), one-hot,
    zero and negative-zero-making weights included."""
    cams, _ = three_camera_rig(48, 27)
    rng = np.random.default_rng(3)
    px, py = rng.uniform(0, 48, 400), rng.uniform(0, 27, 400)
    g = build_guides(cams, px, py)
    w = rng.dirichlet(np.ones(3), size=400).T
    w[:, :50] = np.eye(3)[:, rng.integers(0, 3, 50)]  # kept pixels: one-hot
    w[2, 50:100] = 0.0  # pixels out of camera 3's reach
    want = np.einsum("np,npkc->pkc", w, curved_rays(g, 8))
    got = blended_planes(g, w, 8).transpose(2, 1, 0)
    assert got.shape == want.shape
    np.testing.assert_array_equal(got.view(np.uint64), want.view(np.uint64))
