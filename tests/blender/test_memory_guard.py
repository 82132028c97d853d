"""The memory guard in the scene: a build or render whose estimated peak passes the
budget (``scene.multiscale.memory_budget_mb``, or the free memory) is refused before it
starts, with the estimate, the budget and what to lower; the output file, the report's
place and the camera list are kept (docs/failures.md, "Memory")."""

import ctypes
import os
import re
import subprocess

import bpy
import pytest

from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.io.cache import FieldCache
from multiscale_camera.render import fields, memory

AVAILABLE_BYTES = memory.available_bytes  # the reader itself (conftest fixes what it says)

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
    # 8000 x 8000 pixels: 34 B/px in each of two workers, 52 B/px of shared passes, the
    # Render Result's 20 B/px (core/quality/memory.py, bench/render_memory.py)
    assert (
        "Error: Multiscale: The render would need about 9.9 GB of memory (workers: share "
        "of pixels 4.1 GB, shared passes 3.1 GB, render result 1.2 GB), more than the "
        "budget of 1.0 GB" in str(info.value)
    )
    assert not never_built


def test_automatic_budget_is_the_free_memory_less_a_margin(scene, tmp_path):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal: 16000000 kB\nMemAvailable:  8388608 kB\n")
    assert memory.linux_available(str(meminfo)) == 8 << 30
    budget, where = memory.budget_of(scene, available=8 << 30)
    assert budget == (8 << 30) - int(0.1 * (8 << 30))
    assert where == "free memory 8.0 GB less a margin of 819 MB"
    budget, where = memory.budget_of(scene, available=1 << 30)
    assert budget == (1 << 30) - (512 << 20)  # the fixed margin on a small machine
    scene.multiscale.memory_budget_mb = 300
    assert memory.budget_of(scene, available=8 << 30) == (300 << 20, "the scene's Memory Budget")


def test_automatic_budget_never_falls_under_256_mb_so_small_work_goes_on(scene, monkeypatch):
    """With under 512 MB free the margin took it all: a budget of 0 refused even a 64x48
    build. The automatic budget has a floor."""
    budget, where = memory.budget_of(scene, available=300 << 20)
    assert budget == memory.MIN_BUDGET_BYTES == 256 << 20
    assert where == "free memory 300 MB less a margin of 512 MB is under the least budget, 256 MB"
    monkeypatch.setattr(memory, "available_bytes", lambda platform=None: 300 << 20)
    scene.render.resolution_x, scene.render.resolution_y = 64, 48
    scene.multiscale.method = "IMAGE_BLEND"
    request = fields.SERVICE.request(scene)
    assert memory.guard_memory(scene, request, render=True) is None  # not refused


def test_guard_off_is_said_once_when_free_memory_cannot_be_read(scene, monkeypatch):
    """Where the free memory cannot be read and no Memory Budget is set, the guard let
    everything through without a word: now it says, once a session, that it is off."""
    monkeypatch.setattr(memory, "available_bytes", lambda platform=None: None)
    monkeypatch.setattr(memory, "_SAID_OFF", [])
    assert memory.budget_of(scene) == (None, "")
    request = fields.SERVICE.request(scene)
    assert memory.guard_memory(scene, request) == memory.GUARD_OFF
    assert memory.GUARD_OFF.startswith("The memory guard is off: this machine's free memory")
    assert "set a Memory Budget (Multiscale > Preview and Cache)" in memory.GUARD_OFF
    assert memory.guard_memory(scene, request) is None  # said once
    scene.multiscale.memory_budget_mb = 64  # a budget set: the guard is on again
    scene.render.resolution_x = scene.render.resolution_y = 4000
    with pytest.raises(memory.MemoryBudgetError):
        memory.guard_memory(scene, fields.SERVICE.request(scene))


def test_render_says_the_guard_is_off_where_the_user_looks(scene, monkeypatch, tmp_path, capfd):
    monkeypatch.setattr(memory, "available_bytes", lambda platform=None: None)
    monkeypatch.setattr(memory, "_SAID_OFF", [])
    scene.multiscale.method = "IMAGE_BLEND"
    scene.render.filepath = str(tmp_path / "out.png")
    bpy.ops.render.render(write_still=True)
    # the engine's warning (its report, printed headless)
    assert "Multiscale: " + memory.GUARD_OFF in capfd.readouterr().out
    assert (tmp_path / "out.png").stat().st_size > 0


class FakeKernel32:
    """Windows' kernel32 as far as ``GlobalMemoryStatusEx`` goes."""

    def __init__(self, avail, ok=1):
        self.avail, self.ok, self.lengths = avail, ok, []

    def GlobalMemoryStatusEx(self, status):  # noqa: N802 (Windows' name)
        self.lengths.append(status.contents.dwLength)
        status.contents.ullTotalPhys = 32 << 30
        status.contents.ullAvailPhys = self.avail
        return self.ok


def test_windows_reader_reads_avail_phys_of_global_memory_status_ex():
    """On Windows (no os.sysconf) the automatic budget was None: the guard was off."""
    assert ctypes.sizeof(memory.MEMORYSTATUSEX) == 64  # as sysinfoapi.h lays it out
    kernel = FakeKernel32(5 << 30)
    assert memory.windows_available(kernel) == 5 << 30
    assert kernel.lengths == [64]  # dwLength set before the call, as Windows asks
    assert memory.windows_available(FakeKernel32(5 << 30, ok=0)) is None  # the call failed
    assert memory.windows_available() is None  # here: no ctypes.windll


VM_STAT = """Mach Virtual Memory Statistics: (page size of 16384 bytes)
Pages free:                               12345.
Pages active:                            400000.
Pages inactive:                          300000.
Pages speculative:                         2000.
Pages throttled:                              0.
Pages wired down:                        150000.
Pages purgeable:                           5000.
"Translation faults":                 123456789.
Pages copy-on-write:                    1234567.
"""


def test_macos_reader_counts_free_and_inactive_pages_of_vm_stat():
    """On macOS (no SC_AVPHYS_PAGES) the automatic budget was None: the guard was off."""
    assert memory.parse_vm_stat(VM_STAT) == (12345 + 300000) * 16384
    intel = VM_STAT.replace("16384", "4096")
    assert memory.parse_vm_stat(intel) == (12345 + 300000) * 4096
    assert memory.parse_vm_stat("Pages free: 12.\n") is None  # no page size
    assert memory.parse_vm_stat(VM_STAT.replace("Pages inactive", "Pages gone")) is None

    def run(args, **_kw):
        assert args == ["vm_stat"]
        return subprocess.CompletedProcess(args, 0, stdout=VM_STAT)

    assert memory.macos_available(run) == (12345 + 300000) * 16384

    def missing(args, **_kw):
        raise FileNotFoundError(args[0])

    assert memory.macos_available(missing) is None


def test_free_memory_is_read_by_the_platform_s_reader(monkeypatch):
    monkeypatch.setattr(memory, "windows_available", lambda: 3 << 30)
    monkeypatch.setattr(memory, "macos_available", lambda: 2 << 30)
    monkeypatch.setattr(memory, "linux_available", lambda: 1 << 30)
    assert AVAILABLE_BYTES("win32") == 3 << 30
    assert AVAILABLE_BYTES("darwin") == 2 << 30
    assert AVAILABLE_BYTES("linux") == 1 << 30
    monkeypatch.setattr(memory, "linux_available", lambda: None)  # no /proc: the free pages
    assert AVAILABLE_BYTES("linux") == os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def test_auto_is_guarded_again_before_it_goes_on_to_scalar_field(scene, monkeypatch):
    """The guard weighs AUTO's first candidate (IMAGE_BLEND, built and measured) before
    the build; a build of AUTO asks it again, against the same budget, before it goes
    on to SCALAR_FIELD, and a refusal names that build and its estimate."""
    scene.multiscale.method = "AUTO"
    scene.render.resolution_x, scene.render.resolution_y = 480, 270
    request = fields.SERVICE.request(bpy.context.evaluated_depsgraph_get().scene)
    workers = memory.worker_count(request.settings.processes)
    first = memory.estimate_memory(request.rig, "AUTO", request.settings, workers)
    then = memory.estimate_memory(request.rig, "SCALAR_FIELD", request.settings, workers)
    assert first.total < then.total
    scene.multiscale.memory_budget_mb = int((first.total + then.total) / 2 / memory.MB)
    monkeypatch.setattr(memory.SERVICE, "cached", lambda _request: None)
    assert memory.guard_memory(scene, request) is None  # the first candidate fits
    memory.guard_candidate(request, "IMAGE_BLEND")  # fits too: nothing said
    with pytest.raises(memory.MemoryBudgetError) as info:
        memory.guard_candidate(request, "SCALAR_FIELD")
    assert str(info.value).startswith(
        f"AUTO's next candidate, the SCALAR_FIELD build, would need about "
        f"{memory.size_text(then.total)} of memory ("
    ), str(info.value)
    assert fields.SERVICE.candidate_guard is memory.guard_candidate
