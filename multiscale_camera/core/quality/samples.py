"""Which preserved pixels the checks before a build look at, and how many must show a
problem before it is reported."""

import numpy as np

# Preserved pixels sampled per camera by the crossing and obstruction checks: enough to
# find a crossing a few pixels wide at 1080p, a fraction of a second of work.
MAX_CHECK_RAYS = 4000
# A crossing or an obstruction is reported once it touches this share of the sampled rays
# (single rays graze mask edges through rounding).
MIN_SHARE = 0.002


def sample_pixels(mask, limit=MAX_CHECK_RAYS):
    """(ix, iy) int arrays: the pixels of ``mask`` ((H, W) bool), every k-th in each
    direction so that at most about ``limit`` are taken."""
    count = int(mask.sum())
    stride = max(1, int(np.ceil(np.sqrt(count / limit)))) if count else 1
    sub = np.zeros_like(mask)
    sub[::stride, ::stride] = mask[::stride, ::stride]
    iy, ix = np.nonzero(sub)
    return ix, iy
