"""The Cycles hand-off from the installed extension (bl_ext.user_default.multiscale_camera)."""

import numpy as np
import pytest

from tests.exr import read_passes

from .test_install_extension import HEIGHT, SCENE, WIDTH

pytestmark = pytest.mark.e2e

HANDOFF = SCENE.replace(
    "bpy.ops.render.render(write_still=True)",
    """scene.multiscale.shading = "CYCLES"
scene.cycles.samples = 4
bpy.ops.render.render(write_still=True)
assert cam.data.type == "PERSP" and not dict(cam.data.cycles_custom), "camera changed"
""",
)


def test_installed_extension_hands_off_to_cycles(run_blender, linux_zip, tmp_path):
    assert HANDOFF != SCENE
    exr = tmp_path / "cycles.exr"
    code = HANDOFF.format(zip=str(linux_zip), exr=str(exr), w=WIDTH, h=HEIGHT)
    proc = run_blender(
        ["-b", "--factory-startup", "--python-exit-code", "1", "--python-expr", code],
        env={"BLENDER_USER_RESOURCES": str(tmp_path / "user")},
    )
    output = proc.stdout + proc.stderr
    assert "hand-off failed" not in output and "rendering with Solid shading" not in output
    passes = read_passes(exr)
    combined, index = passes["Combined"], passes["IndexOB"]
    assert combined.shape == (HEIGHT, WIDTH, 4)
    assert index[HEIGHT // 2, WIDTH // 2, 0] == 3 and index[0, 0, 0] == 0
    # the cube is lit by the sun through Cycles: not black, and not the world's grey
    centre = combined[HEIGHT // 2 - 2 : HEIGHT // 2 + 2, WIDTH // 2 - 2 : WIDTH // 2 + 2, :3]
    assert np.all(np.isfinite(combined)) and centre.mean() > 0
    assert not np.allclose(centre.mean(), combined[0, 0, :3].mean(), rtol=0.05)
