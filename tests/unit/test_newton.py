"""Newton's inversion of the ray families off the cameras' images, and the warnings
that say where the trace put something in place of the field."""

import numpy as np
import pytest

from fixtures.rigs import demo_rig, zoom1000_rig
from multiscale_camera.core.field import StopReason, Traced
from multiscale_camera.core.geometry import Family, Rig
from multiscale_camera.core.geometry.family import LOST_TOLERANCE, RETRY_TOLERANCE
from multiscale_camera.core.quality import substitution_messages


@pytest.mark.parametrize("i, taus", [(1, (0.8, 0.9, 0.97)), (2, (1.85, 1.95, 1.99))])
def test_newton_lost_points_far_off_the_image_of_the_1000x_rig_are_found(i, taus):
    """Where the 1000x rig's transition rays pass beside camera 2 or 3, thousands of
    pixels off its image, Newton from camera 1's pixel lost 1,271 points at 240x135 and
    the field took camera 1's direction there. The retry, damped and started again from
    the middle of the last guide, finds them all."""
    cams, _ = zoom1000_rig(240, 135)
    fam = Family(cams, i, 0.2)
    u, v, t = np.meshgrid([-6000.0, -3000.0, -1500.0, -800.0], [-200.0, 100.0, 300.0], taus)
    pts, _ = fam.evaluate(u.ravel(), v.ravel(), t.ravel())
    x, y = cams[0].project(pts)[0].T
    t0 = fam.start(pts)[2]
    plain = fam.invert(pts, x, y, t0, 12)[3]
    assert (plain > LOST_TOLERANCE * fam.scale).sum() >= 5  # the undamped run diverges
    su, sv, st, _tangent, lost, _jac = fam.solve(pts, x, y, t0, 2, with_jacobian=True)
    assert not lost.any()
    back, _ = fam.evaluate(su, sv, st)
    assert np.linalg.norm(back - pts, axis=1).max() <= RETRY_TOLERANCE * fam.scale


def test_warm_starts_one_newton_step_short_are_finished_without_the_damped_retry(
    monkeypatch,
):
    """The trace's predicted starts get one Newton step; where that leaves a point
    short, a few more plain steps finish it. The damped retry from camera 1's pixel,
    dozens of evaluations a point, is left for the runs that diverge."""
    cams, _ = demo_rig(240, 135)
    fam = Family(cams, 2, 0.2)
    rng = np.random.default_rng(3)
    u, v, tau = rng.uniform(20, 220, 300), rng.uniform(10, 125, 300), rng.uniform(0.1, 2.9, 300)
    pts, _ = fam.evaluate(u, v, tau)
    su, sv = u + rng.normal(0, 3, 300), v + rng.normal(0, 3, 300)
    st = np.maximum(tau + rng.normal(0, 0.1, 300), 0.0)
    one = fam.invert(pts, su, sv, st, 1, tolerance=1e-6)[3]
    short = int((one > RETRY_TOLERANCE * fam.scale).sum())
    assert short >= 30  # one step leaves them short
    damped = []
    plain = Family.invert_damped

    def counted(self, points, *args, **kwargs):
        damped.append(len(points))
        return plain(self, points, *args, **kwargs)

    monkeypatch.setattr(Family, "invert_damped", counted)
    ru, rv, rt, _tangent, lost = fam.solve(pts, su, sv, st, 1, tolerance=1e-6)
    assert lost == 0 and sum(damped) <= short // 10  # (all of them before)
    back, _ = fam.evaluate(ru, rv, rt)
    assert np.linalg.norm(back - pts, axis=1).max() <= RETRY_TOLERANCE * fam.scale
    # the points' own rays (the family is one-to-one here), to within that distance
    assert np.abs(ru - u).max() < 0.05 and np.abs(rv - v).max() < 0.05
    assert np.abs(rt - tau).max() < 1e-3


def test_substitutions_are_said_with_the_camera_and_the_pixels():
    cams, masks = zoom1000_rig(24, 14)
    rig = Rig(cams, masks)
    index = np.full((14, 24), -1, dtype=np.int32)
    index[2, 3], index[5, 7], index[9, 20] = 0, 1, 2
    reason = np.array([StopReason.STALLED, StopReason.LEFT_GRID, StopReason.STALLED], np.int8)
    traced = Traced(
        np.zeros((3, 2, 3), np.float32),
        np.zeros((3, 2), np.float32),
        np.full(3, 2, np.int32),
        reason,
        1.0,
    )
    lost = [
        (1, np.array([[3.5, 2.5], [7.5, 5.5]], np.float32)),
        (1, np.array([[3.5, 2.5]], np.float32)),
    ]
    assert substitution_messages(rig, traced, index, lost) == [
        "Newton's inversion of camera 'C2''s curved rays failed at 3 points of 2 traced rays "
        "(pixels x 3-7, y 2-5): there the field took camera 'C1''s direction instead of "
        "'C2''s, so rays there may bend wrongly",
        "2 traced rays stalled (the blended field vanished) before leaving the grid "
        "(pixels x 3-20, y 2-9)",
    ]
