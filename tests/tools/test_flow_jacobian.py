"""tools/flow_jacobian.py: the flow's Jacobian determinant along traced rays, against
rays written out here, and a fold-free SCALAR_FIELD whose flow keeps its orientation."""

import dataclasses

import numpy as np

import fixtures.rigs as rigs
from fixtures.tools import load_tool
from multiscale_camera.core.geometry import Family, Rig
from multiscale_camera.core.methods import prepare, settings_for
from multiscale_camera.core.methods.traced import preserved_labels
from multiscale_camera.core.quality.folds import quad_folds
from multiscale_camera.core.quality.report import fold_map

fj = load_tool("flow_jacobian")


def _line_focus(x, y, s, focus):
    """Rays P(x, y, s) = (x (1 - s / focus), y, s): they meet on the line x = 0 at
    s = focus, where D = (1 - s / focus) / |(-x / focus, 0, 1)| turns negative."""
    x, y = np.broadcast_to(x, s.shape), np.broadcast_to(y, s.shape)
    return np.stack([x * (1 - s / focus), y, s], axis=-1)[None]


def test_the_determinant_turns_over_where_rays_focus_on_a_line():
    focus, eps, x0, y0 = 2.0, 1e-3, 0.3, -0.1
    s = np.linspace(0.0, 4.0, 41)
    rays = [_line_focus(x0 + dx * eps, y0 + dy * eps, s, focus) for dx, dy in fj.OFFSETS[:5]]
    d = fj.flow_determinant(*rays, eps)[0]
    assert np.allclose(d, (1 - s / focus) / np.sqrt(1 + (x0 / focus) ** 2), atol=1e-9)
    flips, first = fj.sign_changes(d[None], np.ones((1, len(s)), dtype=bool))
    assert flips[0] and s[first[0]] == focus  # D is 0 there: no longer positive
    # checked only before the focus, it keeps its sign
    flips, _ = fj.sign_changes(d[None], (s < focus)[None])
    assert not flips[0]


def test_quad_kinds_split_the_counted_folds_by_the_pixels_they_touch():
    label = np.zeros((4, 5), dtype=int)
    label[0, 0] = 2
    folds = np.zeros((3, 4), dtype=bool)
    folds[0, 0] = folds[2, 3] = True
    kinds = fj.quad_kinds(folds, label)
    assert [int(k.sum()) for k in kinds.values()] == [1, 1, 10]
    assert kinds["folded, in transitions"][2, 3]
    assert kinds["folded, touching kept pixels"][0, 0]


def test_a_fold_free_scalar_field_keeps_its_flows_orientation():
    cams, masks = rigs.zoom_rig(64, 48)
    settings = dataclasses.replace(settings_for("PREVIEW"), processes=1)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", settings)
    folds, _stride = fold_map(fld, 1)
    assert not folds.any()
    quads = fj.quad_kinds(folds, preserved_labels(fld.rig))["not folded, in transitions"]
    r = fj.examine(fld, quads, 0.05, 7)
    assert r["sites"] > 40
    assert r["d_flips"] == 0 and r["tiny_folds"] == 0
    assert r["least_min"] > 0
    assert r["beyond"] == 0  # no tangent from a camera's guides beyond its near plane
    # camera 2's family keeps its orientation along every ray, its tau never runs back
    assert r["family_turns"] == [0, 0] and r["tau_back"] == [0, 0]


def test_orientation_is_the_sign_of_the_familys_jacobian_by_finite_differences():
    cams, _masks = rigs.turned_rig(64, 36)
    family = Family(cams, 2)
    rng = np.random.default_rng(5)
    n = 200
    u, v = rng.uniform(-64, 128, n), rng.uniform(-36, 72, n)
    tau = rng.uniform(0.02, 2.9, n)
    tau = tau[np.abs(tau - np.round(tau)) > 0.02]  # not across a stage's end
    u, v = u[: len(tau)], v[: len(tau)]
    h = 1e-5

    def point(du=0.0, dv=0.0, dt=0.0):
        return family.evaluate(u + du, v + dv, tau + dt)[0]

    cols = [(point(**{k: h}) - point(**{k: -h})) / (2 * h) for k in ("du", "dv", "dt")]
    det = np.einsum("ij,ij->i", cols[0], np.cross(cols[1], cols[2]))
    sure = np.abs(det) > 1e-6 * np.abs(det).max()
    assert sure.sum() > 0.9 * len(tau)
    np.testing.assert_array_equal(fj.orientation(family, u, v, tau)[sure], np.sign(det[sure]))


def test_family_sheets_flags_the_rays_along_which_a_family_turns_over(monkeypatch):
    cams, masks = rigs.zoom_rig(64, 48)
    settings = dataclasses.replace(settings_for("PREVIEW"), processes=1)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", settings)
    real = fj.orientation

    def turned_past_half(family, u, v, tau):  # camera 2's family mirrored from tau 0.5 on
        sign = real(family, u, v, tau)
        return np.where(tau > 0.5, -sign, sign).astype(np.int8)

    monkeypatch.setattr(fj, "orientation", turned_past_half)
    xs, ys = np.arange(0, 64, 8) + 0.5, np.full(8, 24.5)
    with fj.FamilySheets() as sheets:
        fld.tracer().trace(xs, ys, fld.step, 4000)
    assert sheets.both.shape == (2, 8)
    assert not sheets.both[0].any() and not sheets.back.any()
    # the rays camera 2's family was solved for both before and after tau 0.5: 5 of the
    # 8 (the other three, in camera 1's kept border, stay below tau 0.5 on it)
    assert sheets.both[1].sum() == 5


def test_turned_rigs_rays_take_camera_3s_guides_beyond_its_near_plane():
    # camera 3 turned 50 degrees from camera 2: rays of the 2-3 transition reach points
    # beyond its near plane before their tau reaches its last guide (docs/architecture.md)
    cams, masks = rigs.turned_rig(64, 36)
    settings = dataclasses.replace(settings_for("PREVIEW"), processes=1)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", settings)
    transition = preserved_labels(fld.rig) == 0
    ys, xs = np.nonzero(transition)
    with fj.GuidesBeyond() as guides:
        fld.tracer().trace(xs + 0.5, ys + 0.5, fld.step, 4000)
    assert len(guides.rays) == len(xs)
    assert 0.05 * len(xs) < guides.rays.sum() < len(xs)


def _quad_towards(corners_end, k=11):
    """Four straight rays from the unit square at z = 0 (a b c d: (0, 0), (1, 0), (1, 1),
    (0, 1)) to ``corners_end`` (4, 2) at z = 1: (4, k, 3) float64. Ray a runs along z,
    so the sections are the planes z = const."""
    start = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    z = np.linspace(0.0, 1.0, k)
    xy = start[:, None] + (np.asarray(corners_end)[:, None] - start[:, None]) * z[None, :, None]
    return np.concatenate([xy, np.broadcast_to(z[None, :, None], (4, k, 1))], axis=-1)


def test_a_quad_that_loses_its_convexity_turns_one_corner_and_a_crossing_two():
    # d ends inside the triangle a b c: a dart, no edge crosses another
    dart = _quad_towards([[0, 0], [2, 0], [2, 2], [1, 0.5]])
    # d ends beyond b c: edge d a crosses b c
    crossed = _quad_towards([[0, 0], [2, 0], [2, 2], [3, 1]])
    active = np.ones((4, 11), dtype=bool)
    assert fj.section_turns(dart, active).max() == 1
    assert fj.section_turns(crossed, active).max() == 2
    mirrored = _quad_towards([[0, 0], [-1, 0], [-1, 1], [0, 1]])
    assert fj.section_turns(mirrored, active).max() == 4
    for rays in (dart, crossed, mirrored):  # the counter flags a turned corner: all three
        lattice = rays[[0, 1, 3, 2]].reshape(2, 2, 11, 3)  # rows y, columns x
        assert quad_folds(lattice, np.ones((2, 2, 11), dtype=bool))[0, 0]
    assert fj.section_turns(_quad_towards([[0, 0], [2, 0], [2, 2], [0, 2]]), active).max() == 0


def test_the_quads_counted_where_masks_touch_only_lose_their_convexity():
    # the overlapping-masks rig at 192x108: the counter flags 3 quads on the seam, and in
    # each no section turns more than one corner triangle (docs/architecture.md)
    cams, masks = rigs.contradictory_rig(192, 108)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    folds, _stride = fold_map(fld, 1)
    turns = fj.corner_turns(fld, *np.nonzero(folds))
    assert folds.sum() >= 3 and (turns == 1).all(), turns
