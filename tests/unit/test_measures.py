"""The report's measures against references written here: the preserved error along
the whole ray against an independent pinhole projection, and the fold counter against
a brute-force count of the same sections."""

import numpy as np
import pytest

from fixtures.rigs import camera, look_at, turned_rig, zoom1000_rig, zoom_rig
from multiscale_camera.core.geometry import Rig
from multiscale_camera.core.methods import prepare_image_blend, prepare_linear
from multiscale_camera.core.quality import (
    along_ray,
    along_ray_on_planes,
    bending_active,
    fold_map,
    quad_folds,
)

W, H, LENS = 64, 48, 50.0
EYE, TARGET = np.array([0.3, -6.0, 2.0]), np.array([0.0, 0.0, 0.5])


def _frame():
    """Camera axes of a camera at EYE looking at TARGET, from look_at's definition:
    right, up and forward (the camera looks down its local -Z)."""
    m = look_at(EYE, TARGET)
    return m[:3, 0], m[:3, 1], -m[:3, 2]


def pinhole_pixels(points):
    """Continuous pixel coordinates of world points: x = W/2 + (x_cam / depth) * lens /
    36 mm * W, y = H/2 - (y_cam / depth) * lens / 36 mm * W (36 mm sensor fitted to the
    width, top-left origin)."""
    r, u, f = _frame()
    rel = np.asarray(points, dtype=np.float64) - EYE
    depth = rel @ f
    k = LENS / 36.0 * W
    return np.stack([W / 2 + (rel @ r) / depth * k, H / 2 - (rel @ u) / depth * k], -1)


def pinhole_direction(x, y):
    """Unit direction of the pinhole ray through continuous pixel (x, y)."""
    r, u, f = _frame()
    k = LENS / 36.0 * W
    d = f + r * (x - W / 2) / k - u * (y - H / 2) / k
    return d / np.linalg.norm(d)


def dense_worst(polyline, x, y, near, far, samples=4001):
    """Worst pixel distance and angle over ``samples`` points of every segment of a
    polyline (its last segment run on to depth ``far``) between depths near and far."""
    r, u, f = _frame()
    last = polyline[-1] - polyline[-2]
    run = (far - (polyline[-1] - EYE) @ f) / (last @ f)
    pts = np.vstack([polyline, polyline[-1] + last * max(run, 0.0)])
    worst, angle = 0.0, 0.0
    ref = pinhole_direction(x, y)
    for a, b in zip(pts[:-1], pts[1:]):
        t = np.linspace(0.0, 1.0, samples)[:, None]
        p = a + (b - a) * t
        depth = (p - EYE) @ f
        inside = (depth >= near) & (depth <= far)
        if not inside.any():
            continue
        worst = max(worst, np.hypot(*(pinhole_pixels(p[inside]) - [x, y]).T).max())
        if np.linalg.norm(b - a) * inside.mean() > 1e-3 * near:
            cos = (b - a) @ ref / np.linalg.norm(b - a)
            angle = max(angle, np.degrees(np.arccos(min(cos, 1.0))))
    return worst, angle


def _bent_rays(cam, pixels, drift_deg):
    """Polylines for pixels: a bent stretch in front of the near plane that lands exactly
    on the pixel's near-plane point, then on along the pinhole direction turned by
    ``drift_deg`` about the camera's up axis (0: the exact pinhole ray)."""
    r, u, f = _frame()
    near = cam.clip_start
    rays = []
    for x, y in pixels:
        d = pinhole_direction(x, y)
        p = EYE + d * near / (d @ f)
        c, s = np.cos(np.radians(drift_deg)), np.sin(np.radians(drift_deg))
        turned = d * c + np.cross(u, d) * s
        before = [p - 0.9 * near * f + 0.3 * r, p - 0.4 * near * f + 0.05 * u]
        after = [p + turned * near * k for k in (0.5, 2.0, 5.0)]
        rays.append(np.array(before + [p] + after))
    return np.array(rays)


PIXELS = [(10.5, 7.5), (32.5, 24.5), (60.5, 40.5)]


def test_the_exact_pinhole_ray_measures_zero_along_its_whole_stretch():
    cam = camera("C", EYE, TARGET, W, H, lens=LENS, clip_start=1.5, clip_end=40.0)
    rays = _bent_rays(cam, PIXELS, 0.0)
    err, angle = along_ray(rays, cam, *np.array(PIXELS).T)
    assert err.max() < 1e-9 and angle.max() < 1e-5  # the bent part is not measured


@pytest.mark.parametrize("clip_end", [40.0, np.inf])
def test_a_ray_exact_at_its_near_plane_that_drifts_behind_it_is_measured(clip_end):
    """The measure of report version 1 took the ray where it meets the near plane, where
    these rays are exact; along the stretch to the clip end (1000 near distances for an
    unbounded camera) they drift by many pixels."""
    cam = camera("C", EYE, TARGET, W, H, lens=LENS, clip_start=1.5, clip_end=clip_end)
    rays = _bent_rays(cam, PIXELS, 0.4)
    err, angle = along_ray(rays, cam, *np.array(PIXELS).T)
    far = clip_end if np.isfinite(clip_end) else 1000 * 1.5
    for ray, (x, y), e, a in zip(rays, PIXELS, err, angle):
        at_plane = np.hypot(*(pinhole_pixels(ray[2:3])[0] - [x, y]))
        want, want_angle = dense_worst(ray, x, y, 1.5, far)
        assert at_plane < 1e-9
        assert want > 0.5
        # the measure is the supremum the dense samples approach from below
        assert want <= e * (1 + 1e-12) and e == pytest.approx(want, rel=1e-4)
        assert a == pytest.approx(want_angle, rel=1e-6) and 0.3 < a <= 0.4 + 1e-9
    # the report's measure hands the rays over as coordinate planes: the same figures
    planes = np.moveaxis(rays, -1, 0).astype(np.float64)
    on_planes = along_ray_on_planes(planes, cam, *np.array(PIXELS).T)
    np.testing.assert_array_equal(on_planes[0], err)
    np.testing.assert_array_equal(on_planes[1], angle)


def test_a_ray_that_starts_beyond_the_near_plane_beside_the_frustum_is_measured_from_its_entry():
    """On a turned rig a ray starts on camera 1's near plane, which can lie beyond camera
    3's near plane to one side of its frustum, and comes round to camera 3's plane from
    behind. Its stretch is from that entry on: the measure once took every piece beyond
    the plane by depth alone and said 1,000 to 3,000 px for exact rays."""
    cam = camera("C", EYE, TARGET, W, H, lens=LENS, clip_start=1.5, clip_end=40.0)
    r, u, f = _frame()
    for drift, exact in ((0.0, True), (0.4, False)):
        rays = _bent_rays(cam, PIXELS, drift)
        # two vertices beyond the plane (depth 3 and 2 near distances), far to one side
        side = [
            np.array([ray[2] + 2.0 * 1.5 * f - 9.0 * r, ray[2] + 1.5 * f - 6.0 * r]) for ray in rays
        ]
        turned = np.array([np.vstack([s, ray]) for s, ray in zip(side, rays)])
        depth = (turned - EYE) @ f
        assert (depth[:, :2] > 1.5).all() and (depth[:, 2:4] < 1.5).all()
        err, angle = along_ray(turned, cam, *np.array(PIXELS).T)
        for ray, (x, y), e, a in zip(turned, PIXELS, err, angle):
            want, want_angle = dense_worst(ray[4:], x, y, 1.5, 40.0)  # from the plane's point
            far_off, _ = dense_worst(ray[:3], x, y, 1.5, 40.0)  # the start, beside the frustum
            assert far_off > 100  # the image is 64 px wide
            if exact:
                assert e < 1e-9 and a < 1e-5
            else:
                assert want > 0.5 and e == pytest.approx(want, rel=1e-4)
                assert a == pytest.approx(want_angle, rel=1e-6)


def test_the_turned_rigs_image_blend_rays_are_each_cameras_pinhole_rays_from_its_near_plane():
    """IMAGE_BLEND lays every preserved ray out as its camera's curve R_i: checked here
    against each camera's straight ray from its near plane, computed from the camera's
    matrix (look_at), lens and sensor; the report agrees (it said 1,000 to 2,300 px for
    camera 3 when it measured by depth alone)."""
    from multiscale_camera.core.quality import build_report, measured_pixels

    cams, masks = turned_rig(96, 72)
    fld = prepare_image_blend(Rig(cams, masks))
    rep = build_report(fld, "STANDARD")
    for i, cam in enumerate(cams):
        m = np.asarray(cam.matrix_world, dtype=np.float64)
        right, up, fwd, eye = m[:3, 0], m[:3, 1], -m[:3, 2], m[:3, 3]
        k = cam.lens / 36.0 * 96  # pixels per unit at depth 1 (sensor fitted to the width)
        ix, iy = measured_pixels(masks[i])
        d = (
            fwd
            + right[None] * ((ix + 0.5 - 48) / k)[:, None]
            - up[None] * ((iy + 0.5 - 36) / k)[:, None]
        )
        p = eye + d * (cam.clip_start / (d @ fwd))[:, None]  # the near-plane points
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        v = fld.rays(ix, iy).vertices.astype(np.float64)
        near = np.argmin(np.linalg.norm(v - p[:, None], axis=-1), axis=1)
        rows = np.arange(len(ix))
        assert np.linalg.norm(v[rows, near] - p, axis=1).max() < 1e-5 * cam.clip_start
        for j in range(v.shape[1]):  # every later vertex on the straight ray
            after = near < j
            off = v[after, j] - p[after]
            across = off - (off * d[after]).sum(1, keepdims=True) * d[after]
            assert np.linalg.norm(across, axis=1).max(initial=0) < 1e-5 * cam.clip_start
            assert ((off * d[after]).sum(1) > 0).all()
        if i == 2:  # the hard case is there: rays that start beyond camera 3's plane
            assert (((v[:, 0] - eye) @ fwd) > cam.clip_start).mean() > 0.5
        assert rep["cameras"][i]["preserved_px"]["max"] < 1e-3


def test_fold_counter_matches_brute_force_on_the_turned_rig():
    """IMAGE_BLEND truly folds on the turned rig; most of its rays start beyond camera
    3's near plane, whose bending stretch the counter once took to be empty."""
    cams, masks = turned_rig(40, 30)
    fld = prepare_image_blend(Rig(cams, masks))
    verts, active = _lattice(fld)
    start_beyond = ((verts[..., 0, :] - cams[2].eye) @ cams[2].forward) > cams[2].clip_start
    assert start_beyond.mean() > 0.5 and active[start_beyond].any(axis=-1).all()
    folds = quad_folds(verts, active)
    quads = [(y, x) for y in range(29) for x in range(39)]
    brute = brute_force_folds(verts, active, quads).reshape(29, 39)
    assert folds.sum() >= 20
    np.testing.assert_array_equal(folds, brute)


def test_a_ray_that_never_reaches_the_stretch_measures_infinite():
    cam = camera("C", EYE, TARGET, W, H, lens=LENS, clip_start=1.5, clip_end=40.0)
    r, u, f = _frame()
    ray = np.array([EYE + f * 0.2, EYE + f * 0.5, EYE + f * 0.5 - r])  # turns back
    err, angle = along_ray(ray[None], cam, [32.5], [24.5])
    assert np.isinf(err[0]) and np.isinf(angle[0])


def _quad_rays(verts, active, y, x):
    quad = [(y, x), (y, x + 1), (y + 1, x + 1), (y + 1, x)]
    return [verts[p].astype(np.float64) for p in quad], [active[p] for p in quad]


def brute_force_folds(verts, active, quads):
    """For each quad (y, x): every vertex m of ray a gives a plane normal to a's central
    difference there; every other ray meets it at the crossing of its polyline nearest
    to a's vertex (found among all its segments; the end segment extended when the
    polyline does not cross); the quad folds where a corner triangle's orientation in a
    live section differs from the first section's."""
    out = []
    for y, x in quads:
        rays, act = _quad_rays(verts, active, y, x)
        a = rays[0]
        t = np.gradient(a, axis=0)
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        k = len(a)
        pts, live = [np.zeros((k, 3))], act[0].copy()
        for q, aq in zip(rays[1:], act[1:]):
            s = np.einsum("mjc,mc->mj", q[None] - a[:, None], t)  # planes x vertices
            s0, s1 = s[:, :-1], s[:, 1:]  # (planes, segments)
            cross = (s0 * s1 <= 0) & (s0 != s1)
            w = np.where(cross, s0 / np.where(s0 != s1, s0 - s1, 1.0), 0.0)
            c = q[None, :-1] + (q[None, 1:] - q[None, :-1]) * w[..., None]
            dist = np.where(cross, np.linalg.norm(c - a[:, None], axis=-1), np.inf)
            j = np.argmin(dist, axis=1)
            # no crossing: extend the end segment the plane lies beyond
            none = ~cross.any(axis=1)
            j[none] = np.where(s[none, 0] > 0, 0, k - 2)
            m = np.arange(k)
            ends = s0[m, j] / (s0[m, j] - s1[m, j])
            p = q[j] + (q[j + 1] - q[j]) * np.where(none, ends, w[m, j])[:, None] - a
            live &= aq[j]
            pts.append(p)
        orient = []
        for i0, i1, i2 in ((0, 1, 2), (1, 2, 3), (2, 3, 0), (3, 0, 1)):
            area = np.cross(pts[i1] - pts[i0], pts[i2] - pts[i0])
            orient.append(np.sign(np.einsum("mc,mc->m", area, t)))
        orient = np.array(orient).T  # (k, 4)
        flipped = (orient != orient[0]) & (orient != 0) & (orient[0] != 0) & live[:, None]
        out.append(bool(flipped.any()))
    return np.array(out)


def _lattice(fld, y0=0, y1=None, x0=0, x1=None):
    """Rays of the pixels [y0, y1) x [x0, x1) (default: all) as (h, w, K, 3), and the
    bending stretch's vertices."""
    w, h = fld.rig.size
    ys, xs = np.arange(y0, h if y1 is None else y1), np.arange(x0, w if x1 is None else x1)
    iy, ix = np.meshgrid(ys, xs, indexing="ij")
    b = fld.rays(ix.ravel(), iy.ravel())
    verts = b.vertices.reshape(len(ys), len(xs), -1, 3)
    return verts, bending_active(verts, fld.rig.cameras[-1], None, fld.rig.cameras[:-1])


def test_fold_counter_matches_brute_force_where_linear_folds():
    cams, masks = zoom_rig(40, 30, turn_deg=40)
    verts, active = _lattice(prepare_linear(Rig(cams, masks)))
    folds = quad_folds(verts, active)
    quads = [(y, x) for y in range(29) for x in range(39)]
    brute = brute_force_folds(verts, active, quads).reshape(29, 39)
    assert folds.sum() >= 20
    np.testing.assert_array_equal(folds, brute)


def test_no_false_folds_in_the_deepest_preserved_disk_of_the_1000x_rig():
    """Exact IMAGE_BLEND rays of the 1000x rig at 240x135: the count at equal arc length
    flagged 174 quads inside camera 3's preserved disk; in sections, none fold, as the
    brute-force count of the quads around that disk agrees."""
    cams, masks = zoom1000_rig(240, 135)
    fld = prepare_image_blend(Rig(cams, masks))
    folds, stride = fold_map(fld)
    assert stride == 1 and folds.sum() == 0
    ys, xs = np.nonzero(masks[2])
    y0, x0 = ys.min() - 2, xs.min() - 2
    verts, active = _lattice(fld, y0, ys.max() + 3, x0, xs.max() + 3)
    quads = [
        (y, x)
        for y in range(verts.shape[0] - 1)
        for x in range(verts.shape[1] - 1)
        if (y + x) % 5 == 0  # every fifth quad keeps the Python reference quick
    ]
    assert len(quads) > 200
    assert not brute_force_folds(verts, active, quads).any()


def test_a_camera_with_no_measured_pixel_reports_null_and_why():
    from multiscale_camera.core.quality import build_report, headline, readable

    cams, masks = zoom1000_rig(48, 27)
    masks = masks.copy()
    masks[1] = False  # an intermediate camera that only bends rays
    rep = build_report(prepare_image_blend(Rig(cams, masks)), "STANDARD")
    middle = rep["cameras"][1]
    assert rep["version"] == 2 and middle["pixels"] == 0
    assert middle["preserved_px"] == {"p50": None, "p95": None, "max": None}
    assert middle["unmeasured"] == "its mask is empty: no preserved pixel to measure"
    assert rep["newton_lost"] == 0 and rep["unfinished"] == 0
    assert headline(rep).startswith("IMAGE_BLEND: p95 error 0.00 px")
    assert "'C2': not measured: its mask is empty: no preserved pixel to measure" in readable(rep)


def test_a_traced_fields_rays_measured_in_blocks_give_each_ray_its_own_figures(monkeypatch):
    """The report lays a traced field's measured rays out a block of vertices at a time
    (the 1000x rig's 20,000 rays of about 680 vertices a camera held about 400 MB at
    once at 1920x1080): blocks of 700 vertices (a few rays each) give every ray the
    figures it has measured with all the others at once, to float32 rounding (a ray
    laid out with fewer others runs straight on past its trace in fewer float32
    vertices: the same line, rounded elsewhere)."""
    from multiscale_camera.core.methods import prepare, settings_for
    from multiscale_camera.core.quality import measured_pixels, preserved_error, report

    cams, masks = zoom_rig(40, 30)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", settings_for("PREVIEW"))
    k = fld.ray_vertices()
    assert k == fld.traced.vertices.shape[1] > 20
    monkeypatch.setattr(report, "ALONG_BLOCK_VERTICES", 700)
    for i in range(len(cams)):
        ix, iy = measured_pixels(masks[i])
        whole = preserved_error(cams, i, fld.rays(ix, iy))
        blocks = report._preserved_in_blocks(fld, i, ix, iy, None)
        assert len(ix) > 700 // k and blocks.pixels == whole.pixels == len(ix)
        np.testing.assert_allclose(blocks.error_px, whole.error_px, rtol=0, atol=1e-4)
        np.testing.assert_allclose(blocks.angle_deg, whole.angle_deg, rtol=0, atol=1e-4)
