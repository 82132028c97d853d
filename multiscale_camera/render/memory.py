"""The memory guard: before a field is built and before a frame is rendered, the peak
memory of Blender's process and the workers is estimated from shapes (the grid, the
image, the rig: ``core.quality.estimate_memory``, ``render_memory``) and work whose
estimate passes the budget is refused with the estimate, the budget and what to lower,
before anything large is allocated (docs/failures.md, "Memory").

The budget is the scene's Memory Budget (``scene.multiscale.memory_budget_mb``, MB of
2**20 bytes as Blender counts them) when set, else the memory the machine has free less
a margin, and never under ``MIN_BUDGET_BYTES``: on Linux ``MemAvailable`` of
/proc/meminfo, on Windows ``GlobalMemoryStatusEx``, on macOS ``vm_stat``'s free and
inactive pages, elsewhere the free physical pages. Where none can be read the guard
lets the work go on, and says so once (``GUARD_OFF``).
"""

import ctypes
import os
import re
import subprocess
import sys

from ..core.errors import RigError
from ..core.quality import MB, budget_message, estimate_memory, render_memory, size_text
from ..core.runtime import worker_count
from .fields import SERVICE

# Kept free under the automatic budget: the larger of a fixed margin and a fraction of
# what is free (Blender, the desktop and the file cache need some).
MARGIN_BYTES = 512 * MB
MARGIN_FRACTION = 0.1
# The automatic budget never falls under this: a machine short of memory still builds
# and renders small work (a 64x48 preview) rather than refusing everything.
MIN_BUDGET_BYTES = 256 * MB
GUARD_OFF = (
    "The memory guard is off: this machine's free memory cannot be read, so builds and "
    "renders too large for it are not refused; set a Memory Budget (Multiscale > Preview "
    "and Cache) to have them refused"
)
_SAID_OFF = []  # one entry once GUARD_OFF has been said in this session

# The budgets kept for AUTO's further candidates (``SERVICE.budgets``: the budget each
# request was last guarded against, read by ``guard_candidate`` in whichever thread
# builds them): the last this many requests.
MAX_BUDGETS_KEPT = 8


class MemoryBudgetError(RigError):
    """The work would need more memory than its budget; the message says how much and
    what to lower."""


def linux_available(meminfo="/proc/meminfo"):
    """int, bytes of ``MemAvailable`` in ``meminfo`` (a /proc/meminfo file), or None."""
    try:
        with open(meminfo) as lines:
            for line in lines:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


class MEMORYSTATUSEX(ctypes.Structure):
    """Windows' MEMORYSTATUSEX (sysinfoapi.h); ``dwLength`` must be set to its size."""

    _fields_ = [
        ("dwLength", ctypes.c_uint32),
        ("dwMemoryLoad", ctypes.c_uint32),
        ("ullTotalPhys", ctypes.c_uint64),
        ("ullAvailPhys", ctypes.c_uint64),
        ("ullTotalPageFile", ctypes.c_uint64),
        ("ullAvailPageFile", ctypes.c_uint64),
        ("ullTotalVirtual", ctypes.c_uint64),
        ("ullAvailVirtual", ctypes.c_uint64),
        ("ullAvailExtendedVirtual", ctypes.c_uint64),
    ]


def windows_available(kernel32=None):
    """int, bytes of physical memory available (``ullAvailPhys`` of
    ``GlobalMemoryStatusEx``), or None. ``kernel32``: the library to ask (default
    ``ctypes.windll.kernel32``)."""
    try:
        kernel32 = kernel32 if kernel32 is not None else ctypes.windll.kernel32
        status = MEMORYSTATUSEX()
        status.dwLength = ctypes.sizeof(MEMORYSTATUSEX)
        if not kernel32.GlobalMemoryStatusEx(ctypes.pointer(status)):
            return None
    except (AttributeError, OSError):
        return None
    return int(status.ullAvailPhys)


def parse_vm_stat(text):
    """int, bytes of the free and inactive pages in macOS ``vm_stat`` output ``text``
    (what can be had without paging out: psutil's ``available``), or None."""
    size = re.search(r"page size of (\d+) bytes", text)
    pages = {}
    for name, count in re.findall(r"^Pages (free|inactive):\s+(\d+)\.?\s*$", text, re.M):
        pages[name] = int(count)
    if not size or len(pages) < 2:
        return None
    return (pages["free"] + pages["inactive"]) * int(size.group(1))


def macos_available(run=subprocess.run):
    """int, bytes free on macOS (``parse_vm_stat`` of ``vm_stat``), or None."""
    try:
        done = run(["vm_stat"], capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    return parse_vm_stat(done.stdout) if done.returncode == 0 else None


def available_bytes(platform=None):
    """int, bytes of memory the machine has free for new work (by ``platform``, default
    ``sys.platform``: ``linux_available``, ``windows_available``, ``macos_available``,
    else the free physical pages), or None when it cannot be told."""
    platform = platform or sys.platform
    if platform.startswith("linux"):
        free = linux_available()
    elif platform == "win32":
        free = windows_available()
    elif platform == "darwin":
        free = macos_available()
    else:
        free = None
    if free is not None:
        return free
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):
        return None


def budget_of(scene, available=None):
    """(bytes, where they come from) of the scene's memory budget, or (None, "") when
    there is none to be had. ``available``: bytes free (default ``available_bytes``)."""
    fixed = int(getattr(scene.multiscale, "memory_budget_mb", 0))
    if fixed > 0:
        return fixed * MB, "the scene's Memory Budget"
    free = available_bytes() if available is None else available
    if free is None:
        return None, ""
    margin = max(MARGIN_BYTES, int(MARGIN_FRACTION * free))
    if free - margin < MIN_BUDGET_BYTES:
        return MIN_BUDGET_BYTES, (
            f"free memory {size_text(free)} less a margin of {size_text(margin)} is under "
            f"the least budget, {size_text(MIN_BUDGET_BYTES)}"
        )
    return free - margin, f"free memory {size_text(free)} less a margin of {size_text(margin)}"


def guard_memory(scene, request, render=False):
    """Refuse the build of ``request``'s field (when it is not cached) and, with
    ``render``, the frame's render, when either's estimated peak passes the scene's
    budget (``budget_of``).

    Returns
    -------
    ``GUARD_OFF`` the first time in a session that there is no budget (no Memory Budget
    and the free memory cannot be read), for the caller to say where the user looks;
    else None.

    Raises
    ------
    MemoryBudgetError with the estimate, the budget and what to lower.
    """
    budget, where = budget_of(scene)
    if budget is None:
        if _SAID_OFF:
            return None
        _SAID_OFF.append(True)
        return GUARD_OFF
    budgets = SERVICE.budgets  # for AUTO's further candidates
    budgets.pop(request.key, None)  # the newest last
    budgets[request.key] = (budget, where)
    while len(budgets) > MAX_BUDGETS_KEPT:
        budgets.pop(next(iter(budgets)))
    workers = worker_count(request.settings.processes)
    fld = SERVICE.cached(request)
    if fld is None:
        build = estimate_memory(request.rig, request.method, request.settings, workers)
        said = budget_message(build, budget, where, "The field build")
        if said:
            raise MemoryBudgetError(said)
        rays, vertices = build.shapes["traced_rays"], build.shapes["vertices"]
    else:
        traced = getattr(fld, "traced", None)
        rays, vertices = (0, 0) if traced is None else traced.vertices.shape[:2]
    if render:
        w, h = request.rig.size
        samples = max(1, int(scene.multiscale.samples))
        estimate = render_memory(w, h, samples, rays, vertices, workers)
        said = budget_message(estimate, budget, where, "The render")
        if said:
            raise MemoryBudgetError(said)
    return None


def guard_candidate(request, method):
    """Refuse AUTO's further candidate ``method`` (str) for ``request`` when its build's
    estimated peak passes the budget ``guard_memory`` found for the request: the guard
    estimates AUTO's first candidate (IMAGE_BLEND, built and measured) before the build
    starts, and this one before AUTO goes on to it (``Diagnostics.guard``). Nothing to
    do for a request the guard did not see (no budget).

    Raises
    ------
    MemoryBudgetError with the estimate, the budget and what to lower.
    """
    budget = SERVICE.budgets.get(request.key)
    if budget is None:
        return
    workers = worker_count(request.settings.processes)
    estimate = estimate_memory(request.rig, method, request.settings, workers)
    said = budget_message(
        estimate, budget[0], budget[1], f"AUTO's next candidate, the {method} build,"
    )
    if said:
        raise MemoryBudgetError(said)


SERVICE.candidate_guard = guard_candidate
