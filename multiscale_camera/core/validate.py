"""Checks of a rig that explain, before a build, what would go wrong and what to change."""

import numpy as np

from .errors import RigError

# Consecutive cameras may turn at most this much: beyond it the guides of neighbouring
# pixels cross (paper, section 6).
MAX_TURN_DEG = 90.0


def turn_deg(a, b):
    """Angle between two cameras' view axes, degrees."""
    return float(np.degrees(np.arccos(np.clip(a.forward @ b.forward, -1.0, 1.0))))


def check_rig(rig):
    """Raise ``RigError`` for a rig that cannot give coherent rays; return warnings.

    Checks: consecutive cameras turned more than 90 degrees apart; a camera's near plane
    behind the previous camera's eye (the order of scales reversed).

    Returns
    -------
    list of str, warnings that do not stop a build.
    """
    cams = rig.cameras
    warnings = []
    for a, b in zip(cams, cams[1:]):
        angle = turn_deg(a, b)
        if angle > MAX_TURN_DEG:
            raise RigError(
                f"Cameras '{a.name}' and '{b.name}' look {angle:.0f} degrees apart; consecutive "
                f"cameras must turn less than {MAX_TURN_DEG:.0f} degrees (add a camera between "
                "them to bend the rays in stages)"
            )
        depth = (b.eye + b.forward * b.clip_start - a.eye) @ a.forward
        if depth < a.clip_start:
            warnings.append(
                f"The near plane of '{b.name}' lies before the near plane of '{a.name}': the "
                "list should run from the largest scale to the smallest (move it down the list, "
                "or move the camera)"
            )
    return warnings


def conflict_messages(names, overlaps):
    """Warnings for voxels that preserved rays of two cameras both claim.

    Parameters
    ----------
    names : list of N str. overlaps : (N, N) int, voxels claimed by both i and j.
    """
    out = []
    n = len(names)
    for i in range(n):
        for j in range(i + 1, n):
            count = int(overlaps[i, j])
            if not count:
                continue
            if j == i + 1:
                out.append(
                    f"{count} voxels lie on preserved rays of both '{names[i]}' and '{names[j]}': "
                    "their masks contradict each other there and those voxels were left free "
                    "(widen the gap between the two masks, or move a near plane)"
                )
            else:
                out.append(
                    f"The preserved views of '{names[i]}' and '{names[j]}', which are not "
                    f"neighbours in the list, cross in {count} voxels: rays there cannot be "
                    "coherent (move one of the cameras, or shrink its mask)"
                )
    return out
