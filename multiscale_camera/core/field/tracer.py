"""The blended field of the paper's ray field (section 4.4, eq. 6) and its streamlines
(section 4.5).

1. Tangents: X_i(x) is the unit tangent of R_i through x, found by inverting the family
   R_i(u, v, tau) with Newton's method, warm-started from the ray's previous position.
   It is exact at any point, so preserved rays do not depend on the grid resolution.
2. Blend (eq. 6): Y = sum_i w(N, i) X_i / sum_i w(N, i), w = 1 - |N - i| clipped at 0
   (or its monotone cubic smoothstep), N the membership solved from ``fill``'s M.
3. Trace: RK4 streamlines of Y (``trace``) from pixel seeds on camera 1's near plane.
"""

import time
from functools import partial

import numpy as np

from ..errors import Cancelled
from ..geometry import Family, dot3, solve3
from ..runtime import runtime, worker_count
from .grid import FieldSampler
from .plane_step import NearPlaneStep, schedule_of
from .preserved_rays import arc_length_rays, first_past_near_plane, scheduled_rays
from .trace import StopReason, Traced, merge, rk4_streamlines, straight_tails

# RK4 step, in cells, at an accuracy target of 0.5 px on an image STEP_WIDTH pixels
# wide. The trace's error in world units falls about as the step cubed (measured 0.22,
# 0.023 and 0.002 px at 2, 1 and 0.5 cells on a 4x rig at 1920x1080); cells do not
# depend on the image size, so in pixels it grows with the width. The step scales with
# the cube root of the target over the width, but a smaller image lengthens it by at
# most STEP_WIDTH_GAIN: a transition two cells wide is the narrowest the cells hold,
# and a longer step lets neighbouring rays sample it differently (on the 1000x rig at
# 480x270: no folds at 2 and 2.25 cells, 3 folded quads at 2.4).
STEP_CELLS = 1.5
STEP_WIDTH = 1920
STEP_WIDTH_GAIN = 4.0 / 3.0


def step_cells(accuracy_px, width=STEP_WIDTH):
    """RK4 step in cells (float, 0.5 to 3) for an accuracy target in pixels on an image
    ``width`` pixels wide."""
    gain = min((STEP_WIDTH / max(width, 1)) ** (1.0 / 3.0), STEP_WIDTH_GAIN)
    ratio = accuracy_px / 0.5
    return float(np.clip(STEP_CELLS * gain * ratio ** (1.0 / 3.0), 0.5, 3.0))


# A ray stalls where the blended tangents cancel to less than this length.
STALL_SPEED = 1e-3
# Newton iterations per tangent evaluation when warm-started from a point one step away.
WARM_ITERATIONS = 2
# ... and when the start is predicted from the Jacobian where the ray's last evaluation
# converged (``FieldTracer._tangent``): its error is already about the square of the
# distance moved, and one step squares it again.
PREDICTED_ITERATIONS = 1
# Newton's tolerance in the trace, a fraction of the local scale: a point that far off
# turns the tangent by about as many radians, far below what a step's error does (on
# the 1000x rig at 240x135, 1e-6 and 1e-9 trace the same rays to the report's
# precision, with 9% fewer family evaluations).
TRACE_NEWTON_TOLERANCE = 1e-6


# A trace is shared among worker processes only when each gets at least this many
# rays: sending the work out and the rays back cost more than tracing fewer.
MIN_RAYS_PER_PROCESS = 256
# ... and in shares of at most this many rays, so that no worker holds more than a few
# hundred megabytes of rays at once (they come back pickled).
MAX_RAYS_PER_SHARE = 16384
# Ray vertices completed (run-on, membership) at a time after a trace, and laid out
# and sampled at a time for preserved pixels' rays: each vertex of a block holds about
# 140 bytes of float64 temporaries while it is laid out, and a nested domain's sampler
# about 200 (bench/worker_memory.py), so a block takes a few tens of megabytes whatever
# a worker's share of rays.
BLOCK_VERTICES = 1 << 18


def blend_weights(nval, count, cubic=False):
    """Eq. 6's weights w(N, i) for i = 1..count.

    Parameters
    ----------
    nval : (P,) float, membership values. count : int, number of cameras.
    cubic : bool, the monotone cubic (smoothstep) variant; both sum to one between
        neighbouring cameras.

    Returns
    -------
    (count, P) float64.
    """
    i = np.arange(1, count + 1, dtype=np.float64)[:, None]
    w = np.clip(1.0 - np.abs(np.asarray(nval, dtype=np.float64)[None] - i), 0.0, 1.0)
    return w * w * (3.0 - 2.0 * w) if cubic else w


class FieldTracer:
    """Streamlines of the blended field Y (eq. 6) with exact tangents X_i.

    Parameters
    ----------
    rig : Rig. grid : Grid. membership : (nx, ny, nz) float32, the solved N.
    cubic : bool, monotone cubic blending weights.
    domain : ``nested.NestedDomain`` or None: when given, N is read from it (``grid``
        and ``membership`` are then its coarsest level) and the modelled volume is its
        outer box.
    processes : int, worker processes that share a trace's rays (``runtime``); 0: one
        per core. The rays come out the same whichever count traced them, to about
        float32 rounding (numpy may round a float64's last bit differently with the
        length of an array, and the trace carries that on).
    """

    # preserved pixels' rays are laid out exactly (``preserved_rays``): the lattice
    # keeps interpolation from bending them (``methods.traced``)
    exact_preserved = True

    def __init__(self, rig, grid, membership, cubic=False, domain=None, processes=1):
        self.rig = rig
        self.processes = processes
        self.grid = grid
        self.domain = domain
        if domain is None:
            self.n_of = FieldSampler(grid, membership)
            self.contains = grid.contains
        else:
            self.n_of = domain.sample
            self.contains = domain.contains
        self.families = [Family(rig.cameras, i, rig.beta) for i in range(len(rig.cameras))]
        self.cubic = cubic
        self.tangent_seconds = 0.0
        self.missed = 0  # tangent evaluations Newton could not solve (see Family.solve)
        # where: (camera index, (n, 2) float32 camera-1 pixels of the rays) per evaluation
        self.lost = []
        self.seeds = None  # (R, 2) float32 camera-1 pixels of the rays being traced
        self.ready = None  # the Newton state of ``_forget``

    # the per-ray state of the last trace stays behind when the tracer goes to workers
    _TRANSIENT = ("params", "jacobian", "solved_at", "ready", "seeds")

    def __getstate__(self):
        state = dict(self.__dict__)
        for name in self._TRANSIENT:
            state.pop(name, None)
        state["ready"] = state["seeds"] = None
        state["lost"] = []  # a worker sends back only what its share lost
        return state

    def _forget(self, rays):
        """Start the per-ray Newton state afresh for ``rays`` rays: where Newton last
        converged for each ray and family, and the family's Jacobian there (columns
        d/du, d/dv, d/dtau), for the next evaluation's prediction."""
        f = len(self.families)
        self.jacobian = np.zeros((f, rays, 3, 3))
        self.solved_at = np.zeros((f, rays, 3))
        self.ready = np.zeros((f, rays), dtype=bool)

    def _tangent(self, i, x, params, rows):
        """Unit tangent X_i at points ``x`` for rays ``rows``; updates ``params[i, rows]``."""
        start = time.perf_counter()
        if self.ready is None or self.ready.shape[1] != params.shape[1]:
            self._forget(params.shape[1])
        cam = self.rig.cameras[i]
        rel = x - cam.eye
        depth = dot3(rel, cam.forward)
        # ... once the ray has come to camera i's last guide: on a turned rig the start of
        # the bundle can lie beyond camera 3's plane, beside its frustum, on its guides
        beyond = (depth >= cam.clip_start) & (params[i, rows, 2] >= i - 1)
        out = np.empty_like(x)
        # on camera i's straight part the tangent is its pinhole direction
        out[beyond] = rel[beyond] / np.sqrt(dot3(rel[beyond], rel[beyond]))[:, None]
        bend = np.flatnonzero(~beyond)
        if len(bend):
            r = rows[bend]
            xb = x[bend]
            scale = None
            if self.domain is not None and self.domain.scale is not None:
                scale = self.domain.scale(xb)
            u, v, tau = params[i, r, 0], params[i, r, 1], params[i, r, 2]
            # predict: the parameters move with the point by the inverse of the family's
            # Jacobian where it was last solved; one Newton step from there is enough
            ready = np.flatnonzero(self.ready[i, r])
            iterations = np.full(len(r), WARM_ITERATIONS)
            if len(ready):
                rr = r[ready]
                step = solve3(
                    self.jacobian[i, rr, 0],
                    self.jacobian[i, rr, 1],
                    self.jacobian[i, rr, 2],
                    xb[ready] - self.solved_at[i, rr],
                )
                step[~np.isfinite(step).all(axis=1)] = 0.0
                u[ready] += step[:, 0]
                v[ready] += step[:, 1]
                tau[ready] = np.maximum(tau[ready] + step[:, 2], 0.0)
                iterations[ready] = PREDICTED_ITERATIONS
            u, v, tau, out[bend], missed, (ju, jv, jt, ok) = self.families[i].solve(
                xb,
                u,
                v,
                tau,
                iterations,
                scale,
                with_jacobian=True,
                tolerance=TRACE_NEWTON_TOLERANCE,
            )
            params[i, r, 0], params[i, r, 1], params[i, r, 2] = u, v, tau
            self.jacobian[i, r, 0], self.jacobian[i, r, 1], self.jacobian[i, r, 2] = ju, jv, jt
            self.solved_at[i, r] = xb
            self.ready[i, r] = ok
            if missed.any():
                self.missed += int(missed.sum())
                seeds = self.seeds
                at = (
                    seeds[r[missed]]
                    if seeds is not None and len(seeds) == params.shape[1]
                    else None
                )
                self.lost.append(
                    (i, np.full((int(missed.sum()), 2), np.nan, np.float32) if at is None else at)
                )
        self.tangent_seconds += time.perf_counter() - start
        return out

    def velocity(self, x, rows):
        """Blended field sum_i w(N, i) X_i / sum_i w(N, i) at points ``x`` of rays ``rows``.

        Parameters
        ----------
        x : (P, 3) float64 world points. rows : (P,) int64, the rays they belong to
            (their warm-start parameters are read and updated).

        Returns
        -------
        (P, 3) float64: unit where one camera rules, shorter where blended tangents
        disagree (its length is the stall test's speed).
        """
        nval = self.n_of(x)
        w = blend_weights(nval, len(self.families), self.cubic)
        y = np.zeros_like(x)
        for i in range(len(self.families)):
            sel = np.flatnonzero(w[i] > 0)
            if len(sel):
                y[sel] += w[i, sel, None] * self._tangent(i, x[sel], self.params, rows[sel])
        return y / np.maximum(w.sum(0), 1e-30)[:, None]

    def near_plane_split(self, x, direction, rows, step):
        """Where a step from ``x`` along ``direction`` meets the next near plane of cameras
        2..N: there the guides end and the straight rays begin, so the field's curvature
        jumps and a step should not straddle it (see ``rk4_streamlines``' ``split``).

        Returns
        -------
        (P,) float64, arc length to the first plane crossed within ``step``, else ``step``.
        """
        first = np.broadcast_to(np.asarray(step, dtype=np.float64), (len(x),)).copy()
        for cam in self.rig.cameras[1:]:
            f = cam.forward
            dist = cam.clip_start - dot3(x - cam.eye, f)
            rate = dot3(direction, f)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = dist / rate
            ahead = (dist > 0) & (rate > 0) & (t < first)
            first[ahead] = t[ahead]
        return first

    def preserved_rays(self, i, u, v, step, vertices):
        """Rays of camera i's preserved pixels laid out analytically: R_i itself, from
        camera 1's near plane along camera i's guides to its near plane and straight on
        along its pinhole ray to the grid's edge (the caller runs them on from there).

        A preserved pixel's ray is camera i's by definition, whatever the membership
        along it: where N equals i the blended field is X_i and its streamline is R_i,
        and where N sags below i (coarse nested levels, where a small camera's bundle is
        a few cells wide) tracing Y would bend the ray off camera i's family behind its
        near plane (docs/architecture.md, "Tracing"). The membership is recorded at
        every vertex all the same.

        The rays are laid out and sampled ``BLOCK_VERTICES`` vertices at a time and kept
        as float32: the layout's float64 temporaries (about 140 bytes a vertex) of every
        ray at once took hundreds of megabytes in a worker (bench/worker_memory.py).

        Returns
        -------
        ok : (R,) bool, all True. traced : Traced of the R rays.
        """
        r, k = len(u), int(vertices)
        whole = step  # what the rays are recorded with (``Traced.step``), as traced ones
        if isinstance(step, NearPlaneStep):  # the bands of its own guides' planes alone
            step = step.up_to(i)
        verts = np.empty((r, k, 3), dtype=np.float32)
        membership = np.empty((r, k), dtype=np.float32)
        count = np.empty(r, dtype=np.int32)
        block = max(1, BLOCK_VERTICES // k)
        for s in range(0, r, block):
            sl = slice(s, s + block)
            if callable(step):
                laid = scheduled_rays(self.families[i], u[sl], v[sl], step, k, self.contains)
            else:
                laid = arc_length_rays(self.families[i], u[sl], v[sl], step, k)
            on_plane = first_past_near_plane(self.rig.cameras[: i + 1], laid)
            flat = laid.reshape(-1, 3)
            inside = self.contains(flat).reshape(-1, k)
            membership[sl] = self.n_of(flat).reshape(-1, k)
            verts[sl] = laid
            # the tracer keeps the first point outside the grid as a ray's last vertex
            last = np.where(inside.all(axis=1), k, np.argmin(inside, axis=1) + 1)
            # ... and at least one vertex past the near plane's, so the ray runs on along
            # camera i's pinhole ray wherever it leaves the grid
            count[sl] = np.minimum(np.maximum(last, on_plane + 2), k)
            del laid, flat  # before the next block is laid out
        ok = np.ones(r, dtype=bool)
        reason = np.full(r, StopReason.LEFT_GRID, dtype=np.int8)
        reason[count == k] = StopReason.REACHED_LIMIT
        # past the last vertex inside the grid the rays run straight: keep one more
        keep = min(k, int(count.max()) + 1) if r else 2
        return ok, Traced(
            verts[:, :keep].copy() if keep < k else verts,
            membership[:, :keep].copy() if keep < k else membership,
            count,
            reason,
            None if callable(whole) else whole,
            np.full(r, i, dtype=np.int8) if isinstance(whole, NearPlaneStep) else None,
        )

    def _workers(self, rays):
        """Worker processes for ``rays`` rays: 1 (in-process) when too few to share."""
        workers = worker_count(self.processes)
        return min(workers, rays // MIN_RAYS_PER_PROCESS)

    def _shared(self, kind, a, b, step, max_steps, should_stop, parts=False):
        """``_trace_share`` over every n-th of the ``len(a)`` rays in worker processes,
        merged (a share whose worker was given up is traced here); None when the work
        is not shared (too few rays). ``parts``: the shares unmerged instead, a list of
        (Traced, rows): each share's rays and which of the ``len(a)`` they are."""
        rays = len(a)
        workers = self._workers(rays)
        if workers < 2:
            return None
        # every n-th ray to each share: neighbours on the lattice run alike, so the
        # shares take about as long
        n = max(workers, -(-rays // MAX_RAYS_PER_SHARE))
        task = partial(_trace_share, self, kind, a, b, step, max_steps, rays)
        shares = runtime().map(task, [(k, n) for k in range(n)], workers, should_stop).results
        self.missed += sum(p[1] for p in shares)
        self.lost += [entry for p in shares for entry in p[3]]
        # the shares' tangent seconds over the workers that ran them: a round's n
        # shares take about n / workers shares' time (their mean undercounted a round
        # of more shares than workers by that factor)
        self.tangent_seconds += float(np.sum([p[2] for p in shares])) / workers
        orders = [np.arange(k, rays, n) for k in range(n)]
        if parts:
            return [(p[0], rows) for p, rows in zip(shares, orders)]
        return merge([p[0] for p in shares], orders, rays, schedule_of(step))

    def trace(self, u0, v0, step, max_steps, should_stop=None):
        """RK4 streamlines from the near-plane points of pixels (u0, v0) of camera 1.

        Parameters
        ----------
        u0, v0 : (R,) float pixel coordinates. step : float, world units.
        max_steps : int. should_stop : optional callable, polled during the trace.

        Returns
        -------
        Traced

        Raises
        ------
        Cancelled when ``should_stop`` says so.
        """
        traced = self._shared("trace", u0, v0, step, max_steps, should_stop)
        if traced is not None:
            return traced
        return self._trace_here(u0, v0, step, max_steps, should_stop)

    def trace_pixels(self, ix, iy, step, max_steps, should_stop=None, parts=False):
        """Rays of pixels (ix, iy) ((R,) int arrays): R_i laid out analytically where a
        preserved pixel's ray stays in camera i's constraint (``preserved_rays``), RK4
        streamlines for the rest (the transitions). Both run in the workers.

        Returns
        -------
        Traced of the R rays, in the order of the pixels; with ``parts``, a list of
        (Traced, rows), each part's rays and which of the R they are ((n,) int), as the
        workers' shares came back: no merged copy of them all is made (the caller lays
        them out once, ``merge``).
        """
        traced = self._shared("pixels", ix, iy, step, max_steps, should_stop, parts)
        if traced is not None:
            return traced
        traced = self._pixels_here(ix, iy, step, max_steps, should_stop)
        return [(traced, np.arange(len(ix)))] if parts else traced

    def _pixels_here(self, ix, iy, step, max_steps, should_stop=None):
        """``trace_pixels`` in this process."""
        u, v = ix + 0.5, iy + 0.5
        todo = np.ones(len(ix), dtype=bool)
        parts, order = [], []
        for i in range(len(self.rig.cameras)):
            sel = np.flatnonzero(self.rig.masks[i][iy, ix])
            if len(sel) == 0:
                continue
            ok, exact = self.preserved_rays(i, u[sel], v[sel], step, max_steps + 1)
            parts.append(exact)
            order.append(sel[ok])
            todo[sel[ok]] = False
        rest = np.flatnonzero(todo)
        if len(rest):
            parts.append(self._trace_here(u[rest], v[rest], step, max_steps, should_stop))
            order.append(rest)
        return merge(parts, order, len(ix), schedule_of(step))

    def _trace_here(self, u0, v0, step, max_steps, should_stop=None):
        """``trace`` in this process."""
        cam1 = self.rig.cameras[0]
        seeds = cam1.near_points(cam1.directions(u0, v0))
        self.seeds = np.stack([u0, v0], axis=1).astype(np.float32)
        self.params = np.zeros((len(self.families), len(u0), 3))
        self.params[:, :, 0], self.params[:, :, 1] = u0, v0
        self._forget(len(u0))
        lines = rk4_streamlines(
            self.velocity,
            seeds,
            step,
            max_steps,
            stall_speed=STALL_SPEED,
            inside=self.contains,
            should_stop=should_stop,
            with_rays=True,
            split=self.near_plane_split,
        )
        if not lines.complete:
            raise Cancelled()
        pts = lines.points  # (R, K, 3) float32, completed in place block by block
        r, k = pts.shape[:2]
        counts = lines.counts.astype(np.int64)
        membership = np.empty((r, k), dtype=np.float32)
        # in blocks of rays: float64 copies of every vertex, and N's temporaries at
        # every vertex, would take gigabytes at 1920x1080
        block = max(1, BLOCK_VERTICES // k)
        for s in range(0, r, block):
            sl = slice(s, s + block)
            # after a ray stops, run straight on along its last direction at the same
            # step, so vertex k of every ray lies at the same arc length (a ray of one
            # vertex along camera 1's pinhole ray)
            verts = straight_tails(
                pts[sl].astype(np.float64),
                counts[sl],
                step,
                lambda rows, sl=sl: cam1.directions(u0[sl][rows], v0[sl][rows]),
            )
            pts[sl] = verts
            membership[sl] = self.n_of(verts.reshape(-1, 3)).reshape(len(verts), k)
        return Traced(
            pts,
            membership,
            lines.counts.astype(np.int32),
            lines.reason,
            None if callable(step) else step,
        )


def _trace_share(tracer, kind, a, b, step, max_steps, rays, share, context):
    """A worker's share of ``FieldTracer.trace`` (``kind`` "trace": ``a, b`` are u0, v0)
    or ``trace_pixels`` ("pixels": ix, iy): rays k, k + n, ... of ``rays`` for
    ``share`` = (k, n). Returns (Traced, Newton's missed points, tangent seconds, where
    Newton missed: ``FieldTracer.lost`` entries) of the share; the tracer's own counts
    are left as they were (the caller adds these)."""
    k, n = share
    rows = np.arange(k, rays, n)
    missed, seconds, lost = tracer.missed, tracer.tangent_seconds, len(tracer.lost)
    here = tracer._trace_here if kind == "trace" else tracer._pixels_here
    traced = here(a[rows], b[rows], step, max_steps, context)
    counts = tracer.missed - missed, tracer.tangent_seconds - seconds, tracer.lost[lost:]
    tracer.missed, tracer.tangent_seconds = missed, seconds
    del tracer.lost[lost:]
    return traced, *counts
