"""Ctrl-C (SIGINT) and the handler the process had before ``interrupt_stops``: a C
handler Python did not install (Blender's own in `blender -b`, which sets the break
flag Cycles polls) is put back exactly after the block, and ``Interrupt.to_host`` hands
SIGINT to it for a call in C (Cycles' own render), during which a Python handler would
run only once the call returns. The C handler here is libc's ``srand``: a function of
one int, harmless when a signal calls it."""

import ctypes
import os
import signal
import time

import pytest

from multiscale_camera.core.diagnostics import _get_action, _handler_of, interrupt_stops

LIBC = ctypes.CDLL(None)
LIBC.signal.restype = ctypes.c_void_p
LIBC.signal.argtypes = (ctypes.c_int, ctypes.c_void_p)
SRAND = ctypes.cast(LIBC.srand, ctypes.c_void_p).value


@pytest.fixture(autouse=True)
def python_default_after():
    yield
    signal.signal(signal.SIGINT, signal.default_int_handler)


def os_handler():
    """SIGINT's handler as the kernel has it (an address; 0 SIG_DFL, 1 SIG_IGN)."""
    return _handler_of(_get_action())


def ctrl_c():
    """SIGINT to this process, and a moment for Python to run its handler."""
    os.kill(os.getpid(), signal.SIGINT)
    for _ in range(10):
        time.sleep(0.001)


def test_a_c_handler_python_did_not_install_is_put_back_after_the_block():
    LIBC.signal(signal.SIGINT, SRAND)  # as Blender installs its own, before Python runs
    with interrupt_stops() as interrupted:
        assert os_handler() != SRAND  # ours, Python's
        ctrl_c()
        assert interrupted.is_set()
    assert os_handler() == SRAND  # not SIG_DFL: Ctrl-C would end Blender


def test_cycles_stage_hands_ctrl_c_to_the_c_handler_and_takes_it_back():
    LIBC.signal(signal.SIGINT, SRAND)
    with interrupt_stops() as interrupted:
        with interrupted.to_host():
            assert os_handler() == SRAND
            ctrl_c()  # Blender's handler would set its break flag
        assert not interrupted.is_set()
        assert os_handler() != SRAND
        ctrl_c()
        assert interrupted.is_set()
    assert os_handler() == SRAND


def test_cycles_stage_hands_ctrl_c_to_a_python_handler_before():
    heard = []
    signal.signal(signal.SIGINT, lambda signum, _frame: heard.append(signum))
    with interrupt_stops() as interrupted:
        with interrupted.to_host():
            ctrl_c()
        assert heard == [signal.SIGINT]
        assert not interrupted.is_set()
        ctrl_c()
        assert interrupted.is_set() and heard == [signal.SIGINT]


def test_cycles_stage_keeps_ctrl_c_where_the_handler_before_would_raise():
    signal.signal(signal.SIGINT, signal.default_int_handler)
    with interrupt_stops() as interrupted:
        with interrupted.to_host():  # KeyboardInterrupt in the middle of a render: no
            ctrl_c()
        assert interrupted.is_set()
