"""tools/transition_convergence.py: its distance between two traces of a ray, against
rays written out here."""

import numpy as np

from fixtures.rigs import three_camera_rig
from fixtures.tools import load_tool
from multiscale_camera.core.geometry import Rig

tc = load_tool("transition_convergence")


def _line(start, direction, step, k):
    direction = np.asarray(direction, dtype=np.float64)
    direction /= np.linalg.norm(direction)
    return np.asarray(start, dtype=np.float64) + np.arange(k)[:, None] * step * direction


def test_a_parallel_ray_is_its_offset_away_whatever_its_vertices():
    # the same direction 0.3 across, vertices at another spacing and phase: the
    # distance is the offset, in pixels of 0.1 world units
    ref = _line([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.25, 40)[None]
    got = _line([0.3, 0.0, 0.1], [0.0, 0.0, 1.0], 0.4, 20)[None]
    worst = tc.across_px(ref, [40], got, [20], lambda p: np.full(len(p), 0.1))
    np.testing.assert_allclose(worst, [3.0], rtol=1e-12)


def test_sliding_along_the_ray_moves_nothing_and_a_turn_is_measured_where_it_is():
    ref = _line([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], 0.5, 30)
    slid = ref + [0.2, 0.0, 0.0]  # along the ray: nothing across
    bent = ref.copy()
    bent[20:] += (np.arange(10)[:, None] + 1) * [0.0, 0.01, 0.0]  # off by 0.1 at the end
    worst = tc.across_px(
        np.stack([ref, ref]), [30, 30], np.stack([slid, bent]), [30, 30], lambda p: np.ones(len(p))
    )
    np.testing.assert_allclose(worst[0], 0.0, atol=1e-12)
    # the bent ray's last vertex lies past the reference's arc length by its bend: it is
    # compared where the reference's length ends, its earlier vertices exactly
    assert 0.08 < worst[1] <= 0.1 + 1e-12


def test_only_the_vertices_each_ray_counts_are_weighed():
    ref = _line([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 1.0, 10)[None]
    got = ref.copy()
    got[0, 6:] += [5.0, 0.0, 0.0]  # beyond the counted vertices
    worst = tc.across_px(ref, [10], got, [6], lambda p: np.ones(len(p)))
    np.testing.assert_allclose(worst, [0.0], atol=1e-12)


def test_transition_pixels_are_drawn_once_each_and_never_from_a_kept_view():
    cams, masks = three_camera_rig(48, 27)
    rig = Rig(cams, masks)
    kept = np.any([np.asarray(m, dtype=bool) for m in masks], axis=0)
    free = int((~kept).sum())
    u, v = tc.transition_pixels(rig, 100)
    x, y = (u - 0.5).astype(int), (v - 0.5).astype(int)
    assert len(u) == 100 and not kept[y, x].any()
    assert len(set(zip(x.tolist(), y.tolist()))) == 100
    # fewer free pixels than asked: every one of them, once
    u, v = tc.transition_pixels(rig, 10 * free)
    assert len(u) == free and len(set(zip(u.tolist(), v.tolist()))) == free
