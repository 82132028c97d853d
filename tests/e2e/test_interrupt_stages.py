"""Ctrl-C (SIGINT) in `blender -b` stops every stage of a build and a render within 2 s
(docs/failures.md; the bound is 1 s on an idle machine, 2 s for a loaded one): the
signal is sent a quarter of a second into the stage named (``Diagnostics.stage``, or
the Cycles hand-off's march and tables), or as it starts for stages shorter than that,
and the time from the signal to the end of the call is measured in Blender's own
process. Nothing is written and no worker's shared memory is left. AUTO's IMAGE_BLEND
stages (the weight solve, the measure along the rays, the fold count) are signalled at
1920x1080, where they last long enough."""

import os
import subprocess

import pytest

from multiscale_camera.core.runtime.shared import PREFIX
from tests.conftest import REPO, blender_command

pytestmark = pytest.mark.e2e

SCRIPT = """
import os, signal, sys, threading, time
sys.path.insert(0, {repo!r})
import bpy
import multiscale_camera
multiscale_camera.register()
from contextlib import contextmanager
from fixtures.blender.output import say
from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.core import diagnostics
from multiscale_camera.render import cycles
bpy.ops.wm.read_homefile(use_empty=True)
scene = bpy.context.scene
two_camera_scene(scene, {width}, {height})
scene.multiscale.quality = "STANDARD"
scene.multiscale.method = {method!r}
scene.multiscale.shading = {shading!r}
scene.render.filepath = {out!r}
if {shading!r} == "CYCLES":
    scene.cycles.samples = 1024  # Cycles' own stage: about 100 s uncancelled
    scene.cycles.use_adaptive_sampling = False
sent = []
opened = []  # the stages open now, innermost last

def interrupt():
    sent.append(time.perf_counter())
    say("OPEN", ",".join(opened) or None)
    os.kill(os.getpid(), signal.SIGINT)

def arm(name):
    if not sent and name == {stage!r}:
        say("STAGE", name)
        if {delay} > 0:
            threading.Timer({delay}, interrupt).start()
        else:  # at once, from inside the stage: a stage too short for a timer
            interrupt()

stage = diagnostics.Diagnostics.stage

@contextmanager
def armed(self, name):
    opened.append(name)
    arm(name)
    try:
        with stage(self, name):
            yield self
    finally:
        opened.pop()

diagnostics.Diagnostics.stage = armed
for name in ("ray_tables", "write_tables", "_run_cycles"):
    def wrapped(*args, _name=name, _f=getattr(cycles, name), **kwargs):
        opened.append(_name)
        arm(_name)
        try:
            return _f(*args, **kwargs)
        finally:
            opened.pop()
    setattr(cycles, name, wrapped)
try:
    result = {call}
except RuntimeError as err:
    result = str(err).strip()
end = time.perf_counter()
if sent:
    say("SECONDS", end - sent[0])
say("RESULT", result)
"""

COMPUTE = "bpy.ops.multiscale.compute_field()"
RENDER = "bpy.ops.render.render(write_still=True)"
CANCELLED = "{'CANCELLED'}"
RENDER_CANCELLED = "Error: Multiscale: Render cancelled (Ctrl-C); nothing was written"


def interrupted_at(
    stage, call, tmp_path, method="SCALAR_FIELD", shading="SOLID", size=(320, 240), delay=0.25
):
    """Run ``call`` in `blender -b` and SIGINT it ``delay`` s into ``stage`` (0: at once,
    from inside the stage, for stages shorter than a timer's delay); (seconds from the
    signal to the call's end, what the call gave, the output). Fails when the signal
    was never sent or ``stage`` was no longer open (itself or around an inner stage)
    when it was."""
    out = tmp_path / "existing.png"
    out.write_bytes(b"the user's own image")
    code = SCRIPT.format(
        repo=str(REPO),
        out=str(out),
        call=call,
        stage=stage,
        method=method,
        shading=shading,
        width=size[0],
        height=size[1],
        delay=delay,
    )
    temp = tmp_path / "tmp"  # the hand-off's temporary folders go here
    temp.mkdir()
    env = {**os.environ, "MULTISCALE_CACHE_DIR": str(tmp_path / "cache"), "TMPDIR": str(temp)}
    proc = subprocess.Popen(
        [blender_command(), "-b", "--factory-startup", "--python-expr", code],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    output = proc.communicate(timeout=600)[0]
    assert f"STAGE {stage}" in output, output
    seconds = result = None
    open_at_signal = []
    for line in output.splitlines():
        if line.startswith("OPEN "):
            open_at_signal.append(line[len("OPEN ") :].strip().split(","))
        if line.startswith("SECONDS "):
            seconds = float(line.split()[1])
        if line.startswith("RESULT "):
            result = line[len("RESULT ") :].strip()
    assert open_at_signal, f"no SIGINT was sent: the call ended before the timer fired\n{output}"
    assert len(open_at_signal) == 1 and stage in open_at_signal[0], (
        f"SIGINT came with stages {open_at_signal[0]!r} open, not {stage!r}\n{output}"
    )
    assert seconds is not None, output
    assert out.read_bytes() == b"the user's own image"
    assert not [n for n in os.listdir("/dev/shm") if n.startswith(f"{PREFIX}{proc.pid}_")]
    assert not [n for n in os.listdir(temp) if n.startswith("multiscale-cycles-")]
    print(f"{stage}: {seconds:.2f} s from SIGINT to the end")
    return seconds, result, output


@pytest.mark.parametrize("stage", ["fill", "solve", "trace"])
def test_ctrl_c_stops_compute_field_in_each_stage_within_2_s(tmp_path, stage):
    seconds, result, output = interrupted_at(stage, COMPUTE, tmp_path)
    assert result == CANCELLED, output
    assert seconds < 2.0, output


def test_ctrl_c_stops_compute_field_in_the_tangents_within_2_s(tmp_path):
    # VECTOR_FIELD's tangents at 320x240 can take less than a quarter of a second
    seconds, result, output = interrupted_at(
        "tangents", COMPUTE, tmp_path, "VECTOR_FIELD", delay=0.0
    )
    assert result == CANCELLED, output
    assert seconds < 2.0, output


@pytest.mark.parametrize("stage", ["trace", "simplify", "render"])
def test_ctrl_c_stops_a_render_in_each_stage_within_2_s(tmp_path, stage):
    # simplification and the 320x240 tile loop can end within a quarter of a second
    delay = 0.25 if stage == "trace" else 0.0
    seconds, result, output = interrupted_at(stage, RENDER, tmp_path, delay=delay)
    assert result == RENDER_CANCELLED, output
    assert seconds < 2.0, output


@pytest.mark.parametrize("stage", ["ray_tables", "write_tables"])
def test_ctrl_c_stops_the_cycles_tables_within_2_s(tmp_path, stage):
    """The tables are made and written in a fraction of a second: the signal comes as
    each starts, before Cycles' own stage."""
    seconds, result, output = interrupted_at(stage, RENDER, tmp_path, shading="CYCLES", delay=0.0)
    assert result == RENDER_CANCELLED, output
    assert seconds < 2.0, output


def test_ctrl_c_stops_cycles_own_render_within_2_s(tmp_path):
    """A second into Cycles' own render (sampling: its sync takes a fraction of that),
    Ctrl-C reaches Blender's handler (emulated by tools/blender: it sets the break flag
    Cycles polls) and the render fails as in every other stage. It used to be heard
    when Cycles ended, 399 s after the signal at 4096 samples."""
    seconds, result, output = interrupted_at(
        "_run_cycles", RENDER, tmp_path, shading="CYCLES", delay=1.0
    )
    assert "Sent an internal break event" in output
    assert result == RENDER_CANCELLED, output
    assert seconds < 2.0, output


@pytest.mark.parametrize("stage,delay", [("solve", 0.25), ("measure", 0.0), ("folds", 1.0)])
def test_ctrl_c_stops_auto_in_image_blends_stages_within_2_s(tmp_path, stage, delay):
    """AUTO (the default) builds IMAGE_BLEND here and measures it: at 1920x1080 the
    weight solve takes about 2 s and the fold count several seconds (shared with
    workers here), which heard Ctrl-C only once they ended. The measure along the rays
    lasts a fraction of a second: the signal comes as it starts."""
    seconds, result, output = interrupted_at(
        stage, COMPUTE, tmp_path, "AUTO", size=(1920, 1080), delay=delay
    )
    assert result == CANCELLED, output
    assert seconds < 2.0, output


def test_ctrl_c_stops_a_render_in_image_blends_fold_count_within_2_s(tmp_path):
    seconds, result, output = interrupted_at(
        "folds", RENDER, tmp_path, "IMAGE_BLEND", size=(1920, 1080), delay=1.0
    )
    assert result == RENDER_CANCELLED, output
    assert seconds < 2.0, output
