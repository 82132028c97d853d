"""The fold count skips what cannot fold (``kept_limits``): quads kept by camera 1 are
not checked, quads kept by camera i > 1 only up to the first section past camera i's
near plane. Against the full count (every quad, every section: ``quad_folds`` without
a limit, itself checked against the frozen reference) on rigs that fold and rigs that
do not, and on a rig whose quads kept by camera 2 fold before camera 2's near plane."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fixtures.rigs import (
    _chain,
    contradictory_rig,
    demo_rig,
    three_camera_rig,
    turned_rig,
    zoom1000_rig,
)
from multiscale_camera.core.geometry import Rig, build_guides, curved_rays
from multiscale_camera.core.methods import prepare, settings_for
from multiscale_camera.core.quality import fold_map, quad_folds
from multiscale_camera.core.quality import folds as folds_module
from multiscale_camera.core.quality.report import kept_limits

from .fold_reference import reference_quad_folds
from .test_folds_exact import lattice, perturbed

ALL = np.iinfo(np.int16).max  # kept_limits' "every section"


def full_count(fld):
    """Every quad in every section of the bending stretch."""
    w, h = fld.rig.size
    return quad_folds(*lattice(fld, np.arange(w), np.arange(h)))


def steep_rig(width, height):
    """Three cameras turned 80 and then 80 degrees about the subject; camera 2 keeps all
    but two corners, where cameras 1 and 3 keep a few pixels: the rays camera 2 keeps
    cross one another before its near plane (its own curves R_2 fold)."""
    cams = _chain((20.0, 8.0, 3.2), (8.0, 3.2, 1.28), (0, 80, 160), width, height)
    masks = np.zeros((3, height, width), dtype=bool)
    masks[1] = True
    masks[1, :4, :4] = masks[1, -4:, -4:] = False
    masks[0, :2, :2] = masks[2, -2:, -2:] = True
    return cams, masks


@pytest.mark.parametrize(
    "rig", [turned_rig, contradictory_rig, demo_rig, zoom1000_rig, three_camera_rig]
)
def test_skipping_count_equals_the_full_count(rig):
    cams, masks = rig(160, 90)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    skipping, _stride = fold_map(fld, processes=1)
    full = full_count(fld)
    np.testing.assert_array_equal(skipping, full)
    limit = kept_limits(fld, np.arange(90), np.arange(160))
    assert (limit == 0).sum() > 1000  # camera 1 keeps quads: they were skipped
    assert (limit == fld.near_vertex(1) + 2).sum() > 500  # camera 2's cut short
    if rig in (turned_rig, contradictory_rig):
        assert full.sum() > 0, "a rig that folds"


def test_quads_camera_2_keeps_that_fold_before_its_near_plane_are_counted():
    cams, masks = steep_rig(96, 54)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    skipping, _stride = fold_map(fld, processes=1)
    verts, active = lattice(fld, np.arange(96), np.arange(54))
    full = reference_quad_folds(verts, active)
    np.testing.assert_array_equal(skipping, full)
    limit = kept_limits(fld, np.arange(54), np.arange(96))
    cut = limit == fld.near_vertex(1) + 2  # quads camera 2 keeps
    assert cut.sum() > 0.9 * cut.size
    assert (full & cut).sum() > 1000, (full & cut).sum()  # camera 2's own rays fold


def test_fold_map_makes_rays_only_for_the_quads_it_checks(monkeypatch):
    cams, masks = demo_rig(160, 90)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    made = np.zeros((90, 160), dtype=int)
    planes = type(fld).vertex_planes

    def spy(self, ix, iy):
        np.add.at(made, (iy, ix), 1)
        return planes(self, ix, iy)

    # the count's rays (fold_map's probe, one ray that says how many vertices each
    # has, asks ``rays``)
    monkeypatch.setattr(type(fld), "vertex_planes", spy)
    fold_map(fld, processes=1)
    monkeypatch.undo()
    checked = kept_limits(fld, np.arange(90), np.arange(160)) != 0
    corner = np.zeros((90, 160), dtype=bool)
    for dy in (0, 1):
        for dx in (0, 1):
            corner[dy : dy + 89, dx : dx + 159] |= checked
    assert (made[corner] >= 1).all() and not made[~corner].any()
    assert corner.sum() < 0.6 * corner.size  # camera 1 keeps the rest: no rays there


def test_kept_rays_are_camera_i_curves_and_its_pinhole_rays_past_its_near_plane():
    """What the skip rests on: a kept pixel's ray is R_i bit for bit (one-hot weights),
    and R_i's vertex ``near_vertex(i)`` is on camera i's near plane, the ones after it on
    camera i's pinhole ray through the pixel centre."""
    w, h = 160, 90
    cams, masks = demo_rig(w, h)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    assert fld.exact_kept
    for i, cam in enumerate(cams):
        iy, ix = np.nonzero(masks[i])
        got = fld.rays(ix, iy).vertices
        g = build_guides(cams, ix + 0.5, iy + 0.5, beta=fld.rig.beta)
        curve = curved_rays(g, fld.segments)[i]
        np.testing.assert_array_equal(got, curve.astype(np.float32))
        start = fld.near_vertex(i)
        depth = (curve[:, start:] - cam.eye) @ cam.forward
        assert np.allclose(depth[:, 0], cam.clip_start, rtol=1e-12)
        assert (np.diff(depth, axis=1) > 0).all()
        pix, _depth = cam.project(curve[:, start:].reshape(-1, 3))
        centre = np.repeat(np.stack([ix + 0.5, iy + 0.5], axis=1), curve.shape[1] - start, 0)
        assert np.abs(pix - centre).max() < 1e-6


def test_traced_fields_do_not_claim_exact_kept_rays():
    cams, masks = three_camera_rig(64, 36)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", settings_for("PREVIEW"))
    assert not fld.exact_kept
    assert (kept_limits(fld, np.arange(36), np.arange(64)) == ALL).all()


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    k=st.integers(2, 12),
    noise=st.sampled_from([0.0, 0.05, 0.4]),
    back=st.sampled_from([0.0, 0.3]),
)
def test_limited_sections_are_those_of_the_reference(seed, k, noise, back):
    verts, active = perturbed(seed, k, noise, back, False)
    rng = np.random.default_rng(seed)
    limit = rng.integers(0, k + 2, size=(verts.shape[0] - 1, verts.shape[1] - 1))
    expected = reference_quad_folds(verts, active, np.minimum(limit, k))
    np.testing.assert_array_equal(quad_folds(verts, active, limit), expected)


@pytest.mark.parametrize("rig", [demo_rig, turned_rig])
def test_image_blend_rays_are_the_blend_of_all_curves_bit_for_bit(rig):
    """Kept pixels make their own curve alone: the bits (signed zeros too) of the blend
    of every curve by the pixel's weights, as every pixel's ray was made before."""
    cams, masks = rig(96, 54)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    iy, ix = np.mgrid[0:54, 0:96]
    ix, iy = ix.ravel(), iy.ravel()
    g = build_guides(cams, ix + 0.5, iy + 0.5, beta=fld.rig.beta)
    w = fld.weights[:, iy, ix].astype(np.float64)
    blend = np.einsum("np,npkc->pkc", w, curved_rays(g, fld.segments)).astype(np.float32)
    got = fld.rays(ix, iy).vertices
    np.testing.assert_array_equal(got.view(np.uint32), blend.view(np.uint32))
    assert masks.any(axis=0).mean() > 0.3 and not masks.any(axis=0).all()


@settings(max_examples=200, deadline=None)
@given(
    runs=st.lists(st.tuples(st.integers(1, 300), st.sampled_from([0, 0, 2, 10, 18])), min_size=1),
    cols=st.integers(1, 400),
)
def test_row_windows_cover_every_quad_to_check_once(runs, cols):
    limit = np.concatenate([np.full(n, v) for n, v in runs])
    covered = np.zeros(len(limit), dtype=int)
    for c0, c1, kmax in folds_module._row_windows(limit, cols):
        assert 0 <= c0 < c1 <= len(limit) and c1 - c0 <= cols
        assert kmax >= limit[c0:c1].max() and limit[c0] > 0 and limit[c1 - 1] > 0
        covered[c0:c1] += 1
    assert (covered <= 1).all()
    assert (covered[limit > 0] == 1).all()


@pytest.mark.parametrize("rig", [turned_rig, demo_rig])
def test_image_blend_vertex_planes_are_its_rays_float32_vertices(rig):
    """The fold count reads IMAGE_BLEND's rays as coordinate planes made without a
    bundle: every pixel's, kept or blended, the bits ``rays`` hands to the renderer."""
    cams, masks = rig(64, 36)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    iy, ix = (a.ravel() for a in np.mgrid[0:36, 0:64])
    got = fld.vertex_planes(ix, iy)
    want = np.moveaxis(fld.rays(ix, iy).vertices, -1, 0).astype(np.float64)
    assert got.dtype == np.float64 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, want)
    w = fld.weights[:, iy, ix]
    assert (w == 1).any(axis=0).any() and not (w == 1).any(axis=0).all()  # both kinds
