"""The build report (docs/report.md, schema version 2), measured on the rays a field
actually hands to the renderer."""

import contextvars
import json
import threading
from functools import partial

import numpy as np

from ..diagnostics import check_stop, diagnostics_of
from ..runtime import runtime, worker_count
from .folds import quad_folds_on_planes
from .metrics import (
    ALONG_BLOCK_VERTICES,
    ERODE_PX,
    Preserved,
    bending_active_on_planes,
    measured_pixels,
    preserved_error_on_planes,
)

# 2: preserved_px and angle_deg are the worst along the whole preserved ray (from the
# camera's near plane to its clip end), no longer where it meets the near plane; folds
# are counted in sections across the bundle; newton_lost and unfinished are counted.
VERSION = 2


# Ray vertices per chunk when counting folds: bounds memory (quad_folds holds about a
# dozen float64 planes of one value per vertex: about 50 MB at this size, whatever K
# is; the band's rays and their bending stretch as much again). Half what it was: the
# band's largest arrays (its curves, 3 x 12 MB on a three-camera rig) then stay under
# the allocator's 32 MB threshold for mapping fresh pages, whose faults took 1.2 to 1.5
# s of system time on the three-camera 6x rig at 1920x1080 (0.05 to 0.2 s now), for
# 13.4 to 14.0 user s against 14.0 to 14.7 (bench: docs/performance.md, The fold count).
FOLD_CHUNK_VERTICES = 1 << 19
# Fewer bands than this per worker are cut smaller (``SMALL_BANDS`` a worker) so that
# the workers still share them.
MIN_SHARED_BANDS = 4
# Runs of bands a worker is handed, about (each run goes to the next idle worker).
SHARES_PER_WORKER = 4
# Bands a worker of an image too small for ``MIN_SHARED_BANDS`` full bands a worker.
# (Threads of this process gained nothing there: the count's many small array
# operations hold the interpreter between them; 0.79 to 1.1 s in two threads against
# 0.9 s in one on the three-camera 6x rig at 480x270, 0.49 to 0.68 s in two started
# workers.)
SMALL_BANDS = 4
# Smaller images are counted in this process: a worker's share of them is worth less
# than the trip of the field to it.
FOLD_SHARED_MIN_PIXELS = 1 << 16


def fold_map(fld, processes=1, should_stop=None):
    """Folds among the rendered rays: every quad of neighbouring pixels, at every size.

    The image's rows go in bands of at most ``FOLD_CHUNK_VERTICES`` vertices (each
    band's last row is the next one's first; a band of two rows that holds more, of long
    rays across a wide image, is counted in pieces of columns: ``fold_columns``), shared
    among worker processes (``processes``: ``runtime.worker_count``'s request: 0 one per
    core, 1 keeps them here) in runs of consecutive bands, a few a worker, on images of
    ``FOLD_SHARED_MIN_PIXELS`` (bands cut smaller where there are too few: ``fold_plan``);
    smaller images are counted here. ``should_stop`` (callable () -> bool) cancels the
    count, here or shared, asked before every band (at most about 0.4 s of work at
    1920x1080). The map is the same whatever the bands and wherever they are counted
    (every quad is counted from its four rays alone); a share whose worker is given up
    runs here.

    What cannot fold is not checked (``kept_limits``): where the field lays kept
    pixels' rays out as their camera's curve R_i exactly (``exact_kept``:
    ``IMAGE_BLEND``), a quad whose four pixels camera 1 keeps is four pinhole rays of
    camera 1 from their first vertex on, which no section across them shows crossing;
    one that camera i > 1 keeps is checked up to the first vertex of its first ray past
    camera i's near plane, beyond which its four rays are camera i's pinhole rays and
    every section says the same. Rays are made only for the pixels of the quads checked.
    The map is the full count's (tests/unit/test_folds_kept.py).

    Returns
    -------
    folds : (H - 1, W - 1) bool: the quad of pixels (y, x), (y, x + 1), (y + 1, x + 1),
    (y + 1, x) folds (``quad_folds``). stride : int, the lattice's step in pixels: 1,
    every quad at every size.

    Raises
    ------
    Cancelled when ``should_stop`` says so.
    """
    return FoldCount(fld, processes, should_stop).result()


class FoldCount:
    """``fold_map`` begun: a count shared among workers runs while this process does
    something else (``measure_map`` measures the preserved rays meanwhile), a thread of
    this process waiting on the workers; ``result`` waits for the map. A count kept here
    runs in ``result``. ``close`` stops a count whose map is not wanted (its workers
    return to the pool) and waits for it."""

    def __init__(self, fld, processes=1, should_stop=None):
        w, h = fld.rig.size
        self.xs, self.ys = np.arange(w), np.arange(h)
        self.fld, self.should_stop = fld, should_stop
        traced = getattr(fld, "traced", None)
        if traced is not None:
            k = traced.vertices.shape[1]
        else:  # one ray says how many vertices each has
            one = np.zeros(1, dtype=np.int64)
            k = fld.rays(one, one).vertices.shape[1]
        workers, self.rows = fold_plan(w, h, k, worker_count(processes))
        self.cols = fold_columns(self.rows, k)
        self.starts = list(range(0, len(self.ys) - 1, self.rows - 1))
        self.map = None
        self._stop, self._error, self._thread, self._run = False, None, None, None
        if workers >= 1:
            # runs of consecutive bands (a run's rays lie together in the image), a few a
            # process, so that a process given less of the machine takes fewer
            split = np.array_split(np.asarray(self.starts), (workers + 1) * SHARES_PER_WORKER)
            self.runs = [list(r) for r in split if len(r)]
            task = partial(_fold_bands, self.fld, self.xs, self.ys, self.rows, cols=self.cols)
            self._run = runtime().run(task, self.runs, workers, self._asked, helped=True)
            # iterated in the caller's context: the runtime's journals (what ran where)
            # see the run
            context = contextvars.copy_context()
            self._thread = threading.Thread(
                target=context.run, args=(self._shared,), name="fold count", daemon=True
            )
            self._thread.start()

    def _asked(self):
        return self._stop or (self.should_stop is not None and self.should_stop())

    def _shared(self):
        try:
            self.map = self._assemble(self.runs, self._run.mapped().results)
        except BaseException as err:  # handed to ``result``
            self._error = err

    def _assemble(self, runs, shares):
        out = np.zeros((max(len(self.ys) - 1, 0), max(len(self.xs) - 1, 0)), dtype=bool)
        for run, bands in zip(runs, shares):
            for r0, band in zip(run, bands):
                out[r0 : r0 + len(band)] = band
        return out

    def result(self):
        """(folds, stride), as ``fold_map`` returns them.

        Raises
        ------
        Cancelled when ``should_stop`` says so.
        """
        if self._thread is None:
            stop = self.should_stop
            bands = _fold_bands(self.fld, self.xs, self.ys, self.rows, self.starts, stop, self.cols)
            return self._assemble([self.starts], [bands]), 1
        self._run.help()  # the runs no worker has taken yet are counted here
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self.map, 1

    def close(self):
        """Stop the count if it still runs and wait for it to end."""
        if self._thread is not None and self._thread.is_alive():
            self._stop = True
            self._thread.join()


def fold_plan(width, height, k, available):
    """How ``fold_map`` counts an image ``width`` x ``height`` whose rays have ``k``
    vertices with ``available`` (int) processes: (workers, rows), the worker processes
    sharing the bands with this one (0: none, they are all counted here) and the image
    rows of a band. Bands hold at most ``FOLD_CHUNK_VERTICES`` vertices; an image of
    ``FOLD_SHARED_MIN_PIXELS`` or more is shared among ``available`` processes, this one
    and ``available - 1`` workers (this one counts once it has measured the kept rays:
    a worker more would only take the core from it), on bands cut small enough for
    ``SMALL_BANDS`` a process where full ones would give one fewer than
    ``MIN_SHARED_BANDS``."""
    rows = max(2, FOLD_CHUNK_VERTICES // (int(width) * int(k)))
    if int(available) < 2 or int(width) * int(height) < FOLD_SHARED_MIN_PIXELS:
        return 0, rows
    sharing = int(available)
    if len(range(0, int(height) - 1, rows - 1)) < sharing * MIN_SHARED_BANDS:
        rows = min(rows, max(2, (int(height) - 1) // (sharing * SMALL_BANDS) + 2))
    return sharing - 1, rows


def fold_workers(size, k, processes=1):
    """int, the worker processes ``fold_map`` shares the count of an image of ``size``
    (width, height) among, for rays of ``k`` vertices (0: none, it runs here)."""
    return fold_plan(*size, k, worker_count(processes))[0]


def fold_columns(rows, k):
    """int, the most lattice columns a piece of a band of ``rows`` rows holds for rays of
    ``k`` vertices: ``FOLD_CHUNK_VERTICES`` of them (at least 2). A band of two rows
    still too wide (long rays on a wide image) is counted a piece at a time."""
    return max(2, FOLD_CHUNK_VERTICES // (int(rows) * int(k)))


def _fold_bands(fld, xs, ys, rows, starts, context, cols=None):
    """The fold maps of the lattice bands starting at rows ``starts`` of ``ys`` (each
    ``rows`` rows, the last shorter), a list of (rows - 1, len(xs) - 1) bool; what
    ``fold_map`` runs here or in a worker. ``context``: the cancel check asked before
    every band (``fold_map``'s ``should_stop``, or the run's ``Context``, which in a
    worker beats too), or None. Only the quads ``kept_limits`` leaves to check are
    checked, and only their pixels' rays are made, in pieces of at most ``cols``
    lattice columns (``fold_columns``; None: whole bands), each piece's last column the
    next one's first."""
    out = []
    for r0 in starts:
        check_stop(context)
        band = ys[r0 : r0 + rows]
        limit = kept_limits(fld, band, xs)
        folds = np.zeros((len(band) - 1, len(xs) - 1), dtype=bool)
        out.append(folds)
        need = np.zeros((len(band), len(xs)), dtype=bool)
        for dy in (0, 1):
            for dx in (0, 1):
                need[dy : dy + len(band) - 1, dx : dx + len(xs) - 1] |= limit != 0
        held = np.flatnonzero(need.any(axis=0))
        if len(held) == 0:
            continue
        c0, c1 = held[0], held[-1] + 1  # the lattice's columns that hold them
        width = c1 - c0 if cols is None else int(cols)
        for a in range(c0, max(c1 - 1, c0 + 1), width - 1):
            b = min(a + width, c1)
            if a > c0:
                check_stop(context)
            _fold_piece(fld, band, xs, limit, need, a, b, folds)
    return out


def _fold_piece(fld, band, xs, limit, need, a, b, folds):
    """Count the quads of lattice columns ``a`` to ``b`` (excluded) of a band (``band``:
    its rows of ``ys``; ``limit``, ``need``: its quads' ``kept_limits`` and the pixels
    whose rays they need) into ``folds`` (the band's map, columns a to b - 1)."""
    cams = fld.rig.cameras
    sub = need[:, a:b]
    if b - a < 2 or not sub.any():
        return
    iy, ix = np.nonzero(sub)
    iy, ix = band[iy], xs[a:b][ix]
    planes = fld.vertex_planes(ix, iy)  # (3, P, K) float64
    k = planes.shape[-1]
    exit_index = fld.exit_index(ix, iy)
    counts = None if exit_index is None else exit_index + 1
    active = bending_active_on_planes(planes, cams[-1], counts, cams[:-1])
    verts = np.zeros((3, *sub.shape, k))
    verts[:, sub] = planes
    on = np.zeros((*sub.shape, k), dtype=bool)
    on[sub] = active
    folds[:, a : b - 1] = quad_folds_on_planes(verts, on, np.minimum(limit[:, a : b - 1], k))


def kept_limits(fld, ys, xs):
    """(len(ys) - 1, len(xs) - 1) int: the sections of each quad of the lattice ``ys`` x
    ``xs`` that can fold, counted from the first (``quad_folds``' ``limit``): all of
    them (a large number), unless the field lays kept rays out exactly (``exact_kept``)
    and the quad's four pixels are kept by one camera i:

    - camera 1: none. The four rays are camera 1's pinhole rays from their first vertex
      on (on camera 1's near plane): every section normal to one of them, through a
      point in front of the eye, is a projective image of the image plane, seen from
      the eye, in which each corner triangle keeps the orientation of the pixel
      centres' triangle (its signed area along the normal is det(X1 - e, X2 - e,
      X3 - e) over the plane's distance from the eye, and the points X = e + t d lie at
      t > 0 on the pixels' directions d: the sign of det(d1, d2, d3), fixed).
    - camera i > 1: those up to vertex ``near_vertex(i) + 1`` of ray a, the first
      vertex past the near-plane point p_i of its own pixel. From there on each section
      meets the four rays where they are camera i's pinhole rays (the neighbours' p_i
      lie a pixel's footprint from a's, a stage's segment short of the plane, and the
      walk starts at a's arc length, on their straight parts), and every such section
      orients the triangles alike (as above), so one of them says what all of them
      say: whether the rays are turned there against the first section.
    """
    masks = fld.rig.masks
    out = np.full((len(ys) - 1, len(xs) - 1), np.iinfo(np.int16).max, dtype=np.int16)
    if not fld.exact_kept or len(ys) < 2 or len(xs) < 2:
        return out
    corners = _quad_owners(masks, ys, xs)
    a = corners[0]
    kept = (a >= 0) & (corners == a).all(axis=0)
    for i in range(len(masks)):
        out[kept & (a == i)] = 0 if i == 0 else fld.near_vertex(i) + 2
    return out


def measure(fld, processes=1, diag=None):
    """Preserved errors per camera and folds of a prepared RayField; ``processes``: the
    fold count's workers (``fold_map``); ``diag`` (core.diagnostics.Diagnostics or
    None): the measure's cancel check and its stages (``measure_map``).

    Returns
    -------
    cameras : list of dict (schema "cameras" entries). folds : int.
    A field measured while it was built (AUTO measures its candidates) keeps its
    measurement as ``fld.measured``; it is returned as is.
    """
    done = getattr(fld, "measured", None)
    if done is not None:
        return done
    cameras, folds, _stride = measure_map(fld, processes, diag)
    return cameras, int(folds.sum())


def measure_map(fld, processes=1, diag=None):
    """``measure`` with the fold map itself: cameras (list of dict), folds ((Hy - 1,
    Wx - 1) bool, ``fold_map``'s) and the map's stride (int).

    A count shared among workers (``FoldCount``) runs while this process measures the
    preserved errors, so that both cores work through both. ``diag``
    (core.diagnostics.Diagnostics or None) gets the seconds of the preserved errors
    along the rays (stage "measure") and of the fold count after them (stage "folds":
    what is left of it); its cancel check is asked before each camera, each block of
    ``along_ray`` and each band of the fold count (raises ``Cancelled``, the count
    stopped either way)."""
    diag = diagnostics_of(diag)
    count = FoldCount(fld, processes, diag.should_stop)
    try:
        with diag.stage("measure"):
            cameras = measure_cameras(fld, diag.should_stop)
        with diag.stage("folds"):
            folds, stride = count.result()
    finally:
        count.close()
    return cameras, folds, stride


def measure_cameras(fld, should_stop=None):
    """The report's "cameras" entries of ``fld``: each camera's preserved error along
    the rays of its eroded mask (``preserved_error``), or why it has none; a list of
    dict. ``should_stop`` (callable () -> bool or None) is asked before each camera and
    each block of ``along_ray`` (raises ``Cancelled``)."""
    rig = fld.rig
    cameras = []
    for i, cam in enumerate(rig.cameras):
        check_stop(should_stop)
        ix, iy = measured_pixels(rig.masks[i])
        if len(ix) == 0:  # nothing to measure: said, and the build goes on
            cameras.append(unmeasured_camera(cam.name, no_pixels_reason(rig.masks[i])))
            continue
        pres = _preserved_in_blocks(fld, i, ix, iy, should_stop)
        err, angle = pres.summary()
        entry = {"name": cam.name, "pixels": pres.pixels, "preserved_px": err, "angle_deg": angle}
        missed = pres.unmeasured()
        if missed:
            entry["unmeasured"] = NEVER_CROSS.format(missed=missed, pixels=pres.pixels)
        cameras.append(entry)
    return cameras


def _preserved_in_blocks(fld, i, ix, iy, should_stop):
    """``preserved_error`` of camera ``i`` over the rays of pixels ``ix``, ``iy`` ((P,)
    int), made as coordinate planes (``RayField.vertex_planes``: no bundle's other
    arrays), ``ALONG_BLOCK_VERTICES`` vertices at a time where the field's rays are
    long (``RayField.ray_vertices``), so that its rays and ``along_ray``'s temporaries
    are held for a block at once, not for every measured pixel (on the nested 1000x rig
    at 480x270 a camera's 20,000 measured rays of 426 vertices held 256 MB; at 1920x1080
    they are about 1.6 times as long, and the report's measure was where the build
    peaked). A ray's figures move by float32 rounding alone: laid out with fewer others,
    it runs on past its trace in fewer float32 vertices along the same line."""
    k = fld.ray_vertices()
    block = len(ix) if k is None else max(1, ALONG_BLOCK_VERTICES // k)
    parts = []
    for s in range(0, len(ix), block):
        bx, by = ix[s : s + block], iy[s : s + block]
        planes = fld.vertex_planes(bx, by)
        parts.append(preserved_error_on_planes(fld.rig.cameras, i, planes, bx, by, should_stop))
    if len(parts) == 1:
        return parts[0]
    return Preserved(
        sum(p.pixels for p in parts),
        np.concatenate([p.error_px for p in parts]),
        np.concatenate([p.angle_deg for p in parts]),
    )


def _quad_owners(masks, ys, xs):
    """(4, len(ys) - 1, len(xs) - 1) int: the camera keeping each corner (a, b, c, d, as
    ``quad_folds`` orders them) of every quad of the lattice ``ys`` x ``xs`` of
    ``masks`` ((N, H, W) bool, one owner at most a pixel), -1 where none does."""
    band = masks[:, ys][:, :, xs]
    owner = np.where(band.any(axis=0), band.argmax(axis=0), -1)
    return np.stack([owner[:-1, :-1], owner[:-1, 1:], owner[1:, 1:], owner[1:, :-1]])


def kept_folds(masks, folds, stride, names):
    """The folds no method can avoid: quads whose four pixels every camera's mask keeps.

    A preserved pixel's ray is its camera's own, whatever the method; so where masks of
    two cameras touch (they overlapped, and the smaller camera kept the shared pixels,
    or were painted edge to edge) the rays of a quad across the seam are fixed, and if
    they cross, every method's do.

    Parameters
    ----------
    masks : (N, H, W) bool, at most one True per pixel. folds : (Hy - 1, Wx - 1) bool,
    ``fold_map``'s, on the lattice of ``stride``. names : N str.

    Returns
    -------
    count : int, folded quads whose four pixels are all kept (by any cameras).
    pairs : list of (str, str), the cameras whose masks meet in them, in rig order.
    """
    n, h, w = masks.shape
    xs = np.unique(np.append(np.arange(0, w, stride), w - 1))
    ys = np.unique(np.append(np.arange(0, h, stride), h - 1))
    corners = _quad_owners(masks, ys, xs)
    fixed = folds & (corners >= 0).all(axis=0)
    seen = corners[:, fixed]
    low, high = seen.min(axis=0), seen.max(axis=0)
    pairs = sorted({(int(a), int(b)) for a, b in zip(low, high) if a != b})
    return int(fixed.sum()), [(names[a], names[b]) for a, b in pairs]


def transition_folds(weights, masks, folds, names):
    """The folds in transitions, by the two cameras whose transition holds them.

    Parameters
    ----------
    weights : (N, H, W) float, each pixel's camera weights (IMAGE_BLEND's). masks : (N,
        H, W) bool, at most one True per pixel. folds : (H - 1, W - 1) bool,
        ``fold_map``'s (stride 1). names : N str.

    Returns
    -------
    list of ((str, str), int): for each pair of cameras, in rig order, the folded quads
    not kept whole by masks (``kept_folds`` has those) whose two largest weights, summed
    over the quad's four pixels, are that pair's; most folds first.
    """
    owned = np.asarray(masks).any(axis=0)
    whole = owned[:-1, :-1] & owned[:-1, 1:] & owned[1:, 1:] & owned[1:, :-1]
    open_ = folds & ~whole
    if not open_.any():
        return []
    iy, ix = np.nonzero(open_)
    # the weights of the folded quads alone, in float64 (not the whole image's)
    wt = [
        np.asarray(weights[:, y, x], dtype=np.float64)
        for y, x in ((iy, ix), (iy, ix + 1), (iy + 1, ix), (iy + 1, ix + 1))
    ]
    quad = wt[0] + wt[1] + wt[2] + wt[3]
    top = np.argsort(-quad, axis=0, kind="stable")[:2]
    n = len(names)
    counts = np.bincount(top.min(axis=0) * n + top.max(axis=0), minlength=n * n)
    pairs = np.flatnonzero(counts)  # (low, high) in rig order
    out = [((names[p // n], names[p % n]), int(counts[p])) for p in pairs]
    return sorted(out, key=lambda pc: -pc[1])


# Why a camera's figures are null (schema key "unmeasured" of a camera).
EMPTY_MASK = "its mask is empty: no preserved pixel to measure"
THIN_MASK = (
    "its mask keeps no pixel once eroded by {px} px for measuring (too small or too thin "
    "at this render size); its pixels render, unmeasured"
)
NEVER_CROSS = (
    "{missed} of {pixels} measured rays never cross the camera's near plane (cameras out "
    "of order, largest scale first, or a near plane inside other geometry?)"
)
NULL_FIGURES = {"p50": None, "p95": None, "max": None}


def no_pixels_reason(mask):
    """Why a camera's (H, W) bool ``mask`` gives no pixel to measure."""
    return EMPTY_MASK if not mask.any() else THIN_MASK.format(px=ERODE_PX)


def unmeasured_camera(name, reason):
    """The "cameras" entry of a camera with nothing measured: null figures, a reason."""
    return {
        "name": name,
        "pixels": 0,
        "preserved_px": dict(NULL_FIGURES),
        "angle_deg": dict(NULL_FIGURES),
        "unmeasured": reason,
    }


def build_report(fld, quality, total_seconds=None, processes=1, diag=None):
    """The report of a prepared field as a dict of schema version 2.

    Parameters
    ----------
    fld : RayField. quality : str, the quality enum name.
    total_seconds : float, wall time of the build (default: the sum of the stages).
    processes : int, the fold count's worker processes (``fold_map``; the build's
    ``Settings.processes``, so Blender's Threads setting holds for it too).
    diag : core.diagnostics.Diagnostics or None, the measure's cancel check and stages
    (``measure_map``; raises ``Cancelled``).
    """
    cameras, folds = measure(fld, processes, diag)
    seconds = {k: float(fld.seconds.get(k, 0.0)) for k in ("fill", "solve", "tangents", "trace")}
    seconds["total"] = float(total_seconds if total_seconds is not None else sum(seconds.values()))
    return {
        "version": VERSION,
        "method": fld.method,
        "quality": quality,
        "grids": [list(map(int, g)) for g in fld.grids],
        "seconds": seconds,
        "solver": {
            "iterations": int(fld.solver.get("iterations", 0)),
            "residual": float(fld.solver.get("residual", 0.0)),
            "converged": bool(fld.solver.get("converged", True)),
        },
        "cameras": cameras,
        "folds": folds,
        "stalled": int(fld.stats.get("stalled", 0)),
        "conflicts": int(fld.stats.get("conflicts", 0)),
        # added in version 2: tangent evaluations where Newton's inversion of a ray family
        # failed (the point took camera 1's direction), rays the trace's step limit cut
        "newton_lost": int(fld.stats.get("newton_lost", 0)),
        "unfinished": int(fld.stats.get("unfinished", 0)),
        "warnings": list(fld.warnings),
        # added keys: why AUTO chose the method (absent otherwise); grid levels (1 for one
        # uniform grid, more for nested grids, 0 without a 3D grid)
        **({"auto": fld.stats["auto"]} if "auto" in fld.stats else {}),
        "levels": int(fld.stats.get("levels", len(fld.grids))),
    }


def headline(report):
    """One line for the panel: worst p95 error, folds, time."""
    p95 = [c["preserved_px"]["p95"] for c in report["cameras"]]
    worst = max((v for v in p95 if v is not None), default=0.0)
    unmeasured = sum(1 for c in report["cameras"] if c.get("unmeasured"))
    return (
        f"{report['method']}: p95 error {worst:.2f} px, {report['folds']} folds, "
        f"{report['seconds']['total']:.1f} s"
        + (f", {unmeasured} camera(s) not measured" if unmeasured else "")
    )


def strict(value):
    """``value`` (dicts, lists, numbers, numpy scalars) with every NaN or infinite float
    as None: what strict JSON can hold."""
    if isinstance(value, dict):
        return {k: strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def to_json(report):
    """The report as the strict JSON string stored in ``scene.multiscale.report`` (no
    NaN or Infinity: ``null``, with the camera's "unmeasured" reason)."""
    return json.dumps(strict(report), indent=1, allow_nan=False, default=str)


def readable(report):
    """The report as lines of text for people: the headline, then per camera and for the
    build what each figure means."""
    lines = [headline(report), ""]
    for cam in report.get("cameras", []):
        err, ang = cam["preserved_px"], cam["angle_deg"]
        if cam.get("unmeasured") and err["p95"] is None:
            lines.append(f"'{cam['name']}': not measured: {cam['unmeasured']}")
            continue
        surface = (cam.get("surface_px") or {}).get("p95")
        lines.append(
            f"'{cam['name']}': {cam['pixels']} preserved pixels measured; error along the "
            f"ray p50 {_figure(err['p50'])}, p95 {_figure(err['p95'])}, max "
            f"{_figure(err['max'])} px; angle p95 {_figure(ang['p95'])} deg"
            + (f"; at the visible surface p95 {surface:.2f} px" if surface is not None else "")
            + (f" ({cam['unmeasured']})" if cam.get("unmeasured") else "")
        )
    s = report.get("seconds", {})
    lines.append("")
    lines.append(
        "Time: "
        + ", ".join(f"{k} {s[k]:.1f} s" for k in ("fill", "solve", "tangents", "trace") if k in s)
        + f" (total {s.get('total', 0.0):.1f} s{', cached' if report.get('cached') else ''})"
    )
    solver = report.get("solver", {})
    lines.append(
        f"Solver: {solver.get('iterations', 0)} iterations, residual "
        f"{solver.get('residual', 0.0):.1e}, "
        + ("converged" if solver.get("converged") else "NOT converged")
    )
    lines.append(
        f"Grids: {', '.join('x'.join(map(str, g)) for g in report.get('grids', [])) or 'none'}"
    )
    lines.append(
        f"Folds: {report.get('folds', 0)} (quads of neighbouring rays that cross)"
        f"; stalled rays: {report.get('stalled', 0)}; Newton failures: "
        f"{report.get('newton_lost', 0)}"
    )
    warnings = report.get("warnings", [])
    if warnings:
        lines.append("")
        lines.append("Warnings:")
        lines += [f"- {w}" for w in warnings]
    return lines


def _figure(value):
    """A report figure for people: two decimals, or "none" for a null one."""
    return "none" if value is None else f"{value:.2f}"
