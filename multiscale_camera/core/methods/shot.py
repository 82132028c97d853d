"""AUTO for a rig in motion: one method for the whole shot, chosen once.

A choice measured frame by frame could switch method mid-shot (the rays would jump at
that frame). So AUTO measures IMAGE_BLEND, the cheaper candidate, on a few frames that
cover the shot (``sample_frames``: its first and last keyed frames and the key nearest
its middle) and keeps it for every frame when every sampled frame meets the target
(``registry.shortfall``), else SCALAR_FIELD on the shot's layout. Folds that every
method has (quads across a seam where masks touch, ``quality.kept_folds``) do not count
against IMAGE_BLEND, as they do not for a still. The frames sampled
depend on the shot alone (its keys, not the frames a process was asked to render), and
each measure on that frame's rig alone, so every process of a farm chooses alike.
"""

from dataclasses import dataclass

from ..diagnostics import diagnostics_of
from ..quality import measure_map
from .base import Settings
from .image_blend import prepare_image_blend
from .registry import (
    AT_SEAMS,
    MAX_OVER_TARGET,
    accuracy_misses,
    seam_folds,
    seams_text,
    shortfall,
)

# Frames of a shot AUTO measures IMAGE_BLEND on, at most (each a weights solve and a
# measure of the frame's preserved rays and folds).
MAX_SAMPLED = 3


@dataclass(frozen=True)
class ShotChoice:
    """AUTO's method for a whole shot (``choose_shot_method``).

    method : str, "IMAGE_BLEND" or "SCALAR_FIELD".
    frames : tuple of int, the frames measured.
    why : str, for the report's ``auto`` (docs/report.md).
    """

    method: str
    frames: tuple
    why: str

    def __repr__(self):
        # part of Settings' repr, so of the field's cache key: what the rays depend on
        return f"ShotChoice({self.method!r}, frames={self.frames!r})"


def sample_frames(first, last, keys=(), most=MAX_SAMPLED):
    """The frames of a shot AUTO measures: its first and last keyed frames and the key
    nearest its middle (the earlier of two as near); without keys inside the shot, the
    ends of ``first``..``last`` and the frame at its middle (rounded down).

    Parameters
    ----------
    first, last : int, the shot's range. keys : iterable of float, the frames of its
        cameras' keys (any order, repeats allowed). most : int, frames returned at most
        (>= 2: the ends are always kept).

    Returns
    -------
    tuple of int, ascending, no repeats.
    """
    inside = sorted({int(round(k)) for k in keys if first <= round(k) <= last})
    if len(inside) < 2:
        inside = sorted({int(first), int(last)})
    lo, hi = inside[0], inside[-1]
    mid = (lo + hi) / 2.0
    between = list(inside[1:-1]) or [int((lo + hi) // 2)]
    picked = [lo, hi]
    for k in sorted(between, key=lambda k: (abs(k - mid), k))[: max(0, most - 2)]:
        picked.append(k)
    return tuple(sorted(set(picked)))


def choose_shot_method(samples, settings=None, diag=None):
    """AUTO's method for a shot from IMAGE_BLEND measured on ``samples``.

    Parameters
    ----------
    samples : sequence of (frame, Rig), the frames of ``sample_frames`` with each
        frame's rig (its cameras and masks), in any order; measured ascending.
    settings : Settings (accuracy target, processes). diag : Diagnostics or None
        (cancel, checked between frames).

    Returns
    -------
    ShotChoice: IMAGE_BLEND when every sampled frame meets the target, else
    SCALAR_FIELD, naming the first frame that missed and why (the frames after it are
    not measured). A frame whose every fold lies across a seam where masks touch
    (``registry.seam_folds``), its cameras on the target, meets it: those rays are the
    cameras' own with every method, so SCALAR_FIELD would fold there too. The word then
    names those frames and the cameras whose masks touch.
    """
    settings = settings or Settings()
    diag = diagnostics_of(diag)
    measured, seams = [], []
    for frame, rig in sorted(samples, key=lambda s: s[0]):
        diag.check()
        fld = prepare_image_blend(rig, settings, diag)
        cameras, fold_quads, stride = measure_map(fld, settings.processes, diag)
        folds = int(fold_quads.sum())
        measured.append(int(frame))
        pairs = None
        if not accuracy_misses(cameras, settings.accuracy_px):
            pairs = seam_folds(rig, fold_quads, stride)
        if pairs is not None:  # every method's rays fold there: not IMAGE_BLEND's miss
            seams.append((int(frame), folds, pairs))
            continue
        why = shortfall(cameras, folds, settings.accuracy_px)
        if why:
            return ShotChoice(
                "SCALAR_FIELD",
                tuple(measured),
                f"SCALAR_FIELD: the rig moves and a shot keeps one method; IMAGE_BLEND "
                f"would miss the target at frame {frame}: {why} "
                f"(frames measured: {_listed(measured)})",
            )
    return ShotChoice(
        "IMAGE_BLEND",
        tuple(measured),
        f"IMAGE_BLEND: the rig moves and a shot keeps one method; IMAGE_BLEND meets the "
        f"target (p95 <= {settings.accuracy_px:g} px, max <= "
        f"{MAX_OVER_TARGET * settings.accuracy_px:g} px along every preserved ray, no fold) "
        f"at frames {_listed(measured)} of the shot" + _seams(seams),
    )


def _seams(seams):
    """The word's note on folds at seams: ``seams`` a list of (frame, folds, pairs)."""
    if not seams:
        return ""
    said = "; ".join(f"frame {f}: {n}, {seams_text(pairs)}" for f, n, pairs in seams)
    return f"; its folded quads {AT_SEAMS} ({said})"


def _listed(frames):
    return ", ".join(str(f) for f in frames)
