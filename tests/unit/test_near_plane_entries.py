"""``near_plane_entries`` (coordinate planes, upward crossings located one by one)
against the straightforward form it replaced, written out here: the same float64
bits on the rays of bench rigs, on perturbed rays that cross planes back and forth,
and on rays that start beyond a plane or never reach it."""

import numpy as np
import pytest

from fixtures.rigs import demo_rig, turned_rig, zoom1000_rig
from multiscale_camera.core.geometry import Rig, dot3, near_plane_entries
from multiscale_camera.core.methods import prepare, settings_for


def reference_entries(vertices, cameras):
    """Every segment's upward crossing computed, the earliest after the entry before."""
    v = np.asarray(vertices, dtype=np.float64)
    r, k = v.shape[:2]
    out = np.empty((len(cameras), r))
    prev = np.zeros(r)
    index = np.arange(k - 1, dtype=np.float64)[None, :]
    rows = np.arange(r)
    for n, cam in enumerate(cameras):
        d = dot3(v - cam.eye, cam.forward) - float(cam.clip_start)
        d0, d1 = d[:, :-1], d[:, 1:]
        up = (d0 < 0) & (d1 >= 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            at = index + np.where(up, -d0 / (d1 - d0), np.inf)
        at = np.where(up & (at >= prev[:, None]), at, np.inf).min(axis=1)
        finite = np.isfinite(prev)
        seg = np.clip(np.floor(np.where(finite, prev, 0.0)), 0, k - 2).astype(np.int64)
        t = np.where(finite, prev, 0.0) - seg
        there = d[rows, seg] * (1 - t) + d[rows, seg + 1] * t
        at = np.where(np.isinf(at) & finite & (there >= 0), prev, at)
        out[n] = at
        prev = at
    return out


@pytest.mark.parametrize("rig", [demo_rig, turned_rig, zoom1000_rig])
def test_entries_are_the_reference_bits_on_bench_rigs(rig):
    cams, masks = rig(160, 90)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("PREVIEW"))
    iy, ix = np.mgrid[0:90, 0:160]
    verts = fld.rays(ix.ravel(), iy.ravel()).vertices
    got = near_plane_entries(verts, cams)
    np.testing.assert_array_equal(got, reference_entries(verts, cams))
    assert np.isfinite(got).any(axis=1).all()  # every camera entered somewhere


def test_entries_are_the_reference_bits_on_rays_that_cross_back_and_forth():
    cams, _masks = turned_rig(64, 36)
    rng = np.random.default_rng(3)
    iy, ix = np.mgrid[0:36, 0:64]
    fld = prepare(Rig(cams, _masks), "IMAGE_BLEND", settings_for("PREVIEW"))
    verts = fld.rays(ix.ravel(), iy.ravel()).vertices.astype(np.float64)
    scale = np.linalg.norm(verts[:, -1] - verts[:, 0], axis=-1)[:, None, None]
    noisy = verts + rng.normal(size=verts.shape) * scale * 0.2
    got = near_plane_entries(noisy, cams)
    expected = reference_entries(noisy, cams)
    np.testing.assert_array_equal(got, expected)
    # the case mix the test stands for: several crossings, none, and starts beyond
    assert np.isinf(expected).any() and np.isfinite(expected).any()
    assert (expected[1:] == expected[:-1]).any()  # a ray already beyond the next plane
