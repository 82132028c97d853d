"""tools/fold_sites.py's ``family=`` prototype: the family it patches in must still be one
family (its Jacobian the derivatives of its points, its inverse the pixel it came from),
or the folds it counts would be the patch's, not the family's."""

import numpy as np
import pytest

import multiscale_camera.core.field.tracer as tracer_module
from fixtures.rigs import zoom1000_rig
from fixtures.tools import load_tool
from multiscale_camera.core.geometry import Family
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
