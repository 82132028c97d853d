"""The `blender` command line the tests rely on: tools/blender (the emulator on the bpy
wheel), or a real Blender ($BLENDER). Tests of the tool, not of the extension."""

import json
import re
import struct
import textwrap

import pytest

pytestmark = pytest.mark.e2e


def png_size(path):
    """(width, height) from a PNG's IHDR chunk."""
    with open(path, "rb") as f:
        header = f.read(24)
    assert header[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    return struct.unpack(">II", header[16:24])


@pytest.fixture(scope="module")
def small_blend(tmp_path_factory, run_blender):
    """A saved factory scene: Workbench, 32x24 at 100 %, the cube renamed 'Marker'."""
    path = tmp_path_factory.mktemp("blend") / "small.blend"
    code = f"""
import bpy
scene = bpy.context.scene
scene.render.engine = "BLENDER_WORKBENCH"
scene.render.resolution_x, scene.render.resolution_y = 32, 24
scene.render.resolution_percentage = 100
scene.render.image_settings.file_format = "PNG"
bpy.data.objects["Cube"].name = "Marker"
bpy.ops.wm.save_as_mainfile(filepath={str(path)!r})
"""
    run_blender(["-b", "--factory-startup", "--python-exit-code", "1", "--python-expr", code])
    return path


def test_version(run_blender):
    proc = run_blender(["--version"])
    assert re.match(r"Blender \d+\.\d+\.\d+", proc.stdout), proc.stdout


def test_python_expr_runs_in_factory_scene(run_blender):
    code = "import bpy; print('OBJECTS', sorted(o.name for o in bpy.data.objects))"
    proc = run_blender(["-b", "--factory-startup", "--python-expr", code])
    assert "OBJECTS ['Camera', 'Cube', 'Light']" in proc.stdout


def test_python_file_sees_args_after_double_dash(run_blender, tmp_path):
    script = tmp_path / "script.py"
    report = tmp_path / "report.json"
    script.write_text(
        textwrap.dedent(f"""
        import json, sys
        argv = sys.argv[sys.argv.index("--") + 1:]
        with open({str(report)!r}, "w") as f:
            json.dump({{"name": __name__, "file": __file__, "argv": argv,
                       "full": sys.argv}}, f)
    """)
    )
    run_blender(["-b", "--factory-startup", "--python", script, "--", "a", "--b", "-f", "7"])
    data = json.loads(report.read_text())
    assert data["name"] == "__main__"
    assert data["file"] == str(script)
    assert data["argv"] == ["a", "--b", "-f", "7"]
    assert data["full"][1:5] == ["-b", "--factory-startup", "--python", str(script)]


def test_exception_continues_without_exit_code(run_blender):
    proc = run_blender(
        [
            "-b",
            "--factory-startup",
            "--python-expr",
            "raise RuntimeError('boom')",
            "--python-expr",
            "print('still running')",
        ]
    )
    assert "RuntimeError: boom" in proc.stderr
    assert "still running" in proc.stdout


def test_exit_code_propagates(run_blender, tmp_path):
    script = tmp_path / "fail.py"
    script.write_text("raise ValueError('bad input')\n")
    proc = run_blender(
        [
            "-b",
            "--factory-startup",
            "--python-exit-code",
            "1",
            "--python",
            script,
            "--python-expr",
            "print('not reached')",
        ],
        check=False,
    )
    assert proc.returncode == 1
    assert "ValueError: bad input" in proc.stderr
    assert "not reached" not in proc.stdout


def test_sys_exit_sets_exit_code(run_blender):
    proc = run_blender(
        ["-b", "--factory-startup", "--python-expr", "import sys; sys.exit(4)"], check=False
    )
    assert proc.returncode == 4


def test_opens_blend(run_blender, small_blend):
    code = "import bpy; print('FILE', bpy.data.filepath, 'Marker' in bpy.data.objects)"
    proc = run_blender(["-b", small_blend, "--python-exit-code", "1", "--python-expr", code])
    assert f"FILE {small_blend} True" in proc.stdout


def test_missing_blend_fails(run_blender, tmp_path):
    proc = run_blender(["-b", tmp_path / "missing.blend"], check=False)
    assert proc.returncode != 0


def test_addons_enables(run_blender):
    # Blender's --addons loads them without adding them to the preferences.
    code = "import addon_utils; assert addon_utils.check('node_wrangler')[1]; print('ENABLED')"
    proc = run_blender(
        [
            "-b",
            "--factory-startup",
            "--addons",
            "node_wrangler",
            "--python-exit-code",
            "1",
            "--python-expr",
            code,
        ]
    )
    assert "ENABLED" in proc.stdout


def test_render_frame_to_output(run_blender, small_blend, tmp_path):
    run_blender(["-b", small_blend, "-o", tmp_path / "frame_##", "-f", "3"])
    assert png_size(tmp_path / "frame_03.png") == (32, 24)


def test_render_output_relative_to_blend(run_blender, small_blend):
    out = small_blend.parent / "relative_0002.png"
    run_blender(["-b", small_blend, "-o", "//relative_", "-f", "2"])
    assert png_size(out) == (32, 24)
