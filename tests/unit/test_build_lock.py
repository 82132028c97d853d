"""io.locks.BuildLock: one holder at a time, a dead holder's lock broken within 30 s."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from multiscale_camera.io import locks
from multiscale_camera.io.locks import BuildLock
from tests.conftest import REPO

# Most a killed worker may block the others, seconds.
BLOCK_LIMIT = 30.0


def foreign_lock(path, touched):
    """A lock file of a holder on another host, last touched at ``touched``."""
    path.write_text(json.dumps({"host": "another-host.invalid", "pid": 1, "started": touched}))
    os.utime(path, (touched, touched))


def test_one_holder_at_a_time(tmp_path):
    first, second = BuildLock(str(tmp_path), "k"), BuildLock(str(tmp_path), "k")
    assert first.acquire()
    assert not second.acquire()
    assert second.holder()["pid"] == os.getpid()
    first.release()
    assert not (tmp_path / "k.lock").exists()
    assert second.acquire()
    second.release()


def test_other_keys_do_not_block(tmp_path):
    one, other = BuildLock(str(tmp_path), "a"), BuildLock(str(tmp_path), "b")
    assert one.acquire() and other.acquire()
    one.release()
    other.release()


def test_a_lock_from_another_host_is_stale_only_without_heartbeat(tmp_path):
    now = time.time()
    foreign_lock(tmp_path / "k.lock", now - 1.0)
    lock = BuildLock(str(tmp_path), "k")
    assert not lock.stale(now) and not lock.acquire()
    assert lock.stale(now + locks.STALE_SECONDS)
    foreign_lock(tmp_path / "k.lock", now - locks.STALE_SECONDS - 0.5)
    assert lock.acquire()  # broken and taken
    assert lock.holder()["pid"] == os.getpid()
    lock.release()


def test_a_killed_holder_on_another_host_blocks_at_most_30_s():
    """The longest a waiter can be blocked: a lock touched just before its holder died
    is stale after STALE_SECONDS; the waiter notices within one poll."""
    assert locks.STALE_SECONDS + locks.POLL_SECONDS <= BLOCK_LIMIT
    # and a live holder's heartbeat keeps its lock from ever looking stale
    assert locks.HEARTBEAT_SECONDS * 2 < locks.STALE_SECONDS


def test_heartbeat_keeps_the_lock_fresh(tmp_path, monkeypatch):
    monkeypatch.setattr(locks, "HEARTBEAT_SECONDS", 0.05)
    lock = BuildLock(str(tmp_path), "k")
    assert lock.acquire()
    old = time.time() - 100
    os.utime(lock.path, (old, old))
    time.sleep(0.3)
    fresh = os.stat(lock.path).st_mtime
    lock.release()
    assert fresh > old + 99


HOLD_AND_WAIT = """
import sys, time
sys.path.insert(0, {repo!r})
from multiscale_camera.io.locks import BuildLock
assert BuildLock({folder!r}, "k").acquire()
print("HELD", flush=True)
time.sleep(600)
"""


def test_a_killed_holder_on_this_host_frees_the_lock_at_once(tmp_path):
    """A worker killed mid-build (SIGKILL: no clean-up) leaves its lock file behind;
    a process on the same host sees its holder is gone and takes it without waiting."""
    code = HOLD_AND_WAIT.format(repo=str(REPO), folder=str(tmp_path))
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "HELD"
        lock = BuildLock(str(tmp_path), "k")
        assert not lock.acquire()  # alive: held
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
        assert (tmp_path / "k.lock").exists()
        start = time.perf_counter()
        assert lock.acquire()
        assert time.perf_counter() - start < 1.0
        lock.release()
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


@pytest.mark.slow
def test_a_waiter_takes_a_dead_foreign_lock_within_30_s(tmp_path):
    """In real time: a lock whose holder on another host died just now."""
    foreign_lock(tmp_path / "k.lock", time.time())
    lock = BuildLock(str(tmp_path), "k")
    start = time.perf_counter()
    while not lock.acquire():
        time.sleep(locks.POLL_SECONDS)
        assert time.perf_counter() - start < BLOCK_LIMIT + 5, "still blocked"
    waited = time.perf_counter() - start
    lock.release()
    print(f"blocked {waited:.1f} s")
    assert locks.STALE_SECONDS - 1 <= waited <= BLOCK_LIMIT


def test_a_folder_without_room_for_locks_lets_the_process_build(tmp_path):
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("")
    lock = BuildLock(str(not_a_folder), "k")
    assert lock.acquire()
    lock.release()  # nothing to remove, no error
