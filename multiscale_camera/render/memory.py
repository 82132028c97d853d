"""The memory guard: before a field is built and before a frame is rendered, the peak
memory of Blender's process and the workers is estimated from shapes (the grid, the
image, the rig: ``core.methods.estimate_memory``, ``render_memory``) and work whose
estimate passes the budget is refused with the estimate, the budget and what to lower,
before anything large is allocated (docs/failures.md, "Memory").

The budget is the scene's Memory Budget (``scene.multiscale.memory_budget_mb``) when
set, else the memory the machine has free (``MemAvailable`` of /proc/meminfo, or the
free pages where there is none) less a margin. Where neither can be read the guard
lets the work go on.
"""

import os

from ..core.errors import RigError
from ..core.quality import budget_message, estimate_memory, render_memory, size_text
from ..core.runtime import worker_count
from .fields import SERVICE

MB = 1 << 20
# Kept free under the automatic budget: the larger of a fixed margin and a fraction of
# what is free (Blender, the desktop and the file cache need some).
MARGIN_BYTES = 512 * MB
MARGIN_FRACTION = 0.1


class MemoryBudgetError(RigError):
    """The work would need more memory than its budget; the message says how much and
    what to lower."""


def available_bytes(meminfo="/proc/meminfo"):
    """int, bytes of memory the machine has free for new work (Linux: ``MemAvailable``;
    elsewhere the free physical pages), or None when it cannot be told."""
    try:
        with open(meminfo) as lines:
            for line in lines:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
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
    budget = max(free - margin, 0)
    return budget, f"free memory {size_text(free)} less a margin of {size_text(margin)}"


def guard_memory(scene, request, render=False):
    """Refuse the build of ``request``'s field (when it is not cached) and, with
    ``render``, the frame's render, when either's estimated peak passes the scene's
    budget (``budget_of``).

    Raises
    ------
    MemoryBudgetError with the estimate, the budget and what to lower.
    """
    budget, where = budget_of(scene)
    if budget is None:
        return
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
