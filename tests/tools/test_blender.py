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


def frame_files(folder, prefix):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(prefix))


def test_render_anim_renders_start_to_end(run_blender, small_blend, tmp_path):
    run_blender(["-b", small_blend, "-o", tmp_path / "anim_###", "-s", "2", "-e", "4", "-a"])
    assert frame_files(tmp_path, "anim_") == ["anim_002.png", "anim_003.png", "anim_004.png"]
    assert png_size(tmp_path / "anim_003.png") == (32, 24)


def test_frame_jump_renders_every_nth_frame(run_blender, small_blend, tmp_path):
    run_blender(["-b", small_blend, "-o", tmp_path / "f_", "-s", "1", "-e", "5", "-j", "2", "-a"])
    assert frame_files(tmp_path, "f_") == ["f_0001.png", "f_0003.png", "f_0005.png"]


def test_relative_start_and_end(run_blender, small_blend, tmp_path):
    # -e 4; -s +1: start 1 + 1 = 2; -e -1: end (4 - 1) - 1 + 1 = 3 (Blender's arithmetic)
    run_blender(
        ["-b", small_blend, "-o", tmp_path / "r_#", "-e", "4", "-s", "+1", "-e", "-1", "-a"]
    )
    assert frame_files(tmp_path, "r_") == ["r_2.png", "r_3.png"]


def test_start_after_end_renders_nothing(run_blender, small_blend, tmp_path):
    proc = run_blender(["-b", small_blend, "-o", tmp_path / "n_#", "-e", "3", "-s", "5", "-a"])
    assert frame_files(tmp_path, "n_") == [], proc.stdout


def test_range_flags_reset_by_the_next_blend(run_blender, small_blend, tmp_path):
    # -s and -e act on the scene loaded then: a file opened after them has its own range
    code = "import bpy; s = bpy.context.scene; print('RANGE', s.frame_start, s.frame_end)"
    proc = run_blender(["-b", small_blend, "-s", "5", "-e", "6", "--python-expr", code])
    assert "RANGE 5 6" in proc.stdout
    proc = run_blender(["-b", small_blend, "-s", "5", small_blend, "--python-expr", code])
    assert "RANGE 1 250" in proc.stdout


# Output > Overwrite off and Output > Placeholders, set before -a as a farm's job does.
FARM_OUTPUT = (
    "import bpy; r = bpy.context.scene.render; r.use_overwrite = False; r.use_placeholder = True"
)


def test_no_overwrite_skips_existing_frames(run_blender, small_blend, tmp_path):
    kept = tmp_path / "w_0002.png"
    kept.write_bytes(b"another worker's frame")
    run_blender(
        [
            "-b",
            small_blend,
            "--python-expr",
            FARM_OUTPUT,
            "-o",
            tmp_path / "w_####",
            "-s",
            "1",
            "-e",
            "3",
            "-a",
        ]
    )
    assert kept.read_bytes() == b"another worker's frame"
    assert png_size(tmp_path / "w_0001.png") == png_size(tmp_path / "w_0003.png") == (32, 24)


def test_placeholder_written_before_the_frame_renders(run_blender, small_blend, tmp_path):
    """Each frame's file exists, empty, when its render starts (render_pre runs after
    Blender touched it), so a second worker skips it."""
    watch = (
        "import bpy, os\n"
        "def pre(scene, *_):\n"
        "    path = bpy.path.abspath(scene.render.frame_path(frame=scene.frame_current))\n"
        "    print('PRE', scene.frame_current, os.path.exists(path) and os.path.getsize(path))\n"
        "bpy.app.handlers.render_pre.append(pre)\n"
    )
    proc = run_blender(
        [
            "-b",
            small_blend,
            "--python-expr",
            FARM_OUTPUT,
            "--python-expr",
            watch,
            "-o",
            tmp_path / "p_####",
            "-s",
            "1",
            "-e",
            "2",
            "-a",
        ]
    )
    said = [line for line in proc.stdout.splitlines() if line.startswith("PRE")]
    assert said == ["PRE 1 0", "PRE 2 0"], proc.stdout
    assert png_size(tmp_path / "p_0002.png") == (32, 24)


def test_bad_frame_number_is_reported(run_blender, small_blend, tmp_path):
    proc = run_blender(["-b", small_blend, "-s", "x", "-o", tmp_path / "b_#", "-f", "1"])
    assert "Error: not a number '-s / --frame-start x'." in proc.stderr
    assert frame_files(tmp_path, "b_") == ["b_1.png"]


def test_render_format_and_frame_chunks_as_flamenco_runs_them(run_blender, small_blend, tmp_path):
    """Flamenco's Simple Blender Render: --render-output, --render-format and a chunk
    of frames as --render-frame A..B."""
    run_blender(
        [
            "-b",
            small_blend,
            "--render-output",
            tmp_path / "c_####",
            "--render-format",
            "OPEN_EXR_MULTILAYER",
            "--render-frame",
            "2..3",
        ]
    )
    assert frame_files(tmp_path, "c_") == ["c_0002.exr", "c_0003.exr"]
    with open(tmp_path / "c_0002.exr", "rb") as f:
        assert f.read(4) == b"v/1\x01"  # OpenEXR's magic number


def test_unknown_render_format_is_reported(run_blender, small_blend, tmp_path):
    proc = run_blender(["-b", small_blend, "-F", "NOPE", "-o", tmp_path / "u_#", "-f", "1"])
    assert "Error: Format from '-F / --render-format' not known" in proc.stderr
    assert frame_files(tmp_path, "u_") == ["u_1.png"]
