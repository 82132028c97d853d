"""The cancel check (``Diagnostics.should_stop``) reaches the stages of AUTO's default
build: IMAGE_BLEND's harmonic weight solve, the preserved error along the rays, the fold
count in this process, and AUTO between its candidates. At 1920x1080 the solve took
about 2 s and the fold count 12 s in one process, deaf to Esc and Ctrl-C until they
ended. A stop asked a quarter of a second into each stage ends it within 2 s (the bound
of tests/e2e/test_interrupt_stages.py; the stages ask at most about 0.4 s apart)."""

import time

import numpy as np
import pytest

from fixtures.rigs import demo_rig, zoom_rig
from multiscale_camera.core.diagnostics import Diagnostics
from multiscale_camera.core.errors import Cancelled
from multiscale_camera.core.field import mask_weights
from multiscale_camera.core.geometry import Rig
from multiscale_camera.core.methods import prepare, settings_for
from multiscale_camera.core.methods.image_blend import prepare_image_blend
from multiscale_camera.core.quality import along_ray, fold_map
from multiscale_camera.core.quality.report import measure_cameras

BOUND = 2.0


class StopAfter:
    """A cancel check that says stop from ``delay`` s after the first time it is asked;
    ``asked`` counts the calls, ``stopped`` is when it first said stop."""

    def __init__(self, delay):
        self.delay = delay
        self.start = self.stopped = None
        self.asked = 0

    def __call__(self):
        now = time.perf_counter()
        self.asked += 1
        if self.start is None:
            self.start = now
        if now - self.start >= self.delay:
            if self.stopped is None:
                self.stopped = self.start + self.delay
            return True
        return False


def seconds_to_cancel(call, stop):
    """Run ``call``; the seconds from when ``stop`` began to say stop to ``Cancelled``.
    Fails when the call ended without being cancelled (the stage was too short)."""
    with pytest.raises(Cancelled):
        call()
    assert stop.stopped is not None
    return time.perf_counter() - stop.stopped


@pytest.fixture(scope="module")
def rig_1080():
    cams, masks = demo_rig(1920, 1080)
    return Rig(cams, masks)


@pytest.fixture(scope="module")
def blend_1080(rig_1080):
    return prepare_image_blend(rig_1080, settings_for("STANDARD"))


def test_the_weight_solve_stops_within_2_s_of_a_stop_asked_in_it(rig_1080):
    stop = StopAfter(0.25)
    seconds = seconds_to_cancel(lambda: mask_weights(rig_1080.masks, should_stop=stop), stop)
    assert seconds < BOUND
    assert stop.asked >= 3  # the coarse start, the hierarchy, the iterations


def test_the_weight_solve_asks_before_each_iteration():
    cams, masks = demo_rig(320, 180)
    asked = []
    done = mask_weights(masks, should_stop=lambda: asked.append(1) and False)
    # two solves of three cameras, each its coarse start (one ask before the cycles and
    # one per iteration) and itself: at least its iterations and one more
    assert len(asked) >= done.iterations + 1
    for n in sorted({1, len(asked) // 2, len(asked)}):
        calls = []
        with pytest.raises(Cancelled):
            mask_weights(masks, should_stop=lambda c=calls, n=n: c.append(1) or len(c) >= n)
        assert len(calls) == n  # stopped at the n-th ask, none after


def test_image_blend_hands_its_diagnostics_cancel_to_the_solve_and_times_it():
    cams, masks = zoom_rig(64, 48)
    diag = Diagnostics(should_stop=lambda: True)
    with pytest.raises(Cancelled):
        prepare_image_blend(Rig(cams, masks), settings_for("STANDARD"), diag)
    diag = Diagnostics()
    fld = prepare_image_blend(Rig(cams, masks), settings_for("STANDARD"), diag)
    assert diag.checks >= fld.solver["iterations"] and "solve" in diag.seconds


def test_the_measure_along_the_rays_stops_within_2_s(blend_1080):
    stop = StopAfter(0.05)  # the three cameras' measure takes about 0.4 s
    seconds = seconds_to_cancel(lambda: measure_cameras(blend_1080, stop), stop)
    assert seconds < BOUND


def test_along_ray_asks_before_each_block(monkeypatch):
    from multiscale_camera.core.quality import metrics

    monkeypatch.setattr(metrics, "ALONG_BLOCK_VERTICES", 4 * 3)  # 3 rays of 3 vertices
    cams, _masks = zoom_rig(64, 48)
    cam = cams[0]
    px, py = np.meshgrid(np.arange(4) + 0.5, np.arange(3) + 0.5)
    px, py = px.ravel(), py.ravel()
    d = cam.directions(px, py)
    rays = cam.eye + d[:, None] * np.array([1.0, 2.0, 3.0])[None, :, None]  # 12 rays
    asked = []
    with pytest.raises(Cancelled):
        along_ray(rays, cam, px, py, should_stop=lambda: asked.append(1) or len(asked) >= 3)
    assert len(asked) == 3  # blocks 1 and 2 measured, stopped before block 3 of 4
    err, _angle = along_ray(rays, cam, px, py, should_stop=lambda: False)
    np.testing.assert_allclose(err, 0.0, atol=1e-6)  # pinhole rays: exact


def test_the_fold_count_in_this_process_stops_within_2_s(blend_1080):
    stop = StopAfter(0.25)  # the whole count takes about 12 s in one process
    seconds = seconds_to_cancel(lambda: fold_map(blend_1080, 1, stop), stop)
    assert seconds < BOUND


def test_auto_stops_between_its_candidates(monkeypatch):
    """A stop asked once IMAGE_BLEND is measured and misses: SCALAR_FIELD is never
    started."""
    from multiscale_camera.core.methods import registry

    stopped = []

    def missing(fld, processes=1, diag=None):
        stopped.append(fld.method)  # asked to stop as the measure ends
        cam = {"name": "C", "pixels": 10, "preserved_px": {"p50": 9.0, "p95": 9.0, "max": 9.0}}
        return [cam], np.zeros((4, 4), dtype=bool), 1

    built = []  # the second candidate, started (an IMAGE_BLEND build stands for it)
    monkeypatch.setitem(
        registry.METHODS, "SCALAR_FIELD", lambda *a: built.append(1) or prepare_image_blend(*a)
    )
    monkeypatch.setattr(registry, "measure_map", missing)
    cams, masks = zoom_rig(32, 24)
    diag = Diagnostics(should_stop=lambda: bool(stopped))
    with pytest.raises(Cancelled):
        prepare(Rig(cams, masks), "AUTO", settings_for("STANDARD"), diag)
    assert stopped == ["IMAGE_BLEND"] and built == []
    prepare(Rig(cams, masks), "AUTO", settings_for("STANDARD"))  # no stop: it goes on
    assert built == [1]
