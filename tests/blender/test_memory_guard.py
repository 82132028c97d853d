"""The memory guard in the scene: a build or render whose estimated peak passes the
budget (``scene.multiscale.memory_budget_mb``, or the free memory) is refused before it
starts, with the estimate, the budget and what to lower; the output file, the report's
place and the camera list are kept (docs/failures.md, "Memory")."""

import re

import bpy
import pytest

from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.io.cache import FieldCache
from multiscale_camera.render import fields, memory

KEEP = b"the user's own image"
REFUSED = re.compile(
    r"The field build would need about ([0-9.]+) GB of memory \(.*\), more than the budget "
    r"of 4\.0 GB \(the scene's Memory Budget\); nothing was started: lower the resolution "
    r"\(Output Properties > Format > Resolution, or its %\)"
)


@pytest.fixture
def scene(empty_scene, tmp_path, monkeypatch):
    monkeypatch.setattr(fields.SERVICE, "cache", FieldCache(str(tmp_path / "cache")))
    two_camera_scene(empty_scene)
    return empty_scene


@pytest.fixture
def never_built(monkeypatch):
    """Fail the test if a field build starts."""
    started = []

    def prepare(*_a, **_k):
        started.append(True)
        raise AssertionError("the build started")

    monkeypatch.setattr(fields, "prepare", prepare)
    return started


@pytest.mark.slow  # reading an 8000x8000 rig's masks takes seconds
def test_8000x8000_is_refused_before_the_build_starts_with_the_estimate(
    scene, tmp_path, never_built
):
    out = tmp_path / "existing.png"
    out.write_bytes(KEEP)
    scene.render.filepath = str(out)
    scene.render.resolution_x = scene.render.resolution_y = 8000
    scene.multiscale.memory_budget_mb = 4096
    scene.multiscale.report = '{"old": true}'
    names = [i.camera.name for i in scene.multiscale.cameras]
    with pytest.raises(RuntimeError) as info:
        bpy.ops.render.render(write_still=True)
    found = REFUSED.search(str(info.value))
    assert found and float(found.group(1)) > 4.0, str(info.value)
    assert "Error: Multiscale: The field build would need about" in str(info.value)
    assert out.read_bytes() == KEEP
    assert scene.multiscale.report == ""
    with pytest.raises(RuntimeError) as info:  # Compute Field says the same, builds nothing
        bpy.ops.multiscale.compute_field()
    assert REFUSED.search(str(info.value)), str(info.value)
    assert not never_built
    assert [i.camera.name for i in scene.multiscale.cameras] == names


def test_a_render_within_the_budget_goes_on(scene, tmp_path):
    scene.multiscale.method = "IMAGE_BLEND"
    scene.multiscale.memory_budget_mb = 4096
    scene.render.filepath = str(tmp_path / "out.png")
    bpy.ops.render.render(write_still=True)
    assert (tmp_path / "out.png").stat().st_size > 0


@pytest.mark.slow
def test_render_result_of_a_cached_field_is_guarded_too(scene, never_built, monkeypatch):
    """With the field cached, the render's own memory (the Render Result) is weighed."""
    monkeypatch.setattr(memory.SERVICE, "cached", lambda _request: object())
    scene.render.resolution_x = scene.render.resolution_y = 8000
    scene.multiscale.memory_budget_mb = 1024
    with pytest.raises(RuntimeError) as info:
        bpy.ops.render.render()
    # 8000 x 8000 pixels of 72 bytes (passes and copies) and a 64 MB tile in each worker
    assert (
        "Error: Multiscale: The render would need about 4.4 GB of memory (render result "
        "4.3 GB, workers: tile 128 MB), more than the budget of 1.0 GB" in str(info.value)
    )
    assert not never_built


def test_automatic_budget_is_the_free_memory_less_a_margin(scene, tmp_path):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal: 16000000 kB\nMemAvailable:  8388608 kB\n")
    assert memory.available_bytes(str(meminfo)) == 8 << 30
    budget, where = memory.budget_of(scene, available=8 << 30)
    assert budget == (8 << 30) - int(0.1 * (8 << 30))
    assert where == "free memory 8.0 GB less a margin of 819 MB"
    budget, where = memory.budget_of(scene, available=1 << 30)
    assert budget == (1 << 30) - (512 << 20)  # the fixed margin on a small machine
    scene.multiscale.memory_budget_mb = 300
    assert memory.budget_of(scene, available=8 << 30) == (300 << 20, "the scene's Memory Budget")
