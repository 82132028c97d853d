"""In-process bpy tests: the package is registered once, every test starts from an empty file."""

import bpy
import pytest

import multiscale_camera
from multiscale_camera.render import memory

# The free memory the memory guard's automatic budget sees in these tests: fixed, so no
# test depends on what the shared machine has free at the time (tests of the readers
# call them by name).
TEST_FREE_BYTES = 16 << 30


@pytest.fixture(scope="session", autouse=True)
def registered():
    multiscale_camera.register()
    yield
    multiscale_camera.unregister()


@pytest.fixture(autouse=True)
def fixed_free_memory(monkeypatch):
    monkeypatch.setattr(memory, "available_bytes", lambda platform=None: TEST_FREE_BYTES)


@pytest.fixture(autouse=True)
def empty_scene(registered):
    bpy.ops.wm.read_homefile(use_empty=True)
    yield bpy.context.scene
