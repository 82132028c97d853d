"""Streamlines kept without their padding (``PackedTraced``): the straight runs past
each ray's last traced vertex are laid out again when read, the same to the bit as the
tracer laid them out, whatever the trace's step."""

from dataclasses import replace

import numpy as np
import pytest

from fixtures.rigs import three_camera_rig
from multiscale_camera.core.field.plane_step import NearPlaneStep
from multiscale_camera.core.field.trace import (
    PackedTraced,
    Share,
    StopReason,
    Traced,
    merge,
    straight_tails,
)
from multiscale_camera.core.geometry import Rig
from multiscale_camera.core.methods import prepare, settings_for


@pytest.fixture(scope="module")
def field():
    cams, masks = three_camera_rig(96, 54)
    return prepare(Rig(cams, masks), "SCALAR_FIELD", replace(settings_for("PREVIEW"), processes=1))


def _steps(fld):
    """The three kinds of trace step: a length, a length that follows the point, and the
    near planes' bands around a length."""
    base = fld.step.base if isinstance(fld.step, NearPlaneStep) else fld.step
    h = float(base) / 3  # finer than PREVIEW's: longer rays, of more different lengths

    def varying(x):
        return h * (1.0 + 0.25 * np.tanh(x[:, 0]))

    # the rig's exact preserved rays give its trace bands at the near planes
    assert isinstance(fld.step, NearPlaneStep)
    return {"length": h, "callable": varying, "bands": NearPlaneStep(h, *fld.step.given)}


@pytest.mark.parametrize("kind", ["length", "callable", "bands"])
def test_packed_streamlines_lay_out_the_tracers_rays_bit_for_bit(field, kind):
    step = _steps(field)[kind]
    tracer = field.tracer()
    ys, xs = np.mgrid[0:54:5, 0:96:5]
    u, v = xs.ravel() + 0.5, ys.ravel() + 0.5
    traced = tracer._trace_here(u, v, step, 600)
    counts = traced.counts
    # rays of many lengths: most have runs to lay out
    assert (counts < traced.width - 5).mean() > 0.5
    packed = PackedTraced.pack(traced)
    laid = packed.laid(slice(None), step)
    np.testing.assert_array_equal(laid.vertices, traced.vertices)
    np.testing.assert_array_equal(laid.membership, traced.membership)
    np.testing.assert_array_equal(laid.counts, traced.counts)
    # any rows, in any order
    rows = np.array([len(u) - 1, 0, 7, 7, 3])
    np.testing.assert_array_equal(packed.laid(rows, step).vertices, traced.vertices[rows])
    # the vertices kept are the traced ones: what padding to the longest ray took is gone
    assert len(packed.head) == counts.sum()
    assert packed.head.nbytes < 0.9 * traced.vertices.nbytes


def test_a_ray_with_no_last_segment_is_kept_whole():
    """A ray of one vertex runs on along the direction it was seeded with, which the
    packed ray cannot know: it keeps its run as traced."""
    k = 6
    verts = np.zeros((2, k, 3), dtype=np.float32)
    verts[0, :, 2] = np.arange(k)  # traced 3 vertices, then run on one unit a step
    verts[1, :, 0] = np.arange(k) * 0.5  # one vertex, run on along +x
    traced = Traced(
        verts,
        np.ones((2, k), dtype=np.float32),
        np.array([3, 1], dtype=np.int32),
        np.array([StopReason.LEFT_GRID] * 2, dtype=np.int8),
        1.0,
    )
    packed = PackedTraced.pack(traced)
    np.testing.assert_array_equal(packed.stored, [3, k])
    np.testing.assert_array_equal(packed.laid(slice(None), 1.0).vertices, verts)
    with pytest.raises(ValueError, match="fallback direction"):
        straight_tails(verts[1:].astype(np.float64), np.array([1]), 1.0)


def test_a_share_reads_as_its_pieces_merged(field):
    """A worker's share (each camera's preserved rays as laid out, the streamlines
    packed) reads as ``merge`` lays its pieces out, bands and all."""
    tracer = field.tracer()
    ys, xs = np.mgrid[0:54:3, 0:96:3]
    ix, iy = xs.ravel(), ys.ravel()
    merged = tracer._pixels_here(ix, iy, field.step, 600)
    share = tracer._pixels_here(ix, iy, field.step, 600, packed=True)
    assert isinstance(share, Share) and len(share.pieces) > 1
    laid = share.laid(slice(None), field.step)
    for name in ("vertices", "membership", "counts", "reason", "bands"):
        np.testing.assert_array_equal(getattr(laid, name), getattr(merged, name))
    # a merge of shares, as the lattice's last, lays them out the same
    half = len(ix) // 2
    parts = [
        tracer._pixels_here(ix[:half], iy[:half], field.step, 600, packed=True),
        tracer._pixels_here(ix[half:], iy[half:], field.step, 600, packed=True),
    ]
    order = [np.arange(half), np.arange(half, len(ix))]
    again = merge(parts, order, len(ix), share.schedule, trace_step=field.step)
    alone = merge(
        [
            tracer._pixels_here(ix[:half], iy[:half], field.step, 600),
            tracer._pixels_here(ix[half:], iy[half:], field.step, 600),
        ],
        order,
        len(ix),
        share.schedule,
    )
    np.testing.assert_array_equal(again.vertices, alone.vertices)
    np.testing.assert_array_equal(again.membership, alone.membership)
