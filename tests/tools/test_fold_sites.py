"""tools/fold_sites.py's ``family=`` prototype: the family it patches in must still be one
family (its Jacobian the derivatives of its points, its inverse the pixel it came from),
or the folds it counts would be the patch's, not the family's."""

import numpy as np
import pytest

import multiscale_camera.core.field.tracer as tracer_module
from fixtures.rigs import zoom1000_rig
from fixtures.tools import load_tool
from multiscale_camera.core.geometry import Family, Rig
from multiscale_camera.core.geometry import family as family_module

fs = load_tool("fold_sites")


def test_soft_clamp_is_the_identity_inside_and_bounded_outside():
    c = np.array([-1e6, -30.0, 0.0, 50.0, 100.0, 130.0, 1e6])
    held, slope = fs.soft_clamp(c, 100.0, 0.25)
    np.testing.assert_array_equal(held[2:5], c[2:5])
    np.testing.assert_array_equal(slope[2:5], 1.0)
    assert held[0] == pytest.approx(-25.0) and held[-1] == pytest.approx(125.0)
    assert np.all(np.diff(held) > -1e-12)
    # its slope is the derivative of its value
    h = 1e-4
    x = np.array([-40.0, -3.0, 104.0, 160.0])
    fd = (fs.soft_clamp(x + h, 100.0, 0.25)[0] - fs.soft_clamp(x - h, 100.0, 0.25)[0]) / (2 * h)
    np.testing.assert_allclose(fs.soft_clamp(x, 100.0, 0.25)[1], fd, rtol=1e-7)


@pytest.fixture
def held_family(monkeypatch):
    # edge_family patches the classes: restore them after the test
    monkeypatch.setattr(family_module.Family, "_near", family_module.Family._near)
    monkeypatch.setattr(tracer_module.FieldTracer, "_tangent", tracer_module.FieldTracer._tangent)
    fs.edge_family(0.3)


@pytest.mark.parametrize("i", [1, 2])
def test_the_held_family_is_a_family(held_family, i):
    cams, _masks = zoom1000_rig(192, 108)
    fam = Family(cams, i, 0.2)
    rng = np.random.default_rng(i)
    n = 300
    # pixels on and far off the image, every stretch of tau
    u, v = rng.uniform(-400, 600, n), rng.uniform(-300, 400, n)
    tau = rng.uniform(0, i + 0.8, n)
    p, t, ju, jv = fam.evaluate(u, v, tau, jacobian=True)
    h = 1e-4
    for got, du, dv, dt in ((ju, h, 0, 0), (jv, 0, h, 0), (t, 0, 0, h)):
        fd = (
            fam.evaluate(u + du, v + dv, tau + dt)[0] - fam.evaluate(u - du, v - dv, tau - dt)[0]
        ) / (2 * h)
        assert np.abs(fd - got).max() <= 1e-6 * np.abs(got).max()
    # off the image, the directions are the held pixel's, not the pinhole's
    off = (u < -100) & (tau >= i)
    assert off.sum() > 10
    unit = t[off] / np.linalg.norm(t[off], axis=1)[:, None]
    pinhole = cams[i].directions(u[off], v[off])
    assert np.all(np.einsum("ij,ij->i", unit, pinhole) < 1 - 1e-6)
    # Newton recovers the pixel each point came from
    uu, vv, tt = fam.start(p)
    su, sv, st, _tangent, lost = fam.solve(p, uu, vv, tt, 30)
    assert lost == 0
    np.testing.assert_allclose(su, u, atol=1e-5)
    np.testing.assert_allclose(sv, v, atol=1e-5)


def _at(cam, px, py, depth):
    """The point of camera ``cam``'s pixel (px, py) at ``depth`` along its view axis."""
    d = cam.directions(np.array([px]), np.array([py]))[0]
    return cam.eye + d * depth / (d @ cam.forward)


def test_shrunk_membership_moves_only_transition_values_beside_the_smaller_view():
    cams, masks = zoom1000_rig(192, 108)
    rig = Rig(cams, masks)
    c2, c3 = cams[1], cams[2]
    # beyond each camera's near plane (the fall whole); 3 image widths to the right of
    # the centre is 2.5 image sizes off the view, past m1 = 2
    centre = _at(c2, 96.0, 54.0, 2 * c2.clip_start)
    far = _at(c2, 96.0 + 3 * 192, 54.0, 2 * c2.clip_start)
    behind = c2.eye - c2.forward * c2.clip_start
    far3 = _at(c3, 96.0 + 3 * 192, 54.0, 2 * c3.clip_start)
    x = np.array([centre, far, far, behind, far3, far3])
    nval = np.array([1.6, 1.6, 2.0, 1.6, 2.4, 3.0])
    got = fs.shrunk_membership(rig, x, nval, 0.5, 2.0)
    # within camera 2's view kept; far off it the outer camera's 1; whole values (the
    # preserved rays') kept; behind camera 2's eye kept; the 2-3 band beside camera 3's
    # view down to 2
    np.testing.assert_allclose(got, [1.6, 1.0, 2.0, 1.6, 2.0, 3.0], atol=1e-12)
    # 1.75 image widths right is 1.25 off: half way down the smoothstep, half the excess
    mid = _at(c2, 96.0 + 1.75 * 192, 54.0, 2 * c2.clip_start)
    np.testing.assert_allclose(fs.shrunk_membership(rig, mid[None], [1.6], 0.5, 2.0), [1.3])
    # at camera 2's eye the fall has not begun; half way to its near plane, half of it
    side = _at(c2, 96.0 + 3 * 192, 54.0, 0.5 * c2.clip_start)
    np.testing.assert_allclose(fs.shrunk_membership(rig, side[None], [1.6], 0.5, 2.0), [1.3])
