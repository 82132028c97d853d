"""compute_field, the report and the field cache, driven headless."""

import json
import time

import bpy
import numpy as np
import pytest

from fixtures.blender.objects import mask_image
from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.core.runtime import pool
from multiscale_camera.render import pipeline


@pytest.mark.slow
def test_compute_field_writes_a_version_2_report(empty_scene):
    scene = empty_scene
    two_camera_scene(scene)
    pipeline.clear_fields()
    assert bpy.ops.multiscale.compute_field() == {"FINISHED"}
    report = json.loads(scene.multiscale.report)
    assert report["version"] == 2 and report["method"] == "SCALAR_FIELD"
    assert report["quality"] == "STANDARD" and report["cached"] is False
    assert set(report["seconds"]) >= {"fill", "solve", "tangents", "trace", "total"}
    assert [c["name"] for c in report["cameras"]] == ["C1", "C2"]
    for cam in report["cameras"]:
        assert cam["pixels"] > 0 and set(cam["preserved_px"]) == {"p50", "p95", "max"}
        # the first hit is a point of the measured stretch: never worse than its worst
        assert cam["surface_pixels"] > 0
        assert 0.0 <= cam["surface_px"]["max"] <= cam["preserved_px"]["max"] + 1e-9
    assert report["solver"]["converged"] and len(report["grids"]) == 1
    assert report["newton_lost"] == 0 and report["unfinished"] == 0


@pytest.mark.slow
def test_field_is_reused_until_the_rig_changes(empty_scene):
    scene = empty_scene
    two_camera_scene(scene)
    pipeline.clear_fields()
    first, built = pipeline.build_field(scene)
    assert built
    # lights and materials are not part of the field
    light = next(o for o in scene.objects if o.type == "LIGHT")
    light.rotation_euler.x += 0.3
    bpy.data.materials[0].diffuse_color = (1, 0, 0, 1)
    again, built = pipeline.build_field(scene)
    assert not built and again is first
    bpy.ops.multiscale.compute_field()
    assert json.loads(scene.multiscale.report)["cached"] is True
    # a new mask, a moved camera or another quality rebuild it
    scene.multiscale.cameras[1].mask = mask_image(
        "smaller", np.pad(np.ones((8, 8), bool), ((14, 14), (20, 20)))
    )
    assert pipeline.build_field(scene)[1]
    scene.multiscale.cameras[0].camera.location.z += 0.1
    bpy.context.view_layer.update()
    assert pipeline.build_field(scene)[1]
    scene.multiscale.quality = "PREVIEW"
    assert pipeline.build_field(scene)[1]


@pytest.mark.slow
def test_auto_is_the_default_method_and_the_report_says_what_it_built(empty_scene):
    """The method's default was SCALAR_FIELD, minutes at 1920x1080 where IMAGE_BLEND's
    rays meet the target in seconds; AUTO is the default (docs/report.md)."""
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.property_unset("method")
    assert scene.multiscale.method == "AUTO"
    pipeline.clear_fields()
    assert bpy.ops.multiscale.compute_field() == {"FINISHED"}
    report = json.loads(scene.multiscale.report)
    assert report["method"] == "IMAGE_BLEND" and report["folds"] == 0
    assert report["auto"].startswith("IMAGE_BLEND: the cheapest method whose rays meet")


def test_compute_field_says_when_its_workers_were_given_up(empty_scene, monkeypatch, capfd):
    """The field's trace, in workers that stalled, went on in Blender's process without a
    word; Compute Field now says why it was slow, and the field is the one traced by
    workers that did not stall."""
    from multiscale_camera.core.field import tracer as field_module

    from ..unit.runtime_tasks import InWorkers

    scene = empty_scene
    two_camera_scene(scene, 64, 48)
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 2
    monkeypatch.setattr(field_module, "MIN_RAYS_PER_PROCESS", 16)
    pipeline.clear_fields()
    pooled, _ = pipeline.build_field(scene)
    pipeline.clear_fields()
    monkeypatch.setattr(pool, "STALL_SECONDS", 0.5)
    # the trace's shares hang in the workers, without a beat (in Blender's process they run)
    monkeypatch.setattr(field_module, "_trace_share", InWorkers(field_module._trace_share, "hang"))
    start = time.perf_counter()
    assert bpy.ops.multiscale.compute_field() == {"FINISHED"}
    assert time.perf_counter() - start < 30.0
    assert pipeline.WORKERS_GIVEN_UP in capfd.readouterr().out
    rescued, built = pipeline.build_field(scene)
    assert not built
    np.testing.assert_array_equal(rescued.traced.vertices, pooled.traced.vertices)


def test_a_render_says_which_cameras_show_the_surface_off_their_view(empty_scene):
    from multiscale_camera.render.surface import surface_errors, surface_messages

    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.method = "IMAGE_BLEND"
    pipeline.clear_fields()
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    # IMAGE_BLEND's preserved rays are exact: nothing to say at the 0.5 px target
    assert not [n for n in frame.notices if "preserved pixels show the surface" in n]
    # at a target below float32 rounding both cameras are named, with their figures
    errors = surface_errors(frame.field, frame.tree)
    said = surface_messages(frame.field.rig.cameras, errors, 1e-12)
    assert [m.split(":")[0] for m in said] == ["Camera 'C1'", "Camera 'C2'"]
    assert all("over the 1e-12 px target of the quality" in m for m in said)
