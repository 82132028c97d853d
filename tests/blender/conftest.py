"""In-process bpy tests: the package is registered once, every test starts from an empty file."""

import bpy
import pytest

import multiscale_camera


@pytest.fixture(scope="session", autouse=True)
def registered():
    multiscale_camera.register()
    yield
    multiscale_camera.unregister()


@pytest.fixture(autouse=True)
def empty_scene(registered):
    bpy.ops.wm.read_homefile(use_empty=True)
    yield bpy.context.scene
