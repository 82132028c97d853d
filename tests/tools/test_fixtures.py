"""The fixtures package: its numpy part runs without Blender."""

from tests.conftest import blender_modules_after


def test_numpy_part_imports_no_blender_module():
    code, out = blender_modules_after("import fixtures.masks, fixtures.phantom, fixtures.rigs")
    assert code == 0, out
