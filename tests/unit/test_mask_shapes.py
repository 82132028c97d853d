"""The numpy side of the mask tools: a silhouette's margin, soft shapes' bad input, and
the Image Editor overlay of every camera's mask with its bands and warnings."""

import numpy as np
import pytest

from multiscale_camera.ui.mask_shapes import (
    BAND_COLOUR,
    OVERLAP_COLOUR,
    TOUCH_COLOUR,
    WARNING_ALPHA,
    dilate,
    drag_box,
    mask_warnings,
    outline,
    overlay_rgba,
    soft_shape,
)
from multiscale_camera.ui.preview_lines import PALETTE


def brute_dilate(mask, margin):
    h, w = mask.shape
    out = np.zeros_like(mask)
    for y in range(h):
        for x in range(w):
            for v, u in zip(*np.nonzero(mask)):
                if (x - u) ** 2 + (y - v) ** 2 <= margin * margin:
                    out[y, x] = True
                    break
    return out


@pytest.mark.parametrize("margin", [0, 1, 1.5, 3])
def test_dilate_grows_by_a_disk_of_the_margin(margin):
    rng = np.random.default_rng(3)
    mask = rng.random((12, 15)) > 0.93
    np.testing.assert_array_equal(dilate(mask, margin), brute_dilate(mask, margin))


def test_soft_shape_names_the_shapes_it_knows():
    with pytest.raises(ValueError) as info:
        soft_shape("STAR", 4, 4, (2, 2), (2, 2))
    assert str(info.value) == "Unknown shape 'STAR': one of CIRCLE, ELLIPSE, ROUNDED_RECT"


def test_soft_shape_without_feather_is_hard_and_its_edge_is_half():
    hard = soft_shape("CIRCLE", 20, 20, (10, 10), (10, 10))
    assert set(np.unique(hard)) == {0.0, 1.0}
    # a feathered edge crosses 0.5 on the outline: the claimed pixels are the hard ones
    soft = soft_shape("CIRCLE", 20, 20, (10, 10), (10, 10), feather=6)
    np.testing.assert_array_equal(soft >= 0.5, hard == 1.0)


def three_masks():
    """Camera 1 on the left, camera 2 in the middle (a 1 px gap to camera 1, touching
    at row 0), camera 3 on the right overlapping camera 2 in column 7."""
    m = np.zeros((3, 4, 10), dtype=bool)
    m[0, :, 0:3] = True  # columns 0-2
    m[1, :, 4:8] = True  # columns 4-7 (column 3 is the band between 1 and 2)
    m[1, 0, 3] = True  # ... but row 0 touches camera 1
    m[2, :, 7:10] = True  # columns 7-9: overlaps camera 2 in column 7
    return list(m)


def test_mask_warnings_find_overlap_and_missing_gap():
    overlap, touch, messages = mask_warnings(three_masks())
    want_overlap = np.zeros((4, 10), bool)
    want_overlap[:, 7] = True
    np.testing.assert_array_equal(overlap, want_overlap)
    # cameras 1 and 2 touch at (row 0, col 3): camera 2's pixel there and its
    # 8-connected neighbours of camera 1 in column 2, rows 0-1; cameras 2 and 3 side by
    # side in columns 6 and 8
    assert touch[0, 3] and touch[0, 2] and touch[1, 2]
    assert not touch[2, 2] and not touch[0, 4] and not touch[:, 0:2].any()
    assert touch[:, 6].all() and touch[:, 8].all() and not touch[:, 7].any()
    assert messages == [
        "Masks overlap on 4 pixels (shown red)",
        "No gap between the masks of cameras 1-2, 2-3: leave a transition band between "
        "them (shown yellow)",
    ]


def test_overlay_colours_other_masks_bands_and_warnings():
    masks = three_masks()
    masks[1][0, 3] = False  # a clean gap between cameras 1 and 2
    rgba, messages = overlay_rgba(masks, shown=1, opacity=0.4)
    np.testing.assert_allclose(rgba[2, 1], (*PALETTE[0], 0.4))  # camera 1
    np.testing.assert_allclose(rgba[2, 9], (*PALETTE[2], 0.4))  # camera 3
    np.testing.assert_allclose(rgba[2, 3], (*BAND_COLOUR[:3], 0.4))  # the band
    np.testing.assert_allclose(rgba[2, 5], 0.0)  # camera 2, the one painted: clear
    np.testing.assert_allclose(rgba[2, 7], (*OVERLAP_COLOUR[:3], WARNING_ALPHA))
    np.testing.assert_allclose(rgba[2, 6], (*TOUCH_COLOUR[:3], WARNING_ALPHA))
    assert rgba.dtype == np.float32 and rgba.shape == (4, 10, 4)
    assert len(messages) == 2 and "cameras 2-3" in messages[1]


def test_overlay_frames_an_empty_last_mask():
    masks = [np.zeros((30, 40), bool) for _ in range(2)]
    masks[0][:, :10] = True
    rgba, messages = overlay_rgba(masks, shown=0)
    assert messages == ["The last camera's mask (camera 2) is empty"]
    red = np.all(np.isclose(rgba, (*OVERLAP_COLOUR[:3], WARNING_ALPHA)), axis=-1)
    assert red[0].all() and red[-1].all() and red[:, 0].all() and red[:, -1].all()
    assert not red[1:-1, 1:-1].any()


def test_drag_box_is_the_box_between_the_two_corners_either_way():
    for a, b in [((0.2, 0.7), (0.6, 0.5)), ((0.6, 0.5), (0.2, 0.7))]:
        centre, size = drag_box(a, b)
        np.testing.assert_allclose([*centre, *size], [0.4, 0.6, 0.4, 0.2])


@pytest.mark.parametrize("kind", ["CIRCLE", "ELLIPSE", "ROUNDED_RECT"])
def test_outline_lies_on_the_shape_it_previews(kind):
    pts = outline(kind, (10.0, 20.0), (50.0, 44.0), count=32)
    assert np.allclose(pts[0], pts[-1])  # closed
    x, y = pts[:, 0] - 30.0, pts[:, 1] - 32.0
    if kind == "CIRCLE":
        np.testing.assert_allclose(np.hypot(x, y), 12.0)
    elif kind == "ELLIPSE":
        np.testing.assert_allclose((x / 20.0) ** 2 + (y / 12.0) ** 2, 1.0)
    else:
        np.testing.assert_allclose(np.maximum(np.abs(x) / 20.0, np.abs(y) / 12.0), 1.0)
