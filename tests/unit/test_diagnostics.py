"""The job's Diagnostics: messages with levels, seconds per stage, cancel and progress."""

import time

import pytest

from multiscale_camera.core.diagnostics import Diagnostics, Level, diagnostics_of
from multiscale_camera.core.errors import Cancelled


def test_messages_keep_their_level_order_and_stage():
    diag = Diagnostics()
    diag.info("built from the cache")
    with diag.stage("fill"):
        diag.warn("two cameras claim 12 voxels")
    diag.say("no such camera", Level.ERROR)
    diag.warn("two cameras claim 12 voxels")  # said once only
    assert [(m.level, m.stage) for m in diag.messages] == [
        (Level.INFO, None),
        (Level.WARNING, "fill"),
        (Level.ERROR, None),
    ]
    assert diag.texts(Level.WARNING) == ["two cameras claim 12 voxels"]
    assert [m.text for m in diag.since(2)] == ["no such camera"]


def test_stage_seconds_add_up_over_runs():
    diag = Diagnostics()
    for _ in range(2):
        with diag.stage("solve"):
            time.sleep(0.02)
    assert 0.04 <= diag.seconds["solve"] < 0.5
    assert set(diag.seconds) == {"solve"}


def test_check_raises_cancelled_when_asked_to_stop():
    asked = []
    diag = Diagnostics(should_stop=lambda: bool(asked))
    diag.check()
    asked.append(True)
    with pytest.raises(Cancelled):
        diag.check()
    assert diag.checks == 2
    diagnostics_of(None).check()  # no steering: never stops


def test_progress_is_clipped_and_children_share_steering_not_messages():
    seen = []
    parent = Diagnostics(on_progress=seen.append)
    parent.progress(1.5)
    child = parent.child()
    child.progress(-1)
    child.warn("only the child's")
    with child.stage("trace"):
        pass
    assert seen == [1.0, 0.0]
    assert parent.messages == ()
    parent.merge(child)
    assert parent.texts() == ["only the child's"] and "trace" in parent.seconds


def test_running_seconds_count_the_stage_under_way():
    diag = Diagnostics()
    assert diag.running_seconds("render") == 0.0
    with diag.stage("render"):
        time.sleep(0.02)
        assert diag.running_seconds("render") >= 0.02 and "render" not in diag.seconds
    assert diag.running_seconds("render") == diag.seconds["render"]


def test_a_stage_run_inside_itself_counts_once():
    diag = Diagnostics()
    with diag.stage("field"):
        with diag.stage("field"):
            time.sleep(0.02)
        assert "field" not in diag.seconds
    assert 0.02 <= diag.seconds["field"] < 0.5
