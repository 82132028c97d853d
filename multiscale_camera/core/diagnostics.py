"""What one job (a field build, a frame, a render) has to say, and how it is steered.

A ``Diagnostics`` is made by whoever starts the work (an operator, the render engine,
the viewport) and handed down through every stage: the stages add messages with a
level, time themselves with ``stage``, ask ``check`` where they may stop, and report
``progress``. The caller reads it back: ``messages`` for the user, ``seconds`` for the
report. It replaces lists of notice strings carried on shared objects, ad-hoc timers and
``should_stop`` callables checked by hand.

A Diagnostics belongs to one job and one caller: a cached field is shared by many
callers, so nothing a caller says is written onto the field. ``child`` gives a stage
run elsewhere (a worker thread) its own messages and seconds with the same cancel check
and progress; ``merge`` brings them back.
"""

from __future__ import annotations

import ctypes
import enum
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable
from contextlib import contextmanager
from dataclasses import dataclass

from .errors import Cancelled


class Level(enum.IntEnum):
    """How much a message matters; the order is the severity."""

    INFO = 0
    WARNING = 1
    ERROR = 2


@dataclass(frozen=True)
class Message:
    """One thing said to the user: ``text`` at ``level``, from ``stage`` (or None)."""

    level: Level
    text: str
    stage: str | None = None


class Diagnostics:
    """Messages, seconds per stage, the cancel check and progress of one job.

    Parameters
    ----------
    should_stop : callable () -> bool, or None
        Asked by ``check``; True makes it raise ``Cancelled`` (Esc, a new stroke).
    on_progress : callable (float) -> None, or None
        Told the job's progress in [0, 1] by ``progress``.

    Attributes
    ----------
    seconds : dict of str to float
        Wall-clock seconds per stage name, summed over the stage's runs.
    checks : int
        How many times ``check`` was asked (a rough sign of life for a progress bar).
    guard : callable (str) -> None, or None
        Asked with a method's name before AUTO builds a further candidate than its
        first; it raises (a ``RigError``) to refuse that build (the memory guard,
        which estimates the first candidate before the build starts).
    """

    def __init__(
        self,
        should_stop: Callable[[], bool] | None = None,
        on_progress: Callable[[float], None] | None = None,
    ):
        self._should_stop = should_stop
        self._on_progress = on_progress
        self._messages: list[Message] = []
        self._stages: list[str] = []
        self._started: dict[str, float] = {}
        self.seconds: dict[str, float] = {}
        self.checks = 0
        self.guard: Callable[[str], None] | None = None

    # --- messages ------------------------------------------------------------------

    def say(self, text: str, level: Level = Level.WARNING) -> None:
        """Add ``text`` at ``level`` (WARNING by default), once: a text already said at
        that level is not repeated."""
        stage = self._stages[-1] if self._stages else None
        if any(m.text == text and m.level == level for m in self._messages):
            return
        self._messages.append(Message(Level(level), str(text), stage))

    def warn(self, text: str) -> None:
        self.say(text, Level.WARNING)

    def info(self, text: str) -> None:
        self.say(text, Level.INFO)

    def extend(self, texts: Iterable[str], level: Level = Level.WARNING) -> None:
        """``say`` each of ``texts``."""
        for text in texts:
            self.say(text, level)

    @property
    def messages(self) -> tuple[Message, ...]:
        """Every message, in the order said."""
        return tuple(self._messages)

    def texts(self, level: Level | None = None) -> list[str]:
        """The texts of the messages at ``level`` (all when None), in order."""
        return [m.text for m in self._messages if level is None or m.level == level]

    def since(self, count: int) -> tuple[Message, ...]:
        """The messages said after the first ``count`` (a caller that reports as the
        job goes keeps ``len(messages)`` and asks for what is new)."""
        return tuple(self._messages[count:])

    # --- time ----------------------------------------------------------------------

    @contextmanager
    def stage(self, name: str):
        """Time the block as stage ``name`` (seconds add up over repeated runs; a stage
        run inside itself counts once); messages said inside it name the stage."""
        if name in self._started:
            yield self
            return
        self._stages.append(name)
        start = self._started[name] = time.perf_counter()
        try:
            yield self
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start
            self._stages.pop()
            del self._started[name]

    def running_seconds(self, name: str) -> float:
        """Seconds of stage ``name`` so far, its current run included."""
        start = self._started.get(name)
        now = 0.0 if start is None else time.perf_counter() - start
        return self.seconds.get(name, 0.0) + now

    # --- steering ------------------------------------------------------------------

    def should_stop(self) -> bool:
        """Whether the job was asked to stop. The bound method is the cancel check that
        numeric kernels take as their ``should_stop`` callable."""
        self.checks += 1
        return bool(self._should_stop is not None and self._should_stop())

    def check(self) -> None:
        """Raise ``Cancelled`` when the job was asked to stop."""
        check_stop(self.should_stop)

    def progress(self, fraction: float) -> None:
        """Report the job's progress, ``fraction`` in [0, 1] (clipped)."""
        if self._on_progress is not None:
            self._on_progress(min(1.0, max(0.0, float(fraction))))

    # --- composition -----------------------------------------------------------------

    def child(self) -> Diagnostics:
        """A Diagnostics with the same cancel check and progress, and its own messages
        and seconds (for a stage whose messages the caller may keep or drop)."""
        out = Diagnostics(self._should_stop, self._on_progress)
        out.guard = self.guard
        return out

    def merge(self, other: Diagnostics) -> None:
        """Add ``other``'s messages (those not said yet) and seconds to this one."""
        for m in other.messages:
            if not any(n.text == m.text and n.level == m.level for n in self._messages):
                self._messages.append(m)
        for name, sec in other.seconds.items():
            self.seconds[name] = self.seconds.get(name, 0.0) + sec
        self.checks += other.checks


def check_stop(should_stop: Callable[[], bool] | None) -> None:
    """Raise ``Cancelled`` when ``should_stop`` (a callable, or None: never) says so: the
    one cancel check of the numeric kernels, which take a plain callable so that they
    run the same in a worker process (where it is the worker's ``core.runtime.Context``,
    which beats)."""
    if should_stop is not None and should_stop():
        raise Cancelled()


def diagnostics_of(diag: Diagnostics | None) -> Diagnostics:
    """``diag``, or a fresh Diagnostics that never stops (for callers that pass none)."""
    return diag if diag is not None else Diagnostics()


class Interrupt(threading.Event):
    """What ``interrupt_stops`` yields: set by Ctrl-C (SIGINT) while the block runs;
    ``to_host`` hands SIGINT back to the handler the process had before, for a call
    into C code that polls that handler's flag itself."""

    def __init__(self):
        super().__init__()
        self._host = None  # (Python's handler before, the C handler's sigaction, ours)

    @contextmanager
    def to_host(self):
        """Within the block SIGINT goes to the handler the process had before
        ``interrupt_stops``: in `blender -b` Blender's own (in C), which sets the break
        flag that Blender's C code polls (Cycles' ``test_break``). A Python handler runs
        only when the main thread runs Python again, so a long call in C (a Cycles
        render) would hear ours only when it ends. Nothing changes outside
        ``interrupt_stops``, off the main thread, or when the handler before would end
        the process or raise ``KeyboardInterrupt`` (the default action, Python's own)."""
        host = self._host
        if host is None:
            yield self
            return
        previous, native, ours = host
        if native is not None:
            _set_action(native)
        elif callable(previous) and previous is not signal.default_int_handler:
            signal.signal(signal.SIGINT, previous)
        else:
            yield self
            return
        try:
            yield self
        finally:
            signal.signal(signal.SIGINT, ours)


@contextmanager
def interrupt_stops():
    """Within the block, Ctrl-C (SIGINT) asks the job to stop instead of raising
    ``KeyboardInterrupt`` wherever the main thread happens to be: yields an
    ``Interrupt`` (a ``threading.Event``) that SIGINT sets, for the job's cancel check
    (headless Blender, where no Esc reaches the job). Off the main thread (a render in
    Blender's window) it changes nothing. The handler before it is put back after,
    also one Python did not install (Blender's own, in C: its ``sigaction`` is kept)."""
    interrupted = Interrupt()
    if threading.current_thread() is not threading.main_thread():
        yield interrupted
        return
    before = _get_action()

    def ours(_signum, _frame):
        interrupted.set()

    previous = signal.signal(signal.SIGINT, ours)
    mine = _get_action()
    native = None
    if before is not None and mine is not None and _handler_of(before) > 1:
        # a handler of its own, neither SIG_DFL, SIG_IGN nor Python's
        native = before if _handler_of(before) != _handler_of(mine) else None
    interrupted._host = (previous, native, ours)
    try:
        yield interrupted
    finally:
        interrupted._host = None
        signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)
        if native is not None:
            _set_action(native)


# ``struct sigaction`` is read and written whole, as bytes: its layout differs between
# platforms, but on all of POSIX its first member is the handler. More than any
# platform's size (Linux x86-64: 152 bytes).
_SIGACTION_BYTES = 512


def _libc():
    """The C library (ctypes), or None where it has no ``sigaction`` (Windows)."""
    if os.name != "posix":
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc if hasattr(libc, "sigaction") else None
    except OSError:
        return None


def _get_action():
    """SIGINT's ``struct sigaction`` as bytes, or None where it cannot be read."""
    libc = _libc()
    if libc is None:
        return None
    buf = ctypes.create_string_buffer(_SIGACTION_BYTES)
    if libc.sigaction(signal.SIGINT, None, buf) != 0:
        return None
    return buf.raw


def _set_action(action):
    """Make ``action`` (``_get_action``'s bytes) SIGINT's ``struct sigaction``."""
    libc = _libc()
    if libc is not None:
        libc.sigaction(signal.SIGINT, ctypes.create_string_buffer(action, len(action)), None)


def _handler_of(action):
    """The handler's address in ``action`` (0: SIG_DFL, 1: SIG_IGN)."""
    return ctypes.c_size_t.from_buffer_copy(action[: ctypes.sizeof(ctypes.c_size_t)]).value
