"""The viewport preview's lines: which rays, how coloured, where folds are marked."""

from dataclasses import dataclass

import numpy as np

from fixtures.rigs import two_camera_rig
from multiscale_camera.core.geometry import RayBundle, Rig
from multiscale_camera.core.methods import RayField
from multiscale_camera.ui.preview_lines import PALETTE, camera_colour, frustum_lines, preview_lines


@dataclass
class StraightField(RayField):
    """Camera 1's straight rays, 5 vertices 1 unit apart; ``swap`` exchanges the rays of
    two pixel columns from vertex 3 on (they cross: a fold between them)."""

    swap: tuple = (-1, -1)

    def rays(self, ix, iy):
        ix, iy = np.asarray(ix), np.asarray(iy)
        cam = self.rig.cameras[0]
        a, b = self.swap
        sx = np.where(ix == a, b, np.where(ix == b, a, ix))
        d0 = cam.directions(ix + 0.5, iy + 0.5)
        d1 = cam.directions(sx + 0.5, iy + 0.5)
        p, p1 = cam.near_points(d0), cam.near_points(d1)
        k = np.arange(5)[None, :, None]
        verts = np.where(k <= 2, p[:, None] + d0[:, None] * k, p1[:, None] + d1[:, None] * k)
        n = len(ix)
        return RayBundle(
            verts.astype(np.float32),
            np.full((n, 5), 1.5, np.float32),
            np.stack([ix, iy], 1).astype(np.int32),
            np.zeros(n, np.float32),
            np.zeros(n, np.float32),
        )


def rig():
    cams, masks = two_camera_rig(40, 30)
    return Rig(cams, masks)


def test_colours_blend_the_cameras_by_membership():
    np.testing.assert_allclose(camera_colour([1.0, 2.0]), PALETTE[:2])
    np.testing.assert_allclose(camera_colour(1.5), 0.5 * (PALETTE[0] + PALETTE[1]), rtol=1e-6)


def test_frusta_eye_to_near_plane_and_chained():
    r = rig()
    pos, col = frustum_lines(r.cameras)
    assert pos.shape == (2 * (2 * 8 + 4), 3) and col.shape == (len(pos), 4)
    np.testing.assert_allclose(pos[0], r.cameras[0].eye, rtol=1e-6)
    # every near-plane corner lies on its camera's near plane
    for c, cam in enumerate(r.cameras):
        corners = pos[c * 16 + 1 : c * 16 + 16 : 4]
        depth = (corners - cam.eye) @ cam.forward
        np.testing.assert_allclose(depth, cam.clip_start, rtol=1e-5)


def test_rays_segments_and_fold_marks():
    r = rig()
    plain = preview_lines(StraightField(rig=r, method="TEST"), per_side=8)
    assert plain["count"] == 8 * 6 and len(plain["folds"]) == 0
    assert len(plain["rays"]) == 2 * 4 * plain["count"]  # 4 segments per ray
    np.testing.assert_allclose(
        plain["ray_colours"][:, :3],
        camera_colour(1.5)[None].repeat(len(plain["rays"]), 0),
        rtol=1e-6,
    )
    xs = np.unique(np.linspace(0, 39, 8).round().astype(int))
    pair = (int(xs[3]), int(xs[4]))
    folded = preview_lines(StraightField(rig=r, method="TEST", swap=pair), per_side=8)
    # swapping drawn columns xs[3] and xs[4] crosses their rays: the quads between them
    # fold in every row of quads, nowhere else
    assert len(folded["folds"]) == 6 - 1
    np.testing.assert_allclose(folded["folds"][:, 0].std(), 0.0, atol=0.5)
