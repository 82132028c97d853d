"""The core runs in plain Python: importing every module of it pulls in no Blender."""

from tests.conftest import blender_modules_after


def test_core_imports_neither_bpy_nor_mathutils():
    code, out = blender_modules_after(
        "import pkgutil, importlib, multiscale_camera.core as core; "
        "[importlib.import_module(m.name) "
        "for m in pkgutil.walk_packages(core.__path__, 'multiscale_camera.core.')]"
    )
    assert code == 0, out
