"""The live picture headless: a stroke on a mask leads to a new picture, the picture is
what the render shows at PREVIEW, and a second stroke cancels the first one's job (no
two jobs at once). The timer is called here as Blender calls it (``LivePicture.tick``,
sleeping the interval it returns): background Blender runs no timers."""

import threading
import time

import bpy
import numpy as np
import pytest

from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.adapters.scene import rig_from_scene
from multiscale_camera.core.sampling import PixelRays
from multiscale_camera.render import pipeline
from multiscale_camera.render.fields import SERVICE
from multiscale_camera.render.live import LiveJob, live_size, small_rig
from multiscale_camera.ui import live_picture
from multiscale_camera.ui.live_picture import IMAGE_NAME, LivePicture


def pixels(image):
    """(h, w, 4) float32 of ``image``, row 0 at the top."""
    w, h = image.size
    buf = np.empty(w * h * 4, np.float32)
    image.pixels.foreach_get(buf)
    return buf.reshape(h, w, 4)[::-1]


def stroke(image, cx, cy, radius, value=1.0):
    """A disc of grey ``value`` (1: white) at pixel (cx, cy) (row 0 at the top) painted
    into ``image``."""
    w, h = image.size
    rgba = pixels(image).copy()
    yy, xx = np.mgrid[0:h, 0:w]
    rgba[(xx + 0.5 - cx) ** 2 + (yy + 0.5 - cy) ** 2 <= radius**2, :3] = value
    image.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())
    image.update()


def live_threads():
    return sum(t.name == "multiscale-live" and t.is_alive() for t in threading.enumerate())


def tick_until(live, done, timeout=120.0, seen=None):
    """Call the timer until ``done()``; ``seen`` collects the live threads alive at
    each call."""
    t0 = time.monotonic()
    while not done():
        assert not live.message, live.message
        assert time.monotonic() - t0 < timeout, "the live picture did not come"
        delay = live.tick()
        if seen is not None:
            seen.append(live_threads())
        time.sleep(delay)


def reference_picture(scene):
    """The Combined pass the render pipeline makes at PREVIEW, one ray per pixel (the
    live picture's settings at this small size: picture and field at the render's)."""
    scene.multiscale.quality = "PREVIEW"
    scene.multiscale.samples = 1
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    w, h = frame.size
    return pipeline.render_rows(frame, 0, h)["Combined"]


@pytest.fixture
def scene(empty_scene):
    two_camera_scene(empty_scene, 96, 72)
    return empty_scene


@pytest.fixture(autouse=True)
def fresh_live():
    """Each test starts with a live picture that has shown nothing and no cached field
    (the cache is the test session's own)."""
    SERVICE.clear()
    kept = SERVICE.live
    SERVICE.live = LivePicture()
    yield SERVICE.live
    SERVICE.live.stop()
    SERVICE.live = kept


def test_a_stroke_updates_the_live_picture(scene):
    live = SERVICE.live
    mask = scene.multiscale.cameras[1].mask
    tick_until(live, lambda: live.updates >= 1)
    before = pixels(bpy.data.images[IMAGE_NAME]).copy()
    assert before.shape == (72, 96, 4)
    np.testing.assert_allclose(before, reference_picture(scene), atol=1e-6)

    stroke(mask, 48, 36, 26)  # camera 2 keeps most of the gap
    tick_until(live, lambda: live.updates >= 2)
    after = pixels(bpy.data.images[IMAGE_NAME])
    assert (np.abs(after - before).max(axis=-1) > 0.05).sum() > 300
    np.testing.assert_allclose(after, reference_picture(scene), atol=1e-6)


def test_a_second_stroke_cancels_the_first_ones_job(scene):
    live = SERVICE.live
    mask = scene.multiscale.cameras[1].mask
    tick_until(live, lambda: live.updates >= 1)
    stroke(mask, 48, 36, 26)
    tick_until(live, lambda: live.job is not None)
    first = live.job
    stroke(mask, 48, 36, 20, 0.0)
    # the next look at the masks (within TICK_SECONDS: the looks between only ask
    # whether the job has ended) sees the change: the first job is told to stop
    tick_until(live, first.stopped)
    first.join(30)
    assert first.cancelled and first.rgba is None
    seen = []
    tick_until(live, lambda: live.updates >= 2, seen=seen)
    assert live.cancelled == 1
    assert max(seen) <= 1  # never two jobs at once
    np.testing.assert_allclose(
        pixels(bpy.data.images[IMAGE_NAME]), reference_picture(scene), atol=1e-6
    )


def test_the_job_starts_as_the_change_settles_not_a_look_later(scene):
    """After a change the timer used to come back a whole look (TICK_SECONDS) at a
    time, so a job started up to a look after the settling ended (0.2 s after the
    change, not 0.15 s); now it comes back when the settling ends."""
    live = SERVICE.live
    tick_until(live, lambda: live.updates >= 1)
    stroke(scene.multiscale.cameras[1].mask, 48, 36, 26)
    waits = [live.tick()]  # sees the change
    changed = live.changed
    while live.job is None:
        time.sleep(waits[-1])
        waits.append(live.tick())
    assert live.job.started == changed
    assert waits[0] == live_picture.TICK_SECONDS
    assert sum(waits[:-1]) <= live_picture.SETTLE_SECONDS + 1e-9


def test_a_finished_job_is_shown_within_a_poll_not_a_look(scene, monkeypatch):
    """While a job runs the timer asks every POLL_SECONDS whether it has ended (it used
    to ask every look, TICK_SECONDS, so a picture waited 50 ms on average after its
    job), and looks at the masks every TICK_SECONDS still."""
    live = SERVICE.live
    tick_until(live, lambda: live.updates >= 1)
    looks = []
    key_of = live.key_of
    monkeypatch.setattr(live, "key_of", lambda *a: looks.append(a[-1]) or key_of(*a))
    stroke(scene.multiscale.cameras[1].mask, 48, 36, 26)
    tick_until(live, lambda: live.job is not None)
    job, looks[:], waits = live.job, [], []
    t0 = time.perf_counter()
    while live.updates < 2:
        waits.append(live.tick())
        time.sleep(waits[-1])
    assert job.rgba is not None and not job.alive()
    assert set(waits[:-1]) == {live_picture.POLL_SECONDS}  # while the job ran
    assert waits[-1] == live_picture.TICK_SECONDS  # shown: no job, looks as before
    # the masks were looked at a look apart while it ran; the last look is the one
    # that showed the picture (no job any more)
    assert len(looks) >= 3 and looks[0] >= t0
    assert np.diff(looks[:-1]).min() >= live_picture.TICK_SECONDS - 1e-9


def test_the_picture_of_a_large_render_comes_from_a_smaller_field(scene):
    scene.render.resolution_x, scene.render.resolution_y = 1920, 1080
    depsgraph = bpy.context.evaluated_depsgraph_get()
    job = LiveJob.of(depsgraph.scene, depsgraph)
    assert job.size == (480, 270)
    assert job.field_size == (240, 135)
    assert job.request.quality == "PREVIEW"
    assert live_size(640, 360) == (480, 270)
    assert live_size(96, 72) == (96, 72)


def test_an_image_blend_picture_from_rays_simplified_once_is_the_same(scene, monkeypatch):
    """The picture samples its field between the field's pixels. An IMAGE_BLEND field
    has no traced lattice, and each sample used to be blended from its four pixels' rays
    and simplified on its own (most of the render's time on the demo); now every pixel's
    ray is simplified once (``core.sampling.PixelRays``). The picture stays the same
    within the simplification's tolerance (0.25 px): at most 1% of its pixels (an edge
    met by a chord a fraction of a pixel away) differ by more than 1/255."""
    scene.multiscale.method = "IMAGE_BLEND"
    depsgraph = bpy.context.evaluated_depsgraph_get()
    job = LiveJob.of(depsgraph.scene, depsgraph, max_width=96, field_width=48)
    assert (job.size, job.field_size) == ((96, 72), (48, 36))
    once = job.render()
    samplers = SERVICE.get(job.request).field.__dict__["_samplers"]
    assert [isinstance(s.source, PixelRays) and s.lattice for s in samplers.values()] == [True]
    one_by_one = pipeline.sampler_for
    monkeypatch.setattr(
        pipeline, "sampler_for", lambda *a, pixel_rays=False, **k: one_by_one(*a, **k)
    )
    each = LiveJob.of(depsgraph.scene, depsgraph, max_width=96, field_width=48).render()
    assert not any(s.lattice for s in samplers.values())
    diff = np.abs(once - each).max(axis=-1)
    print(f"differ by more than 1/255: {(diff > 1 / 255).sum()} of {diff.size} pixels")
    assert (diff > 1 / 255).mean() <= 0.01
    assert np.abs(once - each).mean() < 1e-3


def test_a_small_rig_keeps_each_cameras_pixels(scene):
    rig = rig_from_scene(scene)
    small = small_rig(rig, (48, 36))
    assert small.size == (48, 36)
    # nearest pixel: the small mask is the full one at the small pixels' centres
    ys = ((np.arange(36) + 0.5) * 2).astype(int)
    xs = ((np.arange(48) + 0.5) * 2).astype(int)
    np.testing.assert_array_equal(small.masks, rig.masks[:, ys][:, :, xs])
    # the frustum is kept: the corner rays point the same way
    for big, little in zip(rig.cameras, small.cameras):
        np.testing.assert_allclose(
            little.directions(np.array([0.0, 48.0]), np.array([0.0, 36.0])),
            big.directions(np.array([0.0, 96.0]), np.array([0.0, 72.0])),
            atol=1e-12,
        )


def test_the_toggle_stops_the_live_picture(scene):
    live = SERVICE.live
    scene.multiscale.live_picture = False
    for _ in range(5):
        live.tick()
        assert live.job is None
    assert IMAGE_NAME not in bpy.data.images


def test_a_new_file_forgets_the_picture_and_stops_the_job(scene):
    live = SERVICE.live
    tick_until(live, lambda: live.updates >= 1)
    mask = scene.multiscale.cameras[1].mask
    stroke(mask, 48, 36, 26)
    tick_until(live, lambda: live.job is not None)
    job = live.job
    bpy.ops.wm.read_homefile(use_empty=True)
    assert job.stopped()
    assert live.shown_key is None and live.display is None
    job.join(60)
    live.tick()  # the stopped job ends without a picture
    assert live.job is None and live.updates == 1


@pytest.mark.parametrize("turn", ["flip", "rotate 180"])
def test_a_flipped_or_turned_mask_changes_the_key(scene, turn):
    """A sum of the pixels ignores where they are: flipping or turning a mask left the
    key (and the picture) unchanged."""
    live = SERVICE.live
    mask = scene.multiscale.cameras[1].mask
    rgba = pixels(mask).copy()
    rgba[:, :30, :3] = 1.0  # a white band on the left: not symmetric
    mask.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())
    before = live.key_of(scene, set(), time.perf_counter())
    moved = rgba[:, ::-1] if turn == "flip" else rgba[::-1, ::-1]
    mask.pixels.foreach_set(np.ascontiguousarray(moved[::-1]).ravel())
    assert live.key_of(scene, set(), time.perf_counter()) != before


def test_stop_waits_for_the_job_thread(scene):
    """unregister stopped the job without waiting: a running job could start the worker
    processes again after the add-on had shut them down."""
    live = SERVICE.live
    stroke(scene.multiscale.cameras[1].mask, 48, 36, 26)
    tick_until(live, lambda: live.job is not None)
    job = live.job
    live.stop()
    assert job.stopped() and not job.alive()


def test_another_build_cancels_the_live_job_first(scene):
    """The live job builds through the field service from its own thread; a build of
    the render (or Compute Field, the viewport) started beside it ran two at once."""
    live = SERVICE.live
    tick_until(live, lambda: live.job is not None)
    job = live.job
    depsgraph = bpy.context.evaluated_depsgraph_get()
    SERVICE.get(SERVICE.request(depsgraph.scene, depsgraph=depsgraph))
    assert job.stopped()
    assert not job.alive()


def test_the_live_build_leaves_the_renders_frame_reuse_alone(scene):
    """A live build of a moving rig wrote SERVICE.reuse, throwing away what the
    render's frames had left for the next one."""
    cam = scene.multiscale.cameras[0].camera
    cam.keyframe_insert("location", frame=1)  # the rig is in motion: steady layout
    depsgraph = bpy.context.evaluated_depsgraph_get()
    assert SERVICE.request(depsgraph.scene, depsgraph=depsgraph).settings.steady
    job = LiveJob.of(depsgraph.scene, depsgraph)
    assert job.request.settings.steady is False
    kept = SERVICE.reuse
    job.launch().join(120)
    assert job.error is None and job.rgba is not None
    assert SERVICE.reuse is kept and not kept.claims


class AWindow:
    """The live picture's timer run as in a window that shows the images ``shown``."""

    def __init__(self, monkeypatch, shown):
        app = type("App", (), {})()
        app.background = False
        app.is_job_running = bpy.app.is_job_running
        fake = type("Bpy", (), {})()
        fake.app, fake.context, fake.data, fake.types = app, bpy.context, bpy.data, bpy.types
        monkeypatch.setattr(live_picture, "bpy", fake)
        monkeypatch.setattr(live_picture, "shown_images", lambda _wm: set(shown))


def test_masks_not_shown_are_read_one_per_look(scene, monkeypatch):
    """Every mask not shown was read in the same look every 2 s (tens of milliseconds
    each at 1920x1080), whatever READ_SHARE said."""
    live = SERVICE.live
    shown = scene.multiscale.cameras[1].mask.name
    first = scene.multiscale.cameras[0]
    first.mask = bpy.data.images.new("C1 mask", 96, 72)
    third = bpy.data.images.new("spare", 96, 72)
    scene.multiscale.cameras.add().camera = scene.multiscale.cameras[1].camera.copy()
    scene.collection.objects.link(scene.multiscale.cameras[2].camera)
    scene.multiscale.cameras[2].mask = third
    AWindow(monkeypatch, {shown})
    reads = []
    real = live_picture.pixel_checksum
    monkeypatch.setattr(
        live_picture,
        "pixel_checksum",
        lambda image, *rest: reads.append(image.name) or real(image, *rest),
    )
    now = 100.0
    live.key_of(scene, {shown}, now)  # the first look reads them all
    assert sorted(reads) == sorted([first.mask.name, shown, "spare"])
    for step in range(1, 30):
        reads.clear()
        live.key_of(scene, {shown}, now + 0.1 * step)
        assert len([r for r in reads if r != shown]) <= 1, (step, reads)
