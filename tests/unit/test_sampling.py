"""Ray sampling: polyline simplification against a brute-force distance check, sub-pixel
offsets against the Blackman-Harris filter, lattice gathering against the field's own
rays."""

import math
from dataclasses import replace

import numpy as np
import pytest

from fixtures.rigs import two_camera_rig, zoom1000_rig
from multiscale_camera.core import sampling
from multiscale_camera.core.geometry import Rig
from multiscale_camera.core.methods import Settings, prepare, settings_for
from multiscale_camera.core.runtime import runtime
from multiscale_camera.core.sampling import simplification


def point_to_polyline(points, chain):
    """(P,) distance of each point to a chain of vertices (M, 3), the slow obvious way."""
    out = []
    for p in points:
        best = math.inf
        for a, b in zip(chain[:-1], chain[1:]):
            ab = b - a
            t = 0.0 if not ab.any() else np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0)
            best = min(best, float(np.linalg.norm(p - (a + t * ab))))
        out.append(best)
    return np.array(out)


def bent_polyline(rng, k=120, step=0.05):
    """A ray at uniform arc length: straight, a bend of random length and turn, straight."""
    turn = np.zeros(k)
    b0, b1 = sorted(rng.integers(5, k - 5, size=2))
    turn[b0:b1] = rng.uniform(0.0, 1.2) / max(b1 - b0, 1) * rng.uniform(0.3, 1.7, b1 - b0)
    heading = np.cumsum(turn)
    d = np.stack([np.cos(heading), np.sin(heading), 0.1 * np.sin(3 * heading)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    v = np.concatenate([np.zeros((1, 3)), np.cumsum(d[:-1] * step, axis=0)])
    return v + rng.normal(size=3) * 3.0


def test_simplified_chords_stay_within_the_tolerance():
    rng = np.random.default_rng(4)
    verts = np.stack([bent_polyline(rng) for _ in range(40)])
    eyes, angles = np.array([[0.0, 0.0, 10.0]]), np.array([1e-3])
    tol_px = 0.5
    last = np.full(len(verts), verts.shape[1] - 1)
    keep = sampling.simplify(verts, last, eyes, angles, tol_px)
    kept_total = 0
    for v, kp in zip(verts, keep):
        idx = np.flatnonzero(kp)
        assert idx[0] == 0 and idx[-1] == len(v) - 1
        kept_total += len(idx)
        for a, b in zip(idx[:-1], idx[1:]):
            stretch = v[a : b + 1]
            allowed = tol_px * sampling.footprint(stretch, eyes, angles).min()
            dist = point_to_polyline(stretch, v[[a, b]])
            assert dist.max() <= allowed * (1 + 1e-6) + 1e-12
    # and it does simplify: far fewer than the 120 vertices per ray
    assert kept_total / len(verts) < 40


def test_straight_polyline_is_one_segment_and_bend_end_is_kept():
    step = 0.1
    k = 60
    straight = np.stack([np.arange(k) * step, np.zeros(k), np.zeros(k)], 1)
    bent = straight.copy()
    # a 0.3 rad bend over vertices 20..29, straight after
    heading = np.concatenate([np.zeros(20), np.full(10, 0.03), np.zeros(k - 30)]).cumsum()
    d = np.stack([np.cos(heading), np.sin(heading), np.zeros(k)], 1) * step
    bent = np.concatenate([np.zeros((1, 3)), np.cumsum(d[:-1], axis=0)])
    eyes, angles = np.array([[0.0, -50.0, 0.0]]), np.array([1e-3])
    keep = sampling.simplify(np.stack([straight, bent]), [k - 1, k - 1], eyes, angles, 0.25)
    assert np.flatnonzero(keep[0]).tolist() == [0, k - 1]
    kept = np.flatnonzero(keep[1])
    # vertex 29 turns last (the turn at vertex j is between segments j-1 and j)
    assert 29 in kept and kept[-2] == 29


def test_box_distance_relaxes_the_tolerance_only_far_from_geometry():
    rng = np.random.default_rng(1)
    verts = np.stack([bent_polyline(rng) for _ in range(30)])
    eyes, angles = np.array([[0.0, 0.0, 10.0]]), np.array([1e-3])
    last = np.full(len(verts), verts.shape[1] - 1)
    near = (verts.reshape(-1, 3).min(0), verts.reshape(-1, 3).max(0))
    far = (np.full(3, 100.0), np.full(3, 101.0))
    fine = sampling.simplify(verts, last, eyes, angles, 0.25, near).sum()
    coarse = sampling.simplify(verts, last, eyes, angles, 0.25, far).sum()
    assert fine == sampling.simplify(verts, last, eyes, angles, 0.25).sum()
    assert coarse < fine
    # a chord that may stray by half the distance to the box never reaches it
    keep = sampling.simplify(verts, last, eyes, angles, 0.25, far)
    for v, kp in zip(verts, keep):
        pts = v[kp]
        lo, hi = far
        t = np.linspace(0, 1, 50)[:, None, None]
        chords = pts[:-1][None] + t * (pts[1:] - pts[:-1])[None]
        assert (sampling.box_distance(chords, far) > 0).all()


def blackman_harris_cdf(x, width):
    """CDF of the Blackman-Harris window over [-width/2, width/2], integrated in closed
    form term by term."""
    u = np.clip(x / width + 0.5, 0.0, 1.0)
    coef = (0.35875, -0.48829, 0.14128, -0.01168)
    total = coef[0] * u
    for n, c in enumerate(coef[1:], start=1):
        total = total + c * np.sin(2 * math.pi * n * u) / (2 * math.pi * n)
    return total / coef[0]


def test_sample_offsets_follow_the_pixel_filter():
    ix = np.arange(4000) % 64
    iy = np.arange(4000) // 64
    off = sampling.sample_offsets(ix, iy, 16, filter_width=1.5, seed=3)
    assert off.shape == (4000, 16, 2)
    assert np.abs(off).max() <= 0.75 + 1e-12
    np.testing.assert_array_equal(off, sampling.sample_offsets(ix, iy, 16, 1.5, 3))
    assert not np.array_equal(off, sampling.sample_offsets(ix, iy, 16, 1.5, 4))
    for axis in range(2):
        x = np.sort(off[..., axis].ravel())
        empirical = np.arange(1, len(x) + 1) / len(x)
        assert np.abs(empirical - blackman_harris_cdf(x, 1.5)).max() < 0.01
    # stratified: each pixel's 16 samples cover the 4 x 4 strata of the unit square once
    u = np.stack([blackman_harris_cdf(off[..., a], 1.5) for a in range(2)], -1)
    cells = np.floor(u * 4).clip(0, 3)
    ids = np.sort(cells[..., 1] * 4 + cells[..., 0], axis=1)
    np.testing.assert_array_equal(ids, np.broadcast_to(np.arange(16), ids.shape))
    np.testing.assert_array_equal(sampling.sample_offsets(ix, iy, 1), 0.0)


@pytest.fixture(scope="module")
def traced_field():
    cams, masks = two_camera_rig(48, 36)
    return prepare(Rig(cams, masks), "SCALAR_FIELD", Settings(accuracy_px=1.0))


def segment_chains(seg, r):
    a, b = seg.offsets[r], seg.offsets[r + 1]
    end = seg.origin[b - 1] + seg.direction[b - 1] * seg.length[b - 1]
    return np.concatenate([seg.origin[a:b], end[None]])


def test_lattice_rays_stay_within_tolerance_of_the_fields_own_rays(traced_field):
    fld = traced_field
    w, h = fld.rig.size
    iy, ix = np.mgrid[0:h, 0:w]
    ix, iy = ix.ravel(), iy.ravel()
    sampler = sampling.RaySampler(fld, tol_px=0.25)
    assert sampler.lattice
    seg = sampler.segments(ix + 0.5, iy + 0.5)
    bundle = fld.rays(ix, iy)
    np.testing.assert_allclose(seg.start_depth, bundle.start_depth, rtol=1e-5)
    leave = np.clip(fld.exit_index(ix, iy), 0, bundle.vertices.shape[1] - 1)
    np.testing.assert_allclose(
        seg.membership, bundle.membership[np.arange(len(ix)), leave], atol=1e-5
    )
    rng = np.random.default_rng(0)
    worst = 0.0
    for r in rng.choice(len(ix), 150, replace=False):
        verts = bundle.vertices[r].astype(np.float64)
        chain = segment_chains(seg, r)
        allowed = 0.25 * sampling.footprint(verts, sampler.eyes, sampler.angles)
        dist = point_to_polyline(verts, chain)
        worst = max(worst, float((dist / allowed).max()))
    assert worst <= 2.0, f"a chord strays {worst:.2f} tolerances from the field's ray"
    assert len(seg.origin) / len(seg) < 20


def test_sub_pixel_rays_interpolate_the_neighbouring_pixels(traced_field):
    fld = traced_field
    sampler = sampling.RaySampler(fld, tol_px=0.25)
    generic = sampling.RaySampler.__new__(sampling.RaySampler)
    generic.__dict__.update(sampler.__dict__, lattice=False)
    # the midpoint between pixel centres (10, 7) and (11, 7)
    mid = sampler.segments(np.array([11.0]), np.array([7.5]))
    ref = generic.segments(np.array([11.0]), np.array([7.5]))
    rays = fld.rays(np.array([10, 11]), np.array([7, 7]))
    last = rays.vertices[:, -1].astype(np.float64).mean(0)
    for seg in (mid, ref):
        # the sample's last segment passes through the midpoint of the pixels' last vertices
        rel = last - seg.origin[-1]
        off = np.linalg.norm(rel - np.dot(rel, seg.direction[-1]) * seg.direction[-1])
        assert off < 0.05 * np.linalg.norm(rays.vertices[0, -1] - last)
        # both paths give the same ray beyond the bend
        np.testing.assert_allclose(seg.direction[-1], ref.direction[-1], atol=2e-3)


def test_lattice_simplification_hears_a_stop_request(traced_field):
    from multiscale_camera.core.errors import Cancelled

    calls = []

    def stop_on_third_call():
        calls.append(1)
        return len(calls) >= 3

    with pytest.raises(Cancelled):
        sampling.RaySampler(traced_field, 0.25, should_stop=stop_on_third_call)
    assert len(calls) == 3
    # the greedy pass over a 119-vertex lattice consults it every 16 vertices
    seen = []
    sampling.RaySampler(traced_field, 0.25, should_stop=lambda: seen.append(1) and False)
    assert len(seen) >= traced_field.traced.vertices.shape[1] // 16


def test_lattice_simplified_in_worker_processes_is_the_same(traced_field, monkeypatch):
    """The lattice's measures and leaf schedules, shared among worker processes that
    write into shared memory, equal those made in-process."""
    alone = sampling.RaySampler(traced_field, 0.25)
    monkeypatch.setattr(simplification, "CHUNK", 7)  # many chunks from a small lattice
    with runtime().journal() as runs:
        pooled = sampling.RaySampler(traced_field, 0.25, processes=2)
    # the measures and the leaf schedules, every chunk in a worker
    assert len(runs) == 2 and min(len(r.where) for r in runs) > 2
    assert all(r.in_workers == len(r.where) for r in runs)
    np.testing.assert_array_equal(pooled.leaf_keep, alone.leaf_keep)
    np.testing.assert_array_equal(pooled.slot_terms, alone.slot_terms)
    np.testing.assert_array_equal(pooled.slot_castable is None, alone.slot_castable is None)
    v = traced_field.traced.vertices
    eyes, angles = sampling.camera_footprints(traced_field.rig.cameras)
    one = sampling.polyline_measures(v, eyes, angles, 0.25)
    two = sampling.polyline_measures(v, eyes, angles, 0.25, processes=2)
    for a, b in zip(one, two, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.fixture(scope="module")
def blend_field():
    cams, masks = two_camera_rig(48, 36)
    return prepare(Rig(cams, masks), "IMAGE_BLEND", Settings())


def blended_ray(fld, sx, sy):
    """(K, 3) float64: the ray at continuous position (sx, sy), the slow way: the four
    pixel centres around it (the border squares extended), their rays blended
    bilinearly, vertex by vertex."""
    w, h = fld.rig.size
    x0 = min(max(math.floor(sx - 0.5), 0), w - 2)
    y0 = min(max(math.floor(sy - 0.5), 0), h - 2)
    fx, fy = sx - 0.5 - x0, sy - 0.5 - y0
    out = 0.0
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                        (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):  # fmt: skip
        ray = fld.rays(np.array([x0 + dx]), np.array([y0 + dy])).vertices[0]
        out = out + wgt * ray.astype(np.float64)
    return out


def test_image_blend_samples_between_pixels_gather_rays_simplified_once(blend_field):
    """IMAGE_BLEND has no traced lattice: every sample between pixel centres used to be
    blended from its four pixels' rays and simplified on its own (1.1 s of the live
    picture's 1.2 s render on the demo). With ``pixel_rays`` every pixel's ray is taken
    and simplified once, a schedule per square of four pixel centres, and a sample
    gathers its square's kept vertices: its chords stay within the tolerance of the
    blended ray, its start and membership are the blend's."""
    fld = blend_field
    w, h = fld.rig.size
    sampler = sampling.RaySampler(fld, 0.25, pixel_rays=True)
    generic = sampling.RaySampler(fld, 0.25)
    assert sampler.lattice and not generic.lattice
    assert isinstance(sampler.source, sampling.PixelRays)
    rng = np.random.default_rng(5)
    # anywhere between the pixel centres, on them, and in the half pixel at the borders
    sx = np.concatenate([rng.uniform(0.0, w, 300), np.arange(w) + 0.5, [0.0, w, 0.2]])
    sy = np.concatenate([rng.uniform(0.0, h, 300), np.full(w, 7.5), [0.0, h, h - 0.1]])
    seg = sampler.segments(sx, sy)
    ref = generic.segments(sx, sy)
    np.testing.assert_allclose(seg.start_depth, ref.start_depth, rtol=1e-12)
    np.testing.assert_allclose(seg.membership, ref.membership, atol=1e-6)
    worst = 0.0
    for r in range(len(sx)):
        verts = blended_ray(fld, sx[r], sy[r])
        allowed = 0.25 * sampling.footprint(verts, sampler.eyes, sampler.angles)
        dist = point_to_polyline(verts, segment_chains(seg, r))
        worst = max(worst, float((dist / allowed).max()))
    assert worst <= 1.0 + 1e-6, f"a chord strays {worst:.2f} tolerances from the blended ray"
    # simplified: fewer segments than the rays' K - 1 (4.2 of 9 here), and a square's
    # schedule, safe for all its rays, keeps few more than each sample's own (3.9)
    k = fld.rays(np.array([0]), np.array([0])).vertices.shape[1]
    per_ray = len(seg.origin) / len(seg)
    assert per_ray < 0.6 * (k - 1)
    assert per_ray <= 1.2 * len(ref.origin) / len(ref)
    # a pixel centre's ray is the pixel's own: its kept vertices lie on it exactly
    centre = np.arange(300, 300 + w)
    own = fld.rays(np.arange(w), np.full(w, 7)).vertices.astype(np.float64)
    for n, r in enumerate(centre):
        a, b = seg.offsets[r], seg.offsets[r + 1]
        gap = np.linalg.norm(seg.origin[a:b, None] - own[n][None], axis=-1).min(axis=1)
        assert gap.max() < 1e-9


def test_pixel_rays_leave_a_traced_field_its_own_lattice(traced_field, blend_field):
    assert not sampling.PixelRays.suits(traced_field)
    assert sampling.PixelRays.suits(blend_field)
    sampler = sampling.RaySampler(traced_field, 0.25, pixel_rays=True)
    assert sampler.source is traced_field


def test_a_rendered_ray_runs_on_as_the_fields_where_its_corners_traces_end_apart():
    """A leaf's schedule was made from its corners' own turns. Where one corner's trace
    ends at vertex 31 and another's at 100, the corners run on out of step between
    them (each straight), a ray blended from them bends there though no corner turns,
    and the schedule kept none of it: the rendered ray ran on along a chord, its last
    direction up to 4.2 degrees off the field's own ray (p99 0.9) on the nested 1000x
    rig at 120x68 PREVIEW. Every vertex of that stretch is now kept."""
    cams, masks = zoom1000_rig(120, 68)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", replace(settings_for("PREVIEW"), processes=1))
    rng = np.random.default_rng(1)
    ix, iy = rng.integers(0, 120, 1500), rng.integers(0, 68, 1500)
    rays = fld.rays(ix, iy).vertices.astype(np.float64)
    seg = sampling.RaySampler(fld, tol_px=1e-4).segments(ix + 0.5, iy + 0.5, clip=False)
    rendered = seg.direction[seg.offsets[1:] - 1]
    own = rays[:, -1] - rays[:, -2]
    own /= np.linalg.norm(own, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip((rendered * own).sum(axis=1), -1.0, 1.0)))
    assert angle.max() < 0.05, (angle.max(), ix[angle.argmax()], iy[angle.argmax()])
