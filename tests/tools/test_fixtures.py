"""The fixtures package: its numpy part runs without Blender."""

import subprocess
import sys

from tests.conftest import REPO


def test_numpy_part_imports_no_blender_module():
    code = (
        "import sys, fixtures.masks, fixtures.phantom, fixtures.rigs; "
        "bad = sorted(m for m in sys.modules "
        "if m.split('.')[0] in ('bpy', 'mathutils', 'bmesh', 'gpu')); "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
