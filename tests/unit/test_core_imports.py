import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_core_imports_neither_bpy_nor_mathutils():
    code = (
        "import sys, pkgutil, importlib, multiscale_camera.core as core; "
        "[importlib.import_module(m.name) "
        "for m in pkgutil.walk_packages(core.__path__, 'multiscale_camera.core.')]; "
        "bad = sorted(m for m in sys.modules "
        "if m.split('.')[0] in ('bpy', 'mathutils', 'bmesh', 'gpu')); "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
