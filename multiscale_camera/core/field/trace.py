"""Streamlines of a vector field by explicit Runge-Kutta steps (paper section 4.5).

Rays follow dx/ds = v(x) / |v(x)|: the field gives only the direction, so ``s`` is arc
length and a fixed step ``h`` advances every ray by the same distance along its curve.
The field's raw speed |v| is used only to detect stalls. The step is driven by a
Butcher tableau (as in scipy.integrate's ``rk.py``): ``RK4`` by default, ``MIDPOINT``
for a cheaper second-order trace.

All rays of a chunk advance together, vectorised; a ray that stops leaves the active
set, so later stages evaluate the field only where rays are still running. Why each
ray stopped is a ``StopReason``, as VTK's stream tracer records it. ``Traced`` holds a
trace's rays resampled to one layout; ``merge`` gathers the parts of a shared trace.
"""

import enum
from dataclasses import dataclass, replace

import numpy as np

from ..geometry import dot3
from ..runtime import release_free_memory, runtime
from .plane_step import schedule_of

# Rays traced together: bounds the memory of the state, the stages and the vertex
# buffer (about 65536 * K * 12 bytes for K recorded vertices).
CHUNK_RAYS = 65536

# Ask ``should_stop`` every this many steps inside a chunk too, so a long chunk can
# still be cancelled within a fraction of a second.
STOP_CHECK_STEPS = 16

# A ray whose arc length is within this fraction of a step of ``max_length`` has
# reached it (the last step is shortened to land there, up to rounding).
LENGTH_TOLERANCE = 1e-9

# Vertex slots allocated per ray before the buffer has to grow (it doubles).
INITIAL_VERTICES = 64


class StopReason(enum.IntEnum):
    """Why a streamline ended (stored as int8 in ``Streamlines.reason``)."""

    RUNNING = 0  # not traced to the end: the trace was cancelled by ``should_stop``
    LEFT_GRID = 1  # the last step ended outside the region (``inside`` was False)
    STALLED = 2  # the field's speed at the last vertex fell below ``stall_speed``
    REACHED_LIMIT = 3  # ``max_steps`` steps taken or ``max_length`` arc length reached


@dataclass(frozen=True)
class Tableau:
    """An explicit Runge-Kutta method for an autonomous system.

    Attributes
    ----------
    name : str
    order : int, the global order of accuracy.
    a : tuple of tuples of float, the strictly lower-triangular stage coefficients:
        ``a[i]`` has ``i`` entries (stage i uses k_0 .. k_{i-1}).
    b : tuple of float, the weights of the stages in the step; they sum to one.
    """

    name: str
    order: int
    a: tuple
    b: tuple

    def __post_init__(self):
        if len(self.a) != len(self.b) or any(len(r) != i for i, r in enumerate(self.a)):
            raise ValueError(f"Tableau {self.name}: a must be strictly lower triangular")
        if abs(sum(self.b) - 1.0) > 1e-12:
            raise ValueError(f"Tableau {self.name}: weights b must sum to 1")


RK4 = Tableau(
    "RK4",
    4,
    a=((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0)),
    b=(1 / 6, 1 / 3, 1 / 3, 1 / 6),
)
MIDPOINT = Tableau("midpoint", 2, a=((), (0.5,)), b=(0.0, 1.0))


@dataclass(frozen=True)
class Streamlines:
    """Traced streamlines as padded polylines.

    Attributes
    ----------
    points : (R, K, 3) float32, world units. Ray r's vertices are
        ``points[r, :counts[r]]``, in order from its seed (vertex 0). Slots past
        ``counts[r]`` repeat the last vertex, so the padding adds only zero-length
        segments. K is the largest count.
    counts : (R,) int32, valid vertices per ray, at least 1.
    reason : (R,) int8, ``StopReason`` values.
    length : (R,) float64, world units: the arc length integrated (the sum of the
        steps taken). The polyline through the vertices is a chord of the curve, so
        its length is at most this, and equal on straight rays (except a step whose
        later stages found no field, which moves less than its length).

    Notes
    -----
    For a ray that left the region, the last two vertices are its last point inside
    and the first step end outside, whatever ``record_every`` was.
    """

    points: np.ndarray
    counts: np.ndarray
    reason: np.ndarray
    length: np.ndarray

    def __len__(self):
        return len(self.counts)

    @property
    def ends(self):
        """(R, 3) float32, world units: the last valid vertex of each ray."""
        return self.points[np.arange(len(self.counts)), self.counts - 1]

    @property
    def complete(self):
        """bool: every ray was traced to a stop (the trace was not cancelled)."""
        return bool((self.reason != StopReason.RUNNING).all())


def rk4_streamlines(
    velocity,
    seeds,
    step,
    max_steps,
    max_length=np.inf,
    stall_speed=1e-3,
    inside=None,
    record_every=1,
    should_stop=None,
    tableau=RK4,
    chunk=CHUNK_RAYS,
    with_rays=False,
    split=None,
):
    """Trace one streamline from every seed through a vector field.

    Parameters
    ----------
    velocity : callable, (P, 3) float64 world points -> (P, 3) float array, the field
        (any units; only its direction and, for the stall test, its length matter).
        It may be called with any P up to ``chunk`` and with points outside the
        region (intermediate stages of a step that leaves it).
    seeds : (R, 3) float, world units: the first vertex of each ray.
    step : float, world units: arc length per step; or a callable, (P, 3) float64
        points -> (P,) float64 positive lengths, the step to take from each point (a
        step that follows the field's local scale; it needs a finite ``max_steps`` and
        no ``max_length``). Vertex k is then the k-th step's end.
    max_steps : int, steps after which a ray stops with REACHED_LIMIT; may be
        ``np.inf`` when ``max_length`` is finite.
    max_length : float, world units: arc length after which a ray stops with
        REACHED_LIMIT; its last step is shortened to land exactly there.
    stall_speed : float, field units: a ray whose field speed at its current vertex
        is below this (or not finite) stops there, STALLED. A stage of a step that
        lands where the speed is exactly zero contributes no direction.
    inside : callable, (P, 3) float64 -> (P,) bool, the region (e.g. ``Grid.contains``);
        default: everywhere. A seed outside stops at once (LEFT_GRID, one vertex).
    record_every : int, keep every n-th step's vertex (plus the seed and the last one).
    should_stop : callable () -> bool, asked before each chunk and every
        ``STOP_CHECK_STEPS`` steps; when it returns True the trace ends: rays not yet
        stopped keep RUNNING, with their vertices so far (untraced ones: the seed).
    tableau : Tableau, the Runge-Kutta method (``RK4`` or ``MIDPOINT``).
    chunk : int, rays traced together.
    with_rays : bool, call ``velocity(points, rays)`` instead, ``rays`` (P,) int64 being
        the indices into ``seeds`` of the rays the points belong to (the same at every
        stage of a step), so the field can keep per-ray state such as warm starts.
    split : callable ``(points (P, 3), directions (P, 3), rays (P,), step) -> (P,)``
        or None: the arc length at which a step from each point should be cut in two,
        or ``step`` for no cut. A step that straddles a surface where the field is only
        once differentiable loses RK4's order; two sub-steps meeting on the surface keep
        it. Only the step's end is recorded, so vertex k still lies at arc length k * step.

    Returns
    -------
    Streamlines with R rays.
    """
    seeds = np.asarray(seeds, dtype=np.float64)
    if seeds.ndim != 2 or seeds.shape[1] != 3:
        raise ValueError(f"Seeds must be (R, 3), got {seeds.shape}")
    if callable(step):
        if np.isfinite(max_length) or not np.isfinite(max_steps):
            raise ValueError("A step function needs a finite max_steps and no max_length")
    elif not step > 0:
        raise ValueError(f"Step must be a positive length, got {step}")
    if int(record_every) < 1:
        raise ValueError(f"record_every must be at least 1, got {record_every}")
    if not np.isfinite(max_steps):
        if not np.isfinite(max_length):
            raise ValueError("Give a finite max_steps or max_length, or rays never stop")
        max_steps = np.ceil(max(max_length, 0.0) / step) + 1
    tracer = _Tracer(
        velocity,
        step if callable(step) else float(step),
        max(int(max_steps), 0),
        float(max_length),
        float(stall_speed),
        inside,
        int(record_every),
        should_stop,
        tableau,
        with_rays,
        split,
    )
    count = len(seeds)
    reason = np.zeros(count, dtype=np.int8)
    length = np.zeros(count, dtype=np.float64)
    counts = np.ones(count, dtype=np.int32)
    pieces = []
    for start in range(0, count, max(int(chunk), 1)):
        stop = min(start + max(int(chunk), 1), count)
        if tracer.cancelled or (should_stop is not None and should_stop()):
            tracer.cancelled = True
            pieces.append((start, seeds[None, start:stop].astype(np.float32)))
            continue
        buf, counts[start:stop], reason[start:stop], length[start:stop] = tracer.trace(
            seeds[start:stop], start
        )
        pieces.append((start, buf))
    return Streamlines(_assemble(pieces, counts), counts, reason, length)


class _Tracer:
    """The settings of one trace; ``trace`` runs a chunk of rays."""

    def __init__(
        self,
        velocity,
        step,
        max_steps,
        max_length,
        stall_speed,
        inside,
        record_every,
        should_stop,
        tableau,
        with_rays,
        split,
    ):
        self.velocity = velocity
        self.split = split
        self.with_rays = with_rays
        self.step = step
        self.max_steps = max_steps
        self.max_length = max_length
        self.stall_speed = stall_speed
        self.inside = inside
        self.every = record_every
        self.should_stop = should_stop
        self.a = [[(j, c) for j, c in enumerate(row) if c != 0.0] for row in tableau.a]
        self.b = [(j, c) for j, c in enumerate(tableau.b) if c != 0.0]
        self.cancelled = False
        steps = max_steps
        if np.isfinite(max_length) and not callable(step):
            steps = min(steps, int(np.ceil(max(max_length, 0.0) / step)) + 1)
        # Seed, every n-th step, last point inside and the final point.
        self.most_vertices = steps // record_every + 3

    def _field(self, x, rays):
        """Field at x: unit directions (P, 3) float64 and speeds (P,) float64."""
        v = self.velocity(x, rays) if self.with_rays else self.velocity(x)
        v = np.asarray(v, dtype=np.float64)
        speed = np.sqrt(dot3(v, v))
        inv = np.divide(1.0, speed, out=np.zeros_like(speed), where=speed > 0)
        return v * inv[:, None], speed

    def trace(self, seeds, first):
        """Trace a chunk: returns (vertices (K, n, 3) float32 slot-major, unpadded;
        counts; reason; length). ``first`` is the index of seeds[0] among all seeds."""
        n = len(seeds)
        rec = _Vertices(n, min(INITIAL_VERTICES, self.most_vertices), self.most_vertices)
        reason = np.zeros(n, dtype=np.int8)
        length = np.zeros(n, dtype=np.float64)
        ids = np.arange(n)
        x = seeds.copy()
        rec.add(ids, x)
        if self.max_steps == 0 or self.max_length <= 0:
            reason[:] = StopReason.REACHED_LIMIT
            return rec.trimmed(), rec.counts, reason, length
        if self.inside is not None:
            out = ~np.asarray(self.inside(x), dtype=bool)
            reason[ids[out]] = StopReason.LEFT_GRID
            ids, x = ids[~out], x[~out]
        s = np.zeros(len(ids))
        for n_step in range(1, self.max_steps + 1):
            if not len(ids):
                break
            if (
                self.should_stop is not None
                and n_step % STOP_CHECK_STEPS == 0
                and self.should_stop()
            ):
                self.cancelled = True
                if (n_step - 1) % self.every:
                    rec.add(ids, x)
                break
            previous_recorded = (n_step - 1) % self.every == 0
            k0, speed = self._field(x, ids + first)
            stalled = ~(speed >= self.stall_speed) | np.isinf(speed)  # NaN and inf too
            if stalled.any():
                reason[ids[stalled]] = StopReason.STALLED
                if not previous_recorded:
                    rec.add(ids[stalled], x[stalled])
                length[ids[stalled]] = s[stalled]
                keep = ~stalled
                ids, x, s, k0 = ids[keep], x[keep], s[keep], k0[keep]
                if not len(ids):
                    break
            h = self._lengths(x, s)
            x_new = self._split_step(x, k0, h, ids + first)
            s += h
            left = np.zeros(len(ids), dtype=bool)
            if self.inside is not None:
                left = ~np.asarray(self.inside(x_new), dtype=bool)
            limit = ~left & (
                (n_step == self.max_steps) | (s >= self.max_length - LENGTH_TOLERANCE * h)
            )
            if left.any():
                reason[ids[left]] = StopReason.LEFT_GRID
                if not previous_recorded:
                    rec.add(ids[left], x[left])
                rec.add(ids[left], x_new[left])
            if n_step % self.every == 0:
                keep_vertex = ~left
                rec.add(ids[keep_vertex], x_new[keep_vertex])
            elif limit.any():
                rec.add(ids[limit], x_new[limit])
            reason[ids[limit]] = StopReason.REACHED_LIMIT
            done = left | limit
            if done.any():
                length[ids[done]] = s[done]
                keep = ~done
                ids, x_new, s = ids[keep], x_new[keep], s[keep]
            x = x_new
        length[ids] = s  # rays cut short by cancelling
        return rec.trimmed(), rec.counts, reason, length

    def _lengths(self, x, s):
        """(P,) float64: the length of the next step from points ``x`` at arc lengths
        ``s``."""
        if callable(self.step):
            return np.asarray(self.step(x), dtype=np.float64)
        return np.minimum(self.step, self.max_length - s)

    def _split_step(self, x, k0, h, rays):
        """One step of length h (P,), cut in two where ``split`` asks."""
        if self.split is None:
            return self._step(x, k0, h[:, None], rays)
        first = np.clip(self.split(x, k0, rays, h), 0.0, h)
        cut = (first > 1e-9 * h) & (first < (1.0 - 1e-9) * h)
        # the whole steps and the cut steps' first parts share their stages' field
        # evaluations: a few cut rays would otherwise cost as many calls as all the rest
        out = self._step(x, k0, np.where(cut, first, h)[:, None], rays)
        if cut.any():
            mid = out[cut]
            k_mid = self._field(mid, rays[cut])[0]
            out[cut] = self._step(mid, k_mid, (h - first)[cut, None], rays[cut])
        return out

    def _step(self, x, k0, h, rays):
        """One explicit RK step of length h (P, 1) from x (P, 3) with k0 = f(x)."""
        ks = [k0]
        for row in self.a[1:]:
            incr = sum(c * ks[j] for j, c in row)
            ks.append(self._field(x + h * incr, rays)[0])
        incr = sum(c * ks[j] for j, c in self.b)
        return x + h * incr


class _Vertices:
    """Per-ray vertex lists of a chunk in one growing (capacity, n, 3) float32 buffer.

    Slot-major, because rays still running share their vertex count: recording a step
    writes one contiguous (n, 3) slab instead of scattering n rows.
    """

    def __init__(self, n, capacity, most):
        self.buf = np.empty((max(capacity, 1), n, 3), dtype=np.float32)
        self.counts = np.zeros(n, dtype=np.int32)
        self.most = most

    def add(self, ids, points):
        if not len(ids):
            return
        slots = self.counts[ids]
        first, need = int(slots.min()), int(slots.max()) + 1
        if need > len(self.buf):
            grown = min(max(2 * len(self.buf), need), max(self.most, need))
            buf = np.empty((grown, *self.buf.shape[1:]), dtype=np.float32)
            buf[: len(self.buf)] = self.buf
            self.buf = buf
        if first + 1 < need:
            self.buf[slots, ids] = points
        elif len(ids) == self.buf.shape[1]:
            self.buf[first] = points
        else:
            self.buf[first, ids] = points
        self.counts[ids] = slots + 1

    def trimmed(self):
        """(K, n, 3) float32, K the largest count."""
        return self.buf[: int(self.counts.max(initial=1))]


def _assemble(pieces, counts):
    """Padded (R, K, 3) float32 from slot-major (K_chunk, n, 3) chunk buffers: slots
    past a ray's count repeat its last vertex."""
    k = max((len(buf) for _, buf in pieces), default=1)
    out = np.empty((len(counts), k, 3), dtype=np.float32)
    for start, buf in pieces:
        out[start : start + buf.shape[1], : len(buf)] = buf.transpose(1, 0, 2)
    short = np.flatnonzero(counts < k)
    if len(short):
        c = counts[short].astype(np.intp)
        missing = k - c
        rows = np.repeat(short, missing)
        first = np.repeat(np.cumsum(missing) - missing, missing)
        slots = np.arange(len(rows)) - first + np.repeat(c, missing)
        out[rows, slots] = np.repeat(out[short, c - 1], missing, axis=0)
    return out


@dataclass(frozen=True)
class Traced:
    """Streamlines of a set of seeds, resampled to a common arc-length layout.

    vertices : (R, K, 3) float32: vertex k at arc length k * step from the seed; after a
        ray stops, its vertices run straight on along its last tangent.
    membership : (R, K) float32, N at each vertex.
    counts : (R,) int32, vertices actually traced (the rest are the straight run-on).
    reason : (R,) int8, ``StopReason`` values.
    step : float, world units; or None when the step followed the local cell size of
        nested grids (vertex k is then the k-th step's end, at no common arc length).
    bands : (R,) int8 or None: how many of the trace's bands at near planes
        (``plane_step.NearPlaneStep``, cameras 2, 3, ... in order) each ray's vertices
        follow: camera i's preserved rays those of cameras 2..i (``up_to``), traced rays
        all. None: every ray follows the whole step.
    """

    vertices: np.ndarray
    membership: np.ndarray
    counts: np.ndarray
    reason: np.ndarray
    step: float
    bands: np.ndarray = None

    @property
    def width(self):
        """int: vertices a ray is laid out with (K)."""
        return self.vertices.shape[1]

    def rows(self, sl):
        """The ``Traced`` of rays ``sl`` (a slice or index array)."""
        bands = None if self.bands is None else self.bands[sl]
        return Traced(
            self.vertices[sl],
            self.membership[sl],
            self.counts[sl],
            self.reason[sl],
            self.step,
            bands,
        )


def straight_tails(verts, counts, step, fallback):
    """Rays run straight on past their last traced vertex at the trace's step, as the
    tracer lays them out (``FieldTracer.trace``): vertex k of every ray at the same arc
    length.

    verts : (R, K, 3) float64, world units; ray r's vertices before ``counts[r]``
        traced, the rest ignored. counts : (R,) int64, 1 .. K. step : the trace's step:
        float (world units), a callable (P, 3) -> (P,) lengths (the step at the last
        vertex runs on), or a ``NearPlaneStep`` (its bands' steps, ``run_lengths``).
    fallback : callable, (m,) int rows -> (m, 3) directions for rays whose last segment
        has no length (a single vertex).

    Returns
    -------
    (R, K, 3) float64, world units: the traced vertices, then the run along the last
    segment's direction."""
    k = verts.shape[1]
    ks = np.arange(k)[None, :]
    rows = np.arange(len(verts))
    last = verts[rows, counts - 1]
    d = last - verts[rows, np.maximum(counts - 2, 0)]
    short = np.linalg.norm(d, axis=-1) < 1e-12
    if short.any():
        d[short] = fallback(np.flatnonzero(short))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    after = ks >= counts[:, None]
    after_last = ks - (counts[:, None] - 1)
    schedule = schedule_of(step)
    if schedule is not None:  # the band's steps, as the trace had them
        run = schedule.run_lengths(last, d, after_last)
    else:
        spacing = step(last)[:, None] if callable(step) else step
        run = after_last * spacing
    return np.where(after[..., None], last[:, None] + d[:, None] * run[..., None], verts)


def run_on(traced, vertices, schedule=None):
    """A ``Traced`` extended to ``vertices`` vertices by running straight on along each
    ray's last segment at the same step; with ``schedule`` (a ``NearPlaneStep``, the
    trace's step) at the steps each ray's own schedule (``Traced.bands``) would have
    taken there, so rays that stop inside a band around a near plane stay in step with
    their neighbours."""
    v, m = traced.vertices, traced.membership
    extra = vertices - v.shape[1]
    if extra <= 0:
        return traced
    d = (v[:, -1] - v[:, -2]).astype(np.float64)
    last = v[:, -1:].astype(np.float64)
    more = np.arange(1, extra + 1)
    tail = np.empty((len(v), extra, 3))
    if schedule is not None:
        bands = traced.bands
        if bands is None:
            bands = np.full(len(v), len(schedule.given[0]), dtype=np.int8)
        for count in np.unique(bands):
            rows = np.flatnonzero(bands == count)
            step = schedule.up_to(int(count))
            length = np.linalg.norm(d[rows], axis=-1, keepdims=True)
            unit = d[rows] / np.maximum(length, 1e-30)
            if schedule_of(step) is not None:  # through its bands
                run = step.run_lengths(last[rows, 0], unit, more[None, :])
            elif callable(step):  # no band, a step that follows the cells: as without one
                run = length * more[None, :]
            else:  # no band: the base step, as laid out
                run = np.broadcast_to(step * more[None, :], (len(rows), extra))
            tail[rows] = last[rows] + unit[:, None] * run[..., None]
    else:
        if traced.step is not None:
            d *= traced.step / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-30)
        # with a step that follows the local cell, the last segment's own length runs on
        tail = last + d[:, None] * more[None, :, None]
    return Traced(
        np.concatenate([v, tail.astype(np.float32)], axis=1),
        np.concatenate([m, np.repeat(m[:, -1:], extra, axis=1)], axis=1),
        traced.counts,
        traced.reason,
        traced.step,
        traced.bands,
    )


def merge(parts, order, total, schedule=None, shared=False):
    """Combine ``Traced`` parts into one, rays placed at ``order`` (one index array per
    part) among ``total`` rays, shorter ones run on (``run_on``, with ``schedule``).
    Consumes ``parts``: each entry is released (set to None) once copied, so a large
    merge holds little more than its result and its largest part.

    ``shared``: the vertices and memberships go into shared memory
    (``Runtime.shared_array``), its pages taken a block at a time as they are written,
    so that workers handed the result (the fold count, the render's tables) map these
    pages rather than a copy of them; where shared memory cannot be had, they go into
    this process's memory as without it."""
    k = max(p.width for p in parts)
    step = parts[0].step
    out = _MergeArrays(total, k, shared)
    counts = np.empty(total, dtype=np.int32)
    reason = np.empty(total, dtype=np.int8)
    banded = any(p.bands is not None for p in parts)
    bands = np.zeros(total, dtype=np.int8) if banded else None
    for j, idx in enumerate(order):
        p, parts[j] = parts[j], None
        counts[idx], reason[idx] = p.counts, p.reason
        if banded:
            bands[idx] = p.bands if p.bands is not None else np.iinfo(np.int8).max
        block = max(1, MERGE_BLOCK_VERTICES // k)
        sub = None
        for s in range(0, len(idx), block):
            sl = slice(s, s + block)
            sub = run_on(replace(p.rows(sl), step=step), k, schedule)
            out.write(idx[sl], sub.vertices, sub.membership)
        del p, sub
        if total * k > MERGE_BLOCK_VERTICES:  # the part's pages back as the result grows
            release_free_memory()
    return Traced(out.verts, out.mem, counts, reason, step, bands)


class _MergeArrays:
    """``merge``'s vertices (total, k, 3) and memberships (total, k), float32: in
    shared memory taken as rows are written, or in this process's memory."""

    def __init__(self, total, k, shared):
        self.verts = self.mem = None
        if shared:
            try:
                pool = runtime()
                self.verts = pool.shared_array((total, k, 3), np.float32, reserve=False)
                self.mem = pool.shared_array((total, k), np.float32, reserve=False)
            except OSError:
                self.verts = self.mem = None
        self.shared = self.mem is not None
        # the rows whose pages are taken (only these are read back on a fall back)
        self.taken = np.zeros(total, dtype=bool) if self.shared else None
        if not self.shared:
            self.verts = np.empty((total, k, 3), dtype=np.float32)
            self.mem = np.empty((total, k), dtype=np.float32)

    def write(self, rows, verts, mem):
        """Write rays ``rows`` ((n,) int): vertices (n, k, 3), memberships (n, k)."""
        if self.shared and len(rows):
            span = slice(int(rows.min()), int(rows.max()) + 1)
            try:
                runtime().shared.reserve(self.verts[span])
                runtime().shared.reserve(self.mem[span])
                self.taken[span] = True
            except OSError:  # /dev/shm is full: the rows written so far move here
                self._here()
        self.verts[rows], self.mem[rows] = verts, mem

    def _here(self):
        """Move to this process's memory (the pages not taken are never touched: on a
        full /dev/shm touching them would fail)."""
        verts = np.empty(self.verts.shape, dtype=np.float32)
        mem = np.empty(self.mem.shape, dtype=np.float32)
        verts[self.taken], mem[self.taken] = self.verts[self.taken], self.mem[self.taken]
        self.verts, self.mem, self.shared, self.taken = verts, mem, False, None


# Ray vertices ``merge`` extends at a time.
MERGE_BLOCK_VERTICES = 1 << 22
