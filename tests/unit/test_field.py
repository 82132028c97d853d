"""The scalar-field method against independent references."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fixtures.masks import disk_masks, radius
from fixtures.rigs import camera, orbit, three_camera_rig, zoom1000_rig, zoom_rig
from multiscale_camera.core.errors import RigError
from multiscale_camera.core.field import (
    FieldTracer,
    choose_grid,
    fill_membership,
    solve_membership,
)
from multiscale_camera.core.geometry import Family, Rig
from multiscale_camera.core.methods import prepare, settings_for, traced
from multiscale_camera.core.quality import along_ray, build_report, turn_deg


def test_single_camera_tangent_field_is_the_pinhole_direction():
    cam = camera("C", (1, -6, 3), (0, 0, 0), clip_start=1.0)
    fam = Family([cam], 0)
    rng = np.random.default_rng(3)
    pts = cam.eye + rng.normal(size=(500, 3)) * 0.3 + cam.forward * rng.uniform(1.5, 9, (500, 1))
    u, v, tau = fam.start(pts)
    u, v, tau, err, tangent = fam.invert(pts, u, v, tau)
    expected = (pts - cam.eye) / np.linalg.norm(pts - cam.eye, axis=-1, keepdims=True)
    got = tangent / np.linalg.norm(tangent, axis=-1, keepdims=True)
    np.testing.assert_allclose(got, expected, atol=1e-10)
    assert err.max() < 1e-9


def test_inverting_the_guide_family_recovers_pixel_and_tangent():
    (c1, c2), _ = zoom_rig(64, 48)
    fam = Family([c1, c2], 1)
    rng = np.random.default_rng(4)
    u, v, tau = rng.uniform(0, 64, 300), rng.uniform(0, 48, 300), rng.uniform(0.02, 1.8, 300)
    pts, tangent = fam.evaluate(u, v, tau)
    # an independent finite-difference tangent of the curve
    ahead, _ = fam.evaluate(u, v, tau + 1e-5)
    behind, _ = fam.evaluate(u, v, tau - 1e-5)
    fd = (ahead - behind) / 2e-5
    np.testing.assert_allclose(tangent, fd, atol=1e-5 * np.abs(tangent).max())
    got_u, got_v, got_tau, err, got_t = fam.invert(pts, u + 0.8, v - 0.6, tau + 0.01, iterations=12)
    np.testing.assert_allclose(got_u, u, atol=1e-6)
    np.testing.assert_allclose(got_v, v, atol=1e-6)
    np.testing.assert_allclose(got_tau, tau, atol=1e-8)


def field_for(rig):
    choice = choose_grid(rig, 0.5, 64**3)
    families = [Family(rig.cameras, i, rig.beta) for i in range(len(rig.cameras))]
    fill = fill_membership(rig, choice.grid, families)
    return choice.grid, fill, solve_membership(fill.values, fill.constrained).x


def test_fill_constrains_every_voxel_around_preserved_rays():
    cams, _ = zoom_rig(64, 48)
    masks = disk_masks(64, 48, 8, 24)
    rig = Rig(cams, masks)
    grid, fill, n = field_for(rig)
    tracer = FieldTracer(rig, grid, n)
    for i in range(2):
        iy, ix = np.nonzero(masks[i])
        keep = np.arange(0, len(ix), 7)
        verts = tracer.preserved_rays(i, ix[keep] + 0.5, iy[keep] + 0.5, grid.cell, 200)[1].vertices
        flat = verts.reshape(-1, 3).astype(np.float64)
        # every preserved ray is laid out, whatever N: the grid's first layer of voxels,
        # on camera 1's near plane, has corners in front of it that no camera claims
        cam1 = cams[0]
        past = (flat - cam1.eye) @ cam1.forward >= cam1.clip_start + 2 * grid.cell
        inside = grid.contains(flat) & past
        idx = grid.to_index(flat[inside])
        # all eight voxels around every other sample along a preserved ray hold camera i
        lo = np.floor(idx).astype(int)
        for corner in np.ndindex(2, 2, 2):
            c = np.minimum(lo + corner, np.array(grid.shape) - 1)
            assert (fill.values[c[:, 0], c[:, 1], c[:, 2]] == i + 1).all()
    assert fill.conflicts == 0


@pytest.mark.slow
def test_streamline_matches_a_tight_adaptive_integration():
    cams, masks = zoom_rig(64, 48)
    rig = Rig(cams, masks)
    grid, _fill, n = field_for(rig)
    tracer = FieldTracer(rig, grid, n)
    # transition pixels: between the two masks
    u0 = np.array([32 + 0.27 * 64 + 0.5])
    v0 = np.array([24.5])
    step = 0.5 * grid.cell
    traced = tracer.trace(u0, v0, step, 2000)
    for r in range(len(u0)):
        tracer.params = np.zeros((2, 1, 3))
        tracer.params[:, 0, 0], tracer.params[:, 0, 1] = u0[r], v0[r]

        def rhs(_s, x):
            y = tracer.velocity(x[None], np.array([0]))[0]
            return y / np.linalg.norm(y)

        count = int(traced.counts[r]) - 1
        s_end = step * (count - 1)
        ref = solve_ivp(
            rhs,
            (0, s_end),
            traced.vertices[r, 0].astype(np.float64),
            method="DOP853",
            rtol=1e-9,
            atol=1e-9,
            t_eval=step * np.arange(count),
            max_step=grid.cell,
        )
        got = traced.vertices[r, :count].astype(np.float64)
        err = np.linalg.norm(ref.y.T - got, axis=-1).max()
        # N is trilinear, so the field has kinks at cell faces and RK4 is not 4th order
        # there; 2% of a cell is ~0.02 of camera 1's pixels here
        assert err < 0.02 * grid.cell, err


@pytest.mark.slow
def test_zoom_rig_scalar_field_meets_the_accuracy_target():
    cams, masks = zoom_rig(240, 180)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", settings_for("STANDARD"))
    report = build_report(fld, "STANDARD")
    for cam in report["cameras"]:
        assert cam["pixels"] > 1000
        assert cam["preserved_px"]["p95"] <= 0.5, cam
        assert cam["angle_deg"]["p95"] < 0.05, cam
    # counted in sections, one quad folds at camera 2's mask edge (pixel (97, 33), just
    # before its near plane, where three of the four rays are interpolated on the
    # lattice: a corner triangle turns over by a quarter of its area), and since the step
    # shortens at camera 2's near plane (``field.NearPlaneStep``, gain 2.1 here) one
    # more among interpolated transition rays (pixel (83, 41)); none is the aim, not met
    # yet (the count at equal arc length saw none)
    assert report["folds"] <= 2
    assert report["stalled"] == 0
    assert report["solver"]["converged"] and report["solver"]["iterations"] < 30
    assert not any(np.isnan(fld.traced.vertices).ravel())


def test_straight_on_continues_each_rays_segment_past_its_last_vertex():
    verts = np.zeros((3, 6, 3), np.float32)
    verts[:, :, 2] = np.arange(6.0)
    verts[1, 3:, 0] = [5.0, -1.0, 7.0]  # run-on vertices out of step
    verts[2, 2:, 1] = [1.0, 3.0, 2.0, 9.0]
    out = verts.copy()
    traced.straight_on(out, np.array([5, 2, 2]))
    np.testing.assert_array_equal(out[0], verts[0])  # nothing past its last
    np.testing.assert_array_equal(out[1, :3], verts[1, :3])
    np.testing.assert_array_equal(out[1, 3:], [[0, 0, 3], [0, 0, 4], [0, 0, 5]])
    np.testing.assert_array_equal(out[2, 2:, 1], [1.0, 2.0, 3.0, 4.0])


def test_a_traced_fields_ray_does_not_depend_on_the_pixels_made_with_it():
    """Past the corners' traced vertices their run-ons (whose step follows the point)
    were mixed vertex by vertex up to the longest ray of the whole request, so a pixel's
    ray bent further out when it was made with others: camera 2's rays here strayed up
    to 0.045 px more among their mask's rays than alone; on the 25x rig at 240x135
    STANDARD, with fewer rays traced, pixel (74, 18) strayed 0.65 px among them, 0.12
    alone."""
    cams, masks = zoom1000_rig(120, 68)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", replace(settings_for("PREVIEW"), processes=1))
    assert fld.stats["levels"] > 1  # nested: the step changes with the cells
    iy, ix = np.nonzero(np.asarray(masks[1], dtype=bool))
    together = fld.rays(ix, iy).vertices
    err_together = along_ray(together, cams[1], ix + 0.5, iy + 0.5, cams[:1])[0]
    rng = np.random.default_rng(0)
    worst = 0.0
    for p in rng.choice(len(ix), 300, replace=False):
        alone = fld.rays(ix[p : p + 1], iy[p : p + 1]).vertices
        np.testing.assert_array_equal(together[p, : alone.shape[1]], alone[0])
        err = along_ray(alone, cams[1], ix[p : p + 1] + 0.5, iy[p : p + 1] + 0.5, cams[:1])[0]
        worst = max(worst, abs(err[0] - err_together[p]))
    assert worst <= 1e-3, worst


@pytest.mark.slow
@pytest.mark.parametrize("nested", [False, True])
def test_interpolated_rays_agree_with_directly_traced_ones(nested):
    cams, masks = zoom_rig(160, 120)
    rig = Rig(cams, masks)
    fld = prepare(rig, "SCALAR_FIELD", replace(settings_for("STANDARD"), nested=nested))
    rng = np.random.default_rng(5)
    ix, iy = rng.integers(0, 159, 300), rng.integers(0, 120, 300)
    got = fld.rays(ix, iy).vertices.astype(np.float64)
    tracer = fld.tracer()
    k = got.shape[1] - 1
    ref = tracer.trace(ix + 0.5, iy + 0.5, fld.step, k)
    right = tracer.trace(ix + 1.5, iy + 0.5, fld.step, k)
    n = min(got.shape[1], ref.vertices.shape[1], right.vertices.shape[1])
    a, b, g = (x[:, :n].astype(np.float64) for x in (ref.vertices, right.vertices, got))
    t = np.diff(a, axis=1, append=2 * a[:, -1:] - a[:, -2:-1])
    t /= np.linalg.norm(t, axis=-1, keepdims=True)

    def across(d):
        return np.linalg.norm(d - (d * t).sum(-1, keepdims=True) * t, axis=-1)

    # in pixels of the multiscale image: over the spacing of neighbouring rays, inside the grid
    px = across(g - a) / np.maximum(across(b - a), 1e-12)
    live = np.arange(n)[None] < np.minimum(ref.counts, right.counts)[:, None]
    worst = np.where(live, px, 0).max(axis=1)
    assert np.percentile(worst, 95) <= 0.5
    # the refinement estimates errors from second differences; across N's kinks at
    # voxel faces a few pixels exceed the target (measured 1.19 px at worst here)
    assert worst.max() <= 1.5


def test_consecutive_cameras_turned_over_90_degrees_are_refused():
    target = (0, 0, 0.5)
    c1 = camera("C1", orbit(target, 20, 0, 20), target, 64, 48, clip_start=8)
    c2 = camera("C2", orbit(target, 5, 100, 20), target, 64, 48, clip_start=2.5)
    msg = (
        f"Cameras 'C1' and 'C2' look {turn_deg(c1, c2):.0f} degrees apart; consecutive cameras "
        "must turn less than 90 degrees (add a camera between them to bend the rays in stages)"
    )
    for method in ("SCALAR_FIELD", "IMAGE_BLEND"):
        with pytest.raises(RigError) as info:
            prepare(Rig((c1, c2), disk_masks(64, 48, 10, 20)), method)
        assert str(info.value) == msg


def test_contradictory_masks_are_counted_and_reported():
    cams, _ = zoom_rig(64, 48)
    # a one-pixel gap between the masks: at this cell size the two tubes touch
    masks = disk_masks(64, 48, 10, 11)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", settings_for("PREVIEW"))
    assert fld.stats["conflicts"] > 0
    assert any("their masks contradict each other there" in w for w in fld.warnings)
    assert not np.isnan(fld.traced.vertices).any()


def test_family_jacobian_matches_central_differences():
    cams, _ = three_camera_rig(192, 108)
    rng = np.random.default_rng(0)
    for i in range(3):
        fam = Family(cams, i)
        u, v, tau = (
            rng.uniform(-20, 210, 300),
            rng.uniform(-20, 130, 300),
            rng.uniform(0, i + 0.9, 300),
        )
        _p, _t, ju, jv = fam.evaluate(u, v, tau, jacobian=True)
        h = 1e-4
        fu = (fam.evaluate(u + h, v, tau)[0] - fam.evaluate(u - h, v, tau)[0]) / (2 * h)
        fv = (fam.evaluate(u, v + h, tau)[0] - fam.evaluate(u, v - h, tau)[0]) / (2 * h)
        np.testing.assert_allclose(ju, fu, atol=1e-7 * np.abs(fu).max())
        np.testing.assert_allclose(jv, fv, atol=1e-7 * np.abs(fv).max())


@pytest.mark.parametrize("nested", [False, True])
def test_a_solve_that_does_not_converge_is_reported(monkeypatch, nested):
    import multiscale_camera.core.field.nested as nested_grids
    import multiscale_camera.core.methods.scalar_field as scalar_field
    from multiscale_camera.core.errors import SolverDidNotConverge

    def stalled(values, constrained, **_kw):
        result = solve_membership(values, constrained, max_iterations=1)
        return type(result)(result.x, False, 1, result.residuals)

    monkeypatch.setattr(scalar_field, "solve_membership", stalled)
    monkeypatch.setattr(nested_grids, "solve_membership", stalled)
    cams, masks = zoom_rig(64, 48)
    with pytest.raises(SolverDidNotConverge) as info:
        prepare(Rig(cams, masks), "SCALAR_FIELD", replace(settings_for("PREVIEW"), nested=nested))
    assert str(info.value).startswith("The membership solve stopped at relative residual ")
    assert str(info.value).endswith("after 1 iterations; simplify the masks or lower the quality")


def test_crossing_views_of_cameras_that_are_not_neighbours_are_named():
    from multiscale_camera.core.quality import conflict_messages

    overlaps = np.array([[0, 4, 9], [4, 0, 0], [9, 0, 0]])
    messages = conflict_messages(["A", "B", "C"], overlaps)
    assert messages == [
        "4 voxels lie on preserved rays of both 'A' and 'B': their masks contradict each other "
        "there and those voxels were left free (widen the gap between the two masks, or move a "
        "near plane)",
        "The preserved views of 'A' and 'C', which are not neighbours in the list, cross in 9 "
        "voxels: rays there cannot be coherent (move one of the cameras, or shrink its mask)",
    ]


def test_non_neighbouring_preserved_views_that_touch_are_detected_without_nan():
    cams, masks = three_camera_rig(96, 54)
    # no ring for camera 2, and camera 1 keeps everything outside a hole barely wider
    # than camera 3's disk: the preserved views of cameras 1 and 3 touch
    r = radius(96, 54) / 96
    masks = np.stack([r > 0.125, np.zeros_like(r, bool), r < 0.12])
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", settings_for("PREVIEW"))
    assert any("which are not neighbours in the list, cross in" in w for w in fld.warnings), (
        fld.warnings
    )
    assert not np.isnan(fld.traced.vertices).any()


def test_stale_warm_start_gives_no_nan_tangent():
    cams, masks = zoom_rig(64, 48)
    rig = Rig(cams, masks)
    grid, _fill, n = field_for(rig)
    tracer = FieldTracer(rig, grid, n)
    fam = tracer.families[1]
    rng = np.random.default_rng(7)
    u, v, tau = rng.uniform(0, 64, 200), rng.uniform(0, 48, 200), rng.uniform(0.1, 0.9, 200)
    points, tangent = fam.evaluate(u, v, tau)
    # warm starts far off: pixels thousands away, as a ray that wandered would leave them
    tracer.params = np.zeros((2, 200, 3))
    tracer.params[1, :, 0] = rng.uniform(-5000, 5000, 200)
    tracer.params[1, :, 1] = rng.uniform(-5000, 5000, 200)
    got = tracer._tangent(1, points, tracer.params, np.arange(200))
    assert np.isfinite(got).all()
    expected = tangent / np.linalg.norm(tangent, axis=-1, keepdims=True)
    solved = np.abs(got - expected).max(axis=1) < 1e-6
    assert solved.all() and tracer.missed == 0


def test_the_trace_step_follows_the_accuracy_target_and_the_image_width():
    from multiscale_camera.core.field import STEP_CELLS, STEP_WIDTH_GAIN, step_cells

    # calibrated at 1920 wide and 0.5 px
    assert step_cells(0.5, 1920) == pytest.approx(STEP_CELLS)
    # the trace's error in pixels grows as step**3 * width: the same error at 3840 wide
    assert step_cells(0.5, 3840) == pytest.approx(STEP_CELLS / 2 ** (1 / 3))
    assert step_cells(0.5, 960) == pytest.approx(STEP_CELLS * 2 ** (1 / 3))
    # smaller images lengthen it by at most STEP_WIDTH_GAIN (folds beyond 2 cells)
    assert step_cells(0.5, 480) == pytest.approx(STEP_CELLS * STEP_WIDTH_GAIN)
    assert step_cells(0.5, 64) == step_cells(0.5, 480)
    # and a looser target lengthens it as its cube root, within 0.5 .. 3 cells
    assert step_cells(0.25, 1920) == pytest.approx(STEP_CELLS / 2 ** (1 / 3))
    assert step_cells(4.0, 1920) == 3.0 and step_cells(0.01, 3840) == 0.5


def test_dilate_takes_every_voxel_within_one_step_on_each_axis():
    from multiscale_camera.core.field.fill import _dilate

    rng = np.random.default_rng(2)
    mask = rng.random((7, 6, 5)) < 0.05
    want = np.zeros_like(mask)
    for x, y, z in np.argwhere(mask):  # the 3x3x3 cube around each set voxel, by hand
        want[max(x - 1, 0) : x + 2, max(y - 1, 0) : y + 2, max(z - 1, 0) : z + 2] = True
    got = _dilate(mask)
    np.testing.assert_array_equal(got, want)
    assert mask.sum() and not got.all()  # neither empty nor everything
