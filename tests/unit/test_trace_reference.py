"""The trace's fast tangents (warm-started, predicted, one Newton step, continued before
the damped retry) against a slow reference: every tangent solved cold, to 1e-12 of the
near distance, with its root checked, and streamlines integrated by the same RK4 steps."""

from dataclasses import replace

import numpy as np
import pytest

import multiscale_camera.core.field.tracer as tracer_module
from fixtures.rigs import demo_rig, zoom1000_rig
from multiscale_camera.core.field import rk4_streamlines
from multiscale_camera.core.geometry import Family, Rig
from multiscale_camera.core.methods import prepare, settings_for


def cold_velocity(rig, n_of, scale_of, x):
    """Eq. 6 written out: w_i = max(0, 1 - |N - i|), each X_i from a cold solve (start
    from ``Family.start``, 40 iterations, tolerance 1e-12 of the local scale
    ``scale_of(x)``, the nested grids' scale field) whose root is checked."""
    nval = n_of(x)
    scale = scale_of(x)
    y = np.zeros_like(x)
    total = np.zeros(len(x))
    for i in range(len(rig.cameras)):
        w = np.maximum(0.0, 1.0 - np.abs(nval - (i + 1)))
        sel = np.flatnonzero(w > 0)
        if not len(sel):
            continue
        fam = Family(rig.cameras, i, rig.beta)
        pts = x[sel]
        u, v, tau = fam.start(pts)
        u, v, tau, tangent, lost = fam.solve(pts, u, v, tau, 40, scale[sel], tolerance=1e-12)
        assert lost == 0
        back, _ = fam.evaluate(u, v, tau)
        gap = np.linalg.norm(back - pts, axis=1) / scale[sel]
        assert (gap <= 1e-9).all(), (i, gap.max(), fam.scale, scale[sel].min())
        y[sel] += w[sel, None] * tangent
        total[sel] += w[sel]
    return y / total[:, None]


def pixel_gap(cams, width, height, a, b):
    """(R,) the largest distance between vertices a and b ((R, K, 3)) in the pixels of
    any camera that sees both (in front of its near plane, on its image)."""
    gap = np.zeros(a.shape[:2])
    for cam in cams:
        pa, da = cam.project(a)
        pb, db = cam.project(b)
        seen = (np.minimum(da, db) >= cam.clip_start) & (pa[..., 0] > 0) & (pa[..., 1] > 0)
        seen &= (pa[..., 0] < width) & (pa[..., 1] < height)
        d = np.linalg.norm(pa - pb, axis=-1)
        gap = np.where(seen, np.maximum(gap, d), gap)
    return gap.max(axis=1)


@pytest.mark.slow
def test_traced_transition_rays_follow_cold_newton_tangents_within_a_hundredth_px():
    width, height = 96, 54
    cams, masks = demo_rig(width, height)
    rig = Rig(cams, masks)
    fld = prepare(rig, "SCALAR_FIELD", replace(settings_for("PREVIEW"), processes=1))
    tracer = fld.tracer()
    # transition pixels: in no camera's mask, spread over the rings
    free = ~np.any(np.stack(masks), axis=0)
    iy, ix = np.nonzero(free[::2, ::2])
    pick = np.linspace(0, len(ix) - 1, 40).astype(int)
    u0, v0 = 2 * ix[pick] + 0.5, 2 * iy[pick] + 0.5
    steps = fld.traced.vertices.shape[1] - 1
    fast = tracer.trace(u0, v0, fld.step, steps)
    assert tracer.missed == 0
    seeds = cams[0].near_points(cams[0].directions(u0, v0))
    slow = rk4_streamlines(
        lambda x: cold_velocity(rig, tracer.n_of, fld.domain.scale, x),
        seeds,
        fld.step,
        steps,
        inside=tracer.contains,
        split=lambda x, d, _rows, h: tracer.near_plane_split(x, d, None, h),
    )
    assert (slow.counts == fast.counts).all()
    k = int(slow.counts.min())
    assert k > 20  # the rays run through the transitions, not out at once
    gap = pixel_gap(cams, width, height, fast.vertices[:, :k], slow.points[:, :k])
    assert gap.max() < 0.01, gap.max()


@pytest.mark.slow
def test_transition_rays_of_the_1000x_rig_match_fully_converged_newton(monkeypatch):
    """On the 1000x rig a cold start cannot always find camera 2's rays far off its
    image (what the warm starts are for), so the reference here is the same trace with
    Newton run to convergence at every evaluation (12 iterations, 1e-11 of the local
    scale): 60 transition rays spread over the image stay within 0.01 px of it in the
    pixels of every camera that sees them. The step shortens near the near planes as a
    function of where the ray is (``field.NearPlaneStep``), so a ray that leaves the
    grid right at its face may end a vertex sooner or later in one trace than in the
    other (one of the 60 here, 6.6e-4 world units apart there)."""
    width, height = 240, 135
    cams, masks = zoom1000_rig(width, height)
    rig = Rig(cams, masks)
    fld = prepare(rig, "SCALAR_FIELD", replace(settings_for("PREVIEW"), processes=1))
    free = ~np.any(np.stack(masks), axis=0)
    iy, ix = np.nonzero(free)
    pick = np.linspace(0, len(ix) - 1, 60).astype(int)
    u0, v0 = ix[pick] + 0.5, iy[pick] + 0.5
    steps = fld.traced.vertices.shape[1] - 1
    fast = fld.tracer().trace(u0, v0, fld.step, steps)
    monkeypatch.setattr(tracer_module, "PREDICTED_ITERATIONS", 12)
    monkeypatch.setattr(tracer_module, "WARM_ITERATIONS", 12)
    monkeypatch.setattr(tracer_module, "TRACE_NEWTON_TOLERANCE", 1e-11)
    converged = fld.tracer()
    ref = converged.trace(u0, v0, fld.step, steps)
    assert converged.missed == 0 and np.abs(ref.counts - fast.counts).max() <= 1
    assert (ref.counts == fast.counts).mean() >= 0.95
    k = int(np.minimum(ref.counts, fast.counts).min())
    gap = pixel_gap(cams, width, height, fast.vertices[:, :k], ref.vertices[:, :k])
    assert gap.max() < 0.01, gap.max()
