"""The memory guard's words: how large an estimate is (``size_text``) and, when it does
not fit the budget, a refusal that names its largest parts and what to lower for each
(``budget_message``; the estimate itself: ``memory``)."""

# What to lower for each part of an estimate (a worker's part: fewer workers).
LOWER_RESOLUTION = "the resolution (Output Properties > Format > Resolution, or its %)"
LOWER_QUALITY = "the Quality (its voxel budget)"
LOWER_TRACED = "the Quality (a looser accuracy target traces fewer rays, with fewer steps)"
FEWER_WORKERS = "the worker processes (Render > Performance > Threads: Fixed, fewer)"
RAISE_BUDGET = "or raise the Memory Budget (Multiscale > Preview and Cache; 0: the free memory)"


def size_text(count):
    """'1.2 GB' or '340 MB' for ``count`` bytes (GB and MB of 2**30 and 2**20 bytes)."""
    return f"{count / 2**30:.1f} GB" if count >= 2**30 else f"{count / 2**20:.0f} MB"


# Parts of a trace: rays, their vertices and what holds them, which a lower Quality
# (a looser accuracy target: fewer rays, longer steps) shrinks as well as the resolution.
TRACED_PARTS = ("traced rays", "error estimate", "shares received", "share of rays")


def _lower(part):
    """What to lower for the part named ``part``: a list of LOWER_* / FEWER_WORKERS."""
    if part.startswith("workers: "):
        return [FEWER_WORKERS]
    if part.startswith("grid"):
        return [LOWER_QUALITY]
    if part in TRACED_PARTS:
        return [LOWER_RESOLUTION, LOWER_TRACED]
    return [LOWER_RESOLUTION]


def budget_message(estimate, budget, budget_text, action="The field build"):
    """The memory guard's refusal, or None when ``estimate`` fits ``budget``.

    Parameters
    ----------
    estimate : MemoryEstimate. budget : int, bytes. budget_text : str, where the budget
    comes from ("the Memory Budget setting", "free memory 3.2 GB less a margin of
    0.5 GB"). action : str, a capitalised noun phrase for the work refused.

    Returns
    -------
    str or None: the estimate and its three largest parts, the budget and where it comes
    from, and what to lower for those of them that weigh at least a quarter of the
    largest (the largest first), or None.
    """
    if estimate.total <= budget:
        return None
    parts = list(estimate.parts.items())[:3]
    said = ", ".join(f"{name} {size_text(count)}" for name, count in parts)
    advice = []
    for name, count in parts:  # what to lower for the parts that weigh (a quarter or more)
        if count >= parts[0][1] / 4:
            advice += [a for a in _lower(name) if a not in advice]
    return (
        f"{action} would need about {size_text(estimate.total)} of memory ({said}), more "
        f"than the budget of {size_text(budget)} ({budget_text}); nothing was started: lower "
        f"{' or '.join(advice)}, {RAISE_BUDGET}"
    )
