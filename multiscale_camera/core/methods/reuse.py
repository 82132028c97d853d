"""Reuse between the builds of a sequence (an animation's frames): what a build may take
from the one before it without changing its answer.

SCALAR_FIELD on a steady layout (``Settings.steady``, ``field.layout``) keeps its grids
while the rig stays inside them, so from one frame to the next:

- a camera's claims on a grid (eq. 4's core and halo, ``field.splat_camera``) depend
  on its family (the cameras up to it, ``beta``) and its mask alone: a camera that did
  not move, nor any before it, claims the same voxels, which are taken as they were;
- the membership solve (eq. 5) starts from the previous frame's solution on the same
  grid instead of the parent level's values (or zero). It stops at the same relative
  residual, so the answer differs from a cold start's by the solver's tolerance (a
  test holds the rays to 0.01 px of a cold build);
- everything else (the other cameras' claims, the trace) is built again: every ray of
  a transition depends on the cameras on either side of it.

IMAGE_BLEND has no grid: its weights (``field.mask_weights``, eased) depend on the masks
alone, and are most of its build; a frame whose masks are those of the build before
takes them as they were (``weights``), one whose masks changed solves them again.

``FrameReuse`` holds that between builds (the field service keeps one per process) and
says per build what was taken and what was built (``record``, ``record_weights``).
"""

import hashlib
import threading

import numpy as np

from .fingerprint import hash_cameras


def family_digest(rig, i):
    """Hex digest of what camera ``i``'s claims depend on: cameras 1..i (placement,
    lens, sensor, shift, clipping, size), ``beta`` and camera i's mask."""
    h = hashlib.sha1()
    h.update(repr((rig.beta, rig.size, i)).encode())
    hash_cameras(h, rig.cameras[: i + 1])
    h.update(np.packbits(np.ascontiguousarray(rig.masks[i])).tobytes())
    return h.hexdigest()


def masks_digest(masks):
    """Hex digest of ``masks`` ((N, H, W) bool): their shape and pixels."""
    masks = np.ascontiguousarray(masks, dtype=bool)
    h = hashlib.sha1(repr(masks.shape).encode())
    h.update(np.packbits(masks).tobytes())
    return h.hexdigest()


def solve_phrase(solve):
    """How a frame's report names its membership solve, from ``record``'s ``solve``:
    "membership solve", "membership solve (warm start)" or "membership solve (warm
    start on k of n grids)"."""
    if solve == "cold":
        return "membership solve"
    if solve == "warm":
        return "membership solve (warm start)"
    return f"membership solve (warm start {solve.removeprefix('warm ')})"


class FrameReuse:
    """Claims and solutions of the last builds, by grid; thread safe (one build at a
    time reads or writes it, under its lock).

    claims : dict (Grid, family digest) -> (core, halo), (nx, ny, nz) bool each.
    solved : dict (Grid, method, settings) -> (nx, ny, nz) float32 membership.
    weights : dict masks digest (``masks_digest``) -> (weights, solver): IMAGE_BLEND's
        eased weights ((N, H, W) float32, read only) and its solve's ``solver`` dict;
        the last build's alone.
    last : dict, what the last build took and built (``record``).
    """

    def __init__(self):
        self.claims = {}
        self.solved = {}
        self.weights = {}
        self.last = {}
        self._lock = threading.Lock()

    def mask_weights(self, masks):
        """(weights, solver) kept for ``masks`` ((N, H, W) bool), or None."""
        key = masks_digest(masks)
        with self._lock:
            return self.weights.get(key)

    def keep_weights(self, masks, weights, solver):
        """Keep IMAGE_BLEND's ``weights`` (and its ``solver`` dict) for ``masks``, and
        no other: masks that changed leave their weights behind."""
        weights.setflags(write=False)  # shared by the fields built on them
        with self._lock:
            self.weights = {masks_digest(masks): (weights, dict(solver))}

    def record_weights(self, reused, seconds):
        """What an IMAGE_BLEND build took and built, for its report (``stats["reuse"]``):
        ``weights`` ("reused" or "solved"), ``rebuilt`` (["weights"] or []),
        ``seconds`` (dict stage -> float, rounded)."""
        out = {
            "weights": "reused" if reused else "solved",
            "rebuilt": [] if reused else ["weights"],
            "seconds": {k: round(float(v), 3) for k, v in seconds.items()},
        }
        with self._lock:
            self.last = out
        return dict(out)

    def known(self, rig, grids):
        """Per grid of ``grids``, per camera: its (core, halo) kept from an earlier
        build, or None (``fill.fill_membership``'s ``known``)."""
        digests = [family_digest(rig, i) for i in range(len(rig.cameras))]
        with self._lock:
            return [[self.claims.get((g, d)) for d in digests] for g in grids]

    def warm(self, grids, tag):
        """Per grid of ``grids``: the membership a build tagged ``tag`` (method and
        settings) solved on it, or None."""
        with self._lock:
            return [self.solved.get((g, tag)) for g in grids]

    def keep(self, rig, grids, fills, fields, tag):
        """Keep the claims of every camera and the solved membership of each grid of
        this build, and nothing else: a camera that moved leaves its earlier claims
        behind, a layout that moved its grids, and the store holds one build's worth."""
        digests = [family_digest(rig, i) for i in range(len(rig.cameras))]
        claims, solved = {}, {}
        for grid, fill, membership in zip(grids, fills, fields, strict=True):
            for d, core, halo in zip(digests, fill.cores, fill.halos, strict=True):
                claims[(grid, d)] = (core, halo)
            solved[(grid, tag)] = membership
        with self._lock:
            self.claims, self.solved = claims, solved

    def record(self, names, known, warm, seconds):
        """What a build took and built, for its report (``stats["reuse"]``).

        names : camera names. known, warm : as handed to the build (per grid).
        seconds : dict stage -> float. Returns a dict: ``claims_reused`` and
        ``claims_built`` (camera names: whose claims were taken on every grid, and
        whose were splatted on some), ``solve`` ("warm" on every grid, "cold", or
        "warm on k of n grids"), ``solve_said`` (``solve_phrase``), ``rebuilt`` (the
        stages run), ``seconds``."""
        reused = [n for i, n in enumerate(names) if all(k[i] is not None for k in known)]
        built = [n for n in names if n not in reused]
        warm_count = sum(w is not None for w in warm)
        solve = (
            "warm"
            if warm_count == len(warm)
            else "cold"
            if warm_count == 0
            else f"warm on {warm_count} of {len(warm)} grids"
        )
        rebuilt = (["fill"] if built else []) + ["solve", "trace"]
        out = {
            "claims_reused": reused,
            "claims_built": built,
            "solve": solve,
            "solve_said": solve_phrase(solve),
            "rebuilt": rebuilt,
            "seconds": {k: round(float(v), 3) for k, v in seconds.items()},
        }
        with self._lock:
            self.last = out
        return dict(out)
