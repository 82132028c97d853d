"""The trace's step, shortened smoothly where rays cross the near planes of cameras 2..N.

Camera i's guides end on its near plane and its straight pinhole rays begin there. The
trace records a vertex at the end of every step, so the segment that straddles the
plane is a chord across the guide's last bend: past the plane it strays from the
pinhole ray by the chord's sag, and so does every ray of that camera's preserved pixels
(``preserved_rays`` lays them out on the trace's schedule). Seen from camera i, whose
pixels are smallest at its near plane, that sag was several pixels: 7.3 px at p95 for
camera 2 of the 4x rig at 480x270 PREVIEW (docs/architecture.md, *Preserved rays*).

The sag falls as the square of the step. ``NearPlaneStep`` divides the step by up to
``gain`` in a band around each plane, as a smooth function of the point alone: rays
that lie side by side take the same steps, so their vertices stay in step and can be
interpolated vertex by vertex, as everywhere else. Pure numpy.
"""

import numpy as np

from ..geometry import dot3

# The band around a near plane, in steps of the trace's own (unshortened) step: the
# step shrinks over BAND_BEFORE steps before the plane, so that the change from one step
# to the next stays small, and grows back over BAND_AFTER steps beyond it.
BAND_BEFORE = 2.0
BAND_AFTER = 1.0
# Largest division of the step at a plane (64 times less sag).
MAX_GAIN = 8.0
# The share of the accuracy target the straddling chord may take, at the worst of the
# sampled preserved pixels and phases, when ``plane_gain`` picks a plane's gain.
CHORD_SHARE = 0.5


def _smoothstep(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


class NearPlaneStep:
    """A trace step (``rk4_streamlines``' callable ``step``) divided by ``gain`` at the
    near planes of cameras 2..N.

    At a point x with base step b (world units) and signed distance d = depth - near
    past a camera's near plane (depth along its view axis), the step is b / g with
    g = 1 + (gain - 1) phi, phi rising as a smoothstep from 0 at d = -BAND_BEFORE b to
    1 at the plane and falling back to 0 at d = BAND_AFTER b; the largest g over the
    planes applies. Far from every plane it is b exactly.

    The band is the whole plane's: traced rays that pass beside camera i's view cross
    it too. Restricting it to rays near the view (a smoothstep over half an image width
    beside it) put camera 1's lattice rays out of step where the rig turns: 2.3 px p95
    for camera 1 of the turned rig at 480x270 PREVIEW, 0.29 without bands. Preserved
    rays follow only the bands of their own guides' planes (``up_to``).

    Parameters
    ----------
    base : float (world units) or callable, (P, 3) float64 -> (P,) float64 lengths:
        the step it shortens (a nested grid's follows the local cell).
    cameras : sequence of PinholeCamera, cameras 2..N (those whose guides end on their
        near plane). gains : sequence of float >= 1, one per camera (1: its plane is
        left alone).

    Picklable (the step goes to worker processes with the tracer).
    """

    def __init__(self, base, cameras, gains):
        self.base = base
        kept = [(c, float(g)) for c, g in zip(cameras, gains) if g > 1.0]
        self.given = (list(cameras), [float(g) for g in gains])
        self.eyes = np.array([c.eye for c, _ in kept], dtype=np.float64).reshape(-1, 3)
        self.forwards = np.array([c.forward for c, _ in kept], dtype=np.float64).reshape(-1, 3)
        self.nears = np.array([float(c.clip_start) for c, _ in kept])
        self.gains = np.array([g for _, g in kept])

    def up_to(self, count):
        """The step of rays that bend into the first ``count`` of ``cameras`` only: the
        bands of those cameras' planes (the base step itself when none has one).

        A preserved ray of camera i runs straight past its own near plane, so the planes
        of the cameras after it cross a straight line, which no step bends: camera 1's
        preserved rays get the base step, and stay in step with one another wherever
        they cross a later camera's band (interpolated across a lattice cell out of step,
        they strayed from their straight line: 0.12 degrees on camera 1 of the 4x rig at
        240x180 STANDARD, against 0.002)."""
        cameras, gains = self.given
        gains = [g if n < count else 1.0 for n, g in enumerate(gains)]
        if max(gains, default=1.0) <= 1.0:
            return self.base
        return NearPlaneStep(self.base, cameras, gains)

    def base_at(self, x):
        """(P,) float64: the unshortened step at points ``x`` (P, 3)."""
        if callable(self.base):
            return np.asarray(self.base(x), dtype=np.float64)
        return np.full(len(x), float(self.base))

    def __call__(self, x):
        x = np.asarray(x, dtype=np.float64)
        b = self.base_at(x)
        g = np.ones(len(x))
        for eye, forward, near, gain in zip(self.eyes, self.forwards, self.nears, self.gains):
            d = (dot3(x - eye, forward) - near) / b
            phi = np.where(
                d < 0.0, _smoothstep(1.0 + d / BAND_BEFORE), 1.0 - _smoothstep(d / BAND_AFTER)
            )
            np.maximum(g, 1.0 + (gain - 1.0) * phi, out=g)
        return b / g

    def run_lengths(self, start, direction, index):
        """Arc lengths of a straight run on the schedule: from ``start`` (R, 3) along unit
        ``direction`` (R, 3), each step this step at the vertex before it, so a ray that
        stopped (it left the grid) runs on with the vertices it would have had, in step
        with its neighbours that went on tracing through the band.

        Steps are taken one by one only while a ray is in a band or heading into one;
        from where every band is behind it (or it moves away from all of them) its run
        goes on at the step there, which no band changes.

        index : (R, M) int, vertex numbers after ``start`` (0 is ``start`` itself;
        negative counts as 0). Returns (R, M) float64, world units.
        """
        start = np.asarray(start, dtype=np.float64)
        direction = np.asarray(direction, dtype=np.float64)
        index = np.broadcast_to(np.maximum(np.asarray(index), 0), (len(start), np.shape(index)[-1]))
        n = int(index.max(initial=0))
        run = np.zeros((len(start), n + 1))
        live = np.arange(len(start))
        for m in range(1, n + 1):
            if not len(live):
                break
            here = start[live] + direction[live] * run[live, m - 1, None]
            step = self(here)
            run[live, m] = run[live, m - 1] + step
            clear = self._clear(here, direction[live], step)
            if clear.any():
                done = live[clear]
                # no band ahead: the rest at the step there
                more = np.arange(1, n - m + 1)
                run[done, m + 1 :] = run[done, m, None] + step[clear, None] * more
                live = live[~clear]
        return np.take_along_axis(run, index, 1)

    def _clear(self, x, direction, step):
        """(P,) bool: points ``x`` whose straight run along ``direction`` meets no band:
        for every plane, past its band and moving on, or before it and moving away
        (a margin of one ``step`` either way)."""
        clear = np.ones(len(x), dtype=bool)
        b = self.base_at(x)
        for eye, forward, near in zip(self.eyes, self.forwards, self.nears):
            d = dot3(x - eye, forward) - near
            rate = dot3(direction, forward)
            past = (d > BAND_AFTER * b + step) & (rate >= 0.0)
            before = (d < -BAND_BEFORE * b - step) & (rate <= 0.0)
            clear &= past | before
        return clear

    def extra_steps(self):
        """int: steps a ray may take beyond the unshortened trace's, crossing every
        band: about (BAND_BEFORE + BAND_AFTER) (gain - 1) / 2 a plane, doubled."""
        return extra_steps(self.gains)


def schedule_of(step):
    """``step`` when it is a ``NearPlaneStep`` (a run-on follows its bands: ``run_on``,
    ``merge``), else None (a run-on keeps the step it ran at)."""
    return step if isinstance(step, NearPlaneStep) else None


def extra_steps(gains):
    """int: the steps that bands of ``gains`` (one per plane) may add to a ray's trace
    (``NearPlaneStep.extra_steps``); at most ``extra_steps([MAX_GAIN] * planes)``."""
    gains = np.asarray(gains, dtype=np.float64)
    return int(np.ceil(((BAND_BEFORE + BAND_AFTER) * (gains - 1.0)).sum())) + 2


# Where the straddling segment's start falls before the plane, as fractions of its
# length, tried by ``chord_errors`` (the sag at the plane peaks near 2/3).
CHORD_PHASES = np.arange(1, 12) / 12.0
# Gauss-Legendre nodes and weights on [0, 1] for the arc length of a guide's last stretch.
_GAUSS_T = 0.5 + 0.5 * np.array([-np.sqrt(3.0 / 5.0), 0.0, np.sqrt(3.0 / 5.0)])
_GAUSS_W = np.array([5.0, 8.0, 5.0]) / 18.0
# Bisection steps of ``plane_gain`` (the gain found to 2^-12 of MAX_GAIN - 1).
GAIN_BISECTIONS = 12


def chord_errors(family, u, v, length):
    """How far a trace's segment that straddles camera i's near plane strays there, in
    camera i's pixels, at the worst of where its start can fall.

    A segment of arc length h starts on R_i's last guide at arc a before the plane and
    ends on the pinhole ray h - a past it; both ends lie on R_i, and the chord between
    them crosses the plane off the pixel's ray by the guide's sag. For a in
    ``CHORD_PHASES`` times h: the point on the guide at parameter tau = i - a / |R'|
    (its arc from the plane measured by Gauss-Legendre quadrature), the end on the
    pinhole ray, the chord's crossing projected into camera i.

    Parameters
    ----------
    family : geometry.Family of camera i >= 1 (0-based). u, v : (R,) float64, pixel
        centres. length : (R,) float64 world units, the segment's length h at each.

    Returns
    -------
    (R,) float64, pixels: the worst over the phases.
    """
    cam, i = family.cameras[-1], family.i
    r, m = len(u), len(CHORD_PHASES)
    direction = cam.directions(u, v)
    plane = cam.near_points(direction)
    # the guide's speed at its end, |dR/dtau| just before tau = i
    _p, end_tangent = family.evaluate(u, v, np.full(r, i - 1e-9))
    speed = np.sqrt(dot3(end_tangent, end_tangent))
    uu, vv = np.repeat(u, m), np.repeat(v, m)
    h = np.repeat(length, m)
    tau = i - np.minimum((h * np.tile(CHORD_PHASES, r)) / np.repeat(speed, m), 1.0)
    start, _t = family.evaluate(uu, vv, tau)
    arc = np.zeros(r * m)
    for t, w in zip(_GAUSS_T, _GAUSS_W):
        _q, tangent = family.evaluate(uu, vv, tau + (i - tau) * t)
        arc += w * (i - tau) * np.sqrt(dot3(tangent, tangent))
    end = np.repeat(plane, m, axis=0) + np.repeat(direction, m, axis=0) * (h - arc)[:, None]
    forward, eye = np.asarray(cam.forward, dtype=np.float64), np.asarray(cam.eye, dtype=np.float64)
    d0, d1 = dot3(start - eye, forward), dot3(end - eye, forward)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip((cam.clip_start - d0) / (d1 - d0), 0.0, 1.0)
    cross = start + (end - start) * np.where(np.isfinite(t), t, 1.0)[:, None]
    pix, _depth = cam.project(cross)
    err = np.hypot(pix[:, 0] - uu, pix[:, 1] - vv)
    return err.reshape(r, m).max(axis=1)


def segment_length(base, gain):
    """The longest segment the shortened schedule can lay across a plane where the
    unshortened step is ``base``: the step from a point 1 / gain of a base step before
    it (no nearer start can be followed by a longer step)."""
    phi = _smoothstep(1.0 - 1.0 / (gain * BAND_BEFORE))
    return base / (1.0 + (gain - 1.0) * phi)


def plane_gain(family, u, v, base, accuracy_px):
    """The least gain (``NearPlaneStep``) at camera i's near plane whose straddling
    segments (``chord_errors``, at ``segment_length``) stray at most ``CHORD_SHARE`` of
    ``accuracy_px`` at the worst of the pixels (u, v) ((R,) float64): 1 when the
    unshortened step already does, MAX_GAIN when even that does not. ``base`` : (R,)
    float64, the unshortened step at each pixel's near-plane point, world units."""
    allowed = CHORD_SHARE * accuracy_px

    def worst(gain):
        return float(chord_errors(family, u, v, segment_length(base, gain)).max())

    if worst(1.0) <= allowed:
        return 1.0
    if worst(MAX_GAIN) > allowed:
        return MAX_GAIN
    lo, hi = 1.0, MAX_GAIN
    for _ in range(GAIN_BISECTIONS):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if worst(mid) <= allowed else (mid, hi)
    return hi
