"""Build locks: one process builds a field that several need, over shared storage.

Render farms run many ``blender -b`` processes on many machines over one cache folder.
When two of them need the same field, the first to create ``<key>.lock`` (an exclusive
create, atomic on local disks and on NFS v3+/SMB) builds it; the others wait for the
field to appear in the cache. The holder writes who it is into the lock (host, process
id) and touches it every ``HEARTBEAT_SECONDS`` while it builds, so a lock whose holder
died is recognised and removed:

- at once, when the holder ran on this host and its process is gone;
- after ``STALE_SECONDS`` without a heartbeat otherwise (another host, or a holder that
  hangs): a killed worker blocks the others for at most that long, plus one poll.

Plain Python: no bpy, no numpy.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time

LOCK_SUFFIX = ".lock"
# The holder touches its lock this often, seconds.
HEARTBEAT_SECONDS = 4.0
# A lock untouched this long is stale (its holder died or hangs), seconds.
STALE_SECONDS = 20.0
# How often a waiting process looks again, seconds.
POLL_SECONDS = 0.5


def holder_id() -> dict:
    """Who this process is: {"host", "pid"}."""
    return {"host": socket.gethostname(), "pid": os.getpid()}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


class BuildLock:
    """The lock of one field, ``<folder>/<key>.lock``.

    Use ``acquire`` (non-blocking) and ``release``; while held, a daemon thread keeps
    the lock's modification time fresh (the heartbeat others judge it by).
    """

    def __init__(self, folder: str, key: str):
        self.path = os.path.join(folder, key + LOCK_SUFFIX)
        self._stop: threading.Event | None = None
        self._thread: threading.Thread | None = None

    def acquire(self) -> bool:
        """Take the lock if it is free (a stale one is removed first); False when a
        live holder has it. A folder where no lock can be written (read-only, gone)
        counts as free: nobody can share it, so this process builds on its own."""
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                if not self.stale():
                    return False
                self.break_stale()
                continue
            except OSError:
                return True
            with os.fdopen(fd, "w") as out:
                json.dump({**holder_id(), "started": time.time()}, out)
            self._start_heartbeat()
            return True
        return False

    def holder(self) -> dict | None:
        """What the lock file says of its holder, or None (no lock, or unreadable:
        being written)."""
        try:
            with open(self.path) as f:
                return json.load(f)
        except (OSError, ValueError):
            return None

    def stale(self, now: float | None = None) -> bool:
        """Whether the lock's holder is gone: a dead process on this host, or no
        heartbeat for ``STALE_SECONDS``. A lock that no longer exists is not stale."""
        try:
            touched = os.stat(self.path).st_mtime
        except FileNotFoundError:
            return False
        now = time.time() if now is None else now
        if now - touched > STALE_SECONDS:
            return True
        who = self.holder()
        if who and who.get("host") == socket.gethostname() and isinstance(who.get("pid"), int):
            return who["pid"] != os.getpid() and not _alive(who["pid"])
        return False

    def break_stale(self) -> None:
        """Remove a stale lock (another waiter may have removed it first)."""
        try:
            os.remove(self.path)
        except FileNotFoundError:
            pass

    def release(self) -> None:
        """Stop the heartbeat and remove the lock."""
        if self._stop is not None:
            self._stop.set()
            self._thread.join()
            self._stop = self._thread = None
        try:
            os.remove(self.path)
        except OSError:  # gone, or never written (an unusable folder)
            pass

    def _start_heartbeat(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._beat, args=(self._stop,), name="multiscale-lock", daemon=True
        )
        self._thread.start()

    def _beat(self, stop: threading.Event) -> None:
        while not stop.wait(HEARTBEAT_SECONDS):
            try:
                os.utime(self.path)
            except OSError:  # removed as stale by another process: nothing to keep fresh
                return
