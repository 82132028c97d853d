"""The report's measures against references written here: the preserved error along
the whole ray against an independent pinhole projection, and the fold counter against
a brute-force count of the same sections."""

import numpy as np
import pytest

from fixtures.rigs import camera, look_at, zoom1000_rig, zoom_rig
from multiscale_camera.core.geometry import Rig
from multiscale_camera.core.methods import prepare_image_blend, prepare_linear
from multiscale_camera.core.quality import along_ray, bending_active, fold_map, quad_folds

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
    return verts, bending_active(verts, fld.rig.cameras[-1])


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
