"""The ray families R_i as smooth maps (u, v, tau) -> world point, and their inverses.

Camera i's curved ray through pixel (u, v) (continuous pixel coordinates, any value:
the family extends past the image edges) is parameterised by tau >= 0:

- tau in [j, j+1] for j < i: the Bezier guide B_j from camera j's near plane to camera
  j+1's, at curve parameter t = tau - j (paper eq. 1, with the guard of ``guides``);
- tau >= i: straight on from p_i along v_i, at distance (tau - i) * S_i, where S_i is
  camera i's near distance (a fixed scale so that tau stays of order one).

Inverting the family at a point gives the pixel and the position along the ray, and so
the tangent field X_i (paper section 4.4) exactly, without sampling it on a grid.
"""

import numpy as np

from .guides import GUARD_FRACTION
from .vectors import dot3, solve3

# Newton has missed a point when its error is still above this fraction of camera i's
# near distance (its tangent then errs by about as much, relatively): retry from camera
# 1's pixel (``solve``). Warm starts end far below it; a diverged run far above.
RETRY_TOLERANCE = 1e-4
# The retry is damped (``invert_damped``): each step is halved until the distance to the
# point falls, at most RETRY_HALVINGS times. Far off a camera's image, where its guides
# run nearly along its near plane, a full Newton step overshoots and the run diverges:
# on the 1000x bench rig at 240x135 the retry's plain Newton lost 1,271 points, the
# damped one none; from far off (a pixel 2,000 wide of camera 1's) halved steps need
# up to about 24 iterations (docs/performance.md).
RETRY_ITERATIONS = 24
RETRY_HALVINGS = 30
# A point still this far off (fraction of the near distance) after the retry is lost:
# its tangent becomes camera 1's direction. Closer, Newton's tangent is kept.
LOST_TOLERANCE = 1e-3
# Plain Newton steps a missed point gets from where it stands before the damped retry
# (``solve``): on the demo rig at 240x135 PREVIEW, 3 more steps bring 7,090 of the
# 7,760 points the trace's one predicted step leaves short within the trace's tolerance.
CONTINUE_ITERATIONS = 3
# The pixel columns of Newton's Jacobian are refreshed every this many iterations (the
# tau column always): from a warm start one step away they hardly change.
JACOBIAN_EVERY = 2
# Newton stops when the point error is below this fraction of camera i's near distance.
NEWTON_TOLERANCE = 1e-9


class Family:
    """The curved rays R_i of one camera of a rig.

    Parameters
    ----------
    cameras : sequence of PinholeCamera, the rig's cameras in order.
    i : int, 0-based index of the camera whose family this is.
    beta : float, Bezier handle fraction (eq. 1).
    """

    def __init__(self, cameras, i, beta=0.2):
        self.cameras = tuple(cameras[: i + 1])
        self.i = i
        self.beta = beta
        self.scale = self.cameras[-1].clip_start

    def _near(self, j, u, v, derivatives=False):
        """Near-plane points p_j and unit directions v_j of pixels (u, v) of camera j, and
        with ``derivatives`` their derivatives along u and along v.

        With a = R (ax u + bx, ay v + by, -1) the unnormalised direction and f the view
        axis (a . f = 1), p = E + d_j a and v = a / |a|.
        """
        cam = self.cameras[j]
        d = cam.directions(u, v)
        p = cam.near_points(d)
        if not derivatives:
            return p, d
        ax, _bx, ay, _by = cam.image_affine
        r, f = cam.rotation, cam.forward
        # the local (lx, ly, -1) gives a . f = 1, so a = (p - E) / d_j
        a = (p - cam.eye) * (1.0 / cam.clip_start)
        inv_norm = 1.0 / np.sqrt(dot3(a, a))[:, None]
        out = []
        for col, scale in ((r[:, 0], ax), (r[:, 1], ay)):
            da = col * scale  # d a / d u (or d v)
            dp = cam.clip_start * (da - a * (da @ f))  # d_j d/du of a / (a . f)
            dd = (da - d * dot3(d, da)[:, None]) * inv_norm  # d/du of a / |a|
            out += [dp, dd]
        return p, d, out

    def evaluate(self, u, v, tau, jacobian=False):
        """Points and tangents of the family, and optionally the derivatives along u, v.

        Parameters
        ----------
        u, v, tau : (P,) float64 arrays.
        jacobian : bool, also return dR/du and dR/dv.

        Returns
        -------
        point : (P, 3) float64, world units.
        tangent : (P, 3) float64, dR/dtau (not normalised), world units per tau unit.
        du, dv : (P, 3) float64, world units per pixel (with ``jacobian``).
        """
        u, v, tau = (np.asarray(a, dtype=np.float64) for a in (u, v, tau))
        n = len(u)
        point = np.empty((n, 3))
        tangent = np.empty((n, 3))
        if jacobian:
            ju, jv = np.empty((n, 3)), np.empty((n, 3))
        stage = np.clip(np.floor(tau), 0, self.i).astype(np.int64)
        for j in range(self.i + 1):
            sel = np.flatnonzero(stage == j) if self.i else np.arange(n)
            if len(sel) == 0:
                continue
            uu, vv, tt = u[sel], v[sel], tau[sel] - j
            first = self._near(j, uu, vv, jacobian)
            p0, d0 = first[0], first[1]
            if j == self.i:
                point[sel] = p0 + d0 * (tt * self.scale)[:, None]
                tangent[sel] = d0 * self.scale
                if jacobian:
                    dp0u, dd0u, dp0v, dd0v = first[2]
                    ju[sel] = dp0u + dd0u * (tt * self.scale)[:, None]
                    jv[sel] = dp0v + dd0v * (tt * self.scale)[:, None]
                continue
            second = self._near(j + 1, uu, vv, jacobian)
            p3, d3 = second[0], second[1]
            span = p3 - p0
            chord = np.sqrt(dot3(span, span))
            out = self.beta * chord
            limit = GUARD_FRACTION * self.cameras[j + 1].clip_start
            into = np.minimum(out, limit)
            q1 = p0 + d0 * out[:, None]
            q2 = p3 - d3 * into[:, None]
            t = tt[:, None]
            s = 1.0 - t
            b0, b1, b2, b3 = s**3, 3 * s * s * t, 3 * s * t * t, t**3
            point[sel] = b0 * p0 + b1 * q1 + b2 * q2 + b3 * p3
            tangent[sel] = 3 * s * s * (q1 - p0) + 6 * s * t * (q2 - q1) + 3 * t * t * (p3 - q2)
            if jacobian:
                unit = span / np.maximum(chord, 1e-300)[:, None]
                clamped = (out >= limit)[:, None]
                for k, dst in ((0, ju), (2, jv)):
                    dp0, dd0 = first[2][k], first[2][k + 1]
                    dp3, dd3 = second[2][k], second[2][k + 1]
                    dout = self.beta * dot3(unit, dp3 - dp0)[:, None]
                    dinto = np.where(clamped, 0.0, dout)
                    dq1 = dp0 + dd0 * out[:, None] + d0 * dout
                    dq2 = dp3 - dd3 * into[:, None] - d3 * dinto
                    dst[sel] = b0 * dp0 + b1 * dq1 + b2 * dq2 + b3 * dp3
        if jacobian:
            return point, tangent, ju, jv
        return point, tangent

    def start(self, points):
        """A good first guess of (u, v, tau) for world points.

        Beyond camera i's near plane the guess is exact (a projection). Between the
        near planes of cameras j and j+1, the pixel is interpolated between the two
        cameras' projections by the point's distance to the two planes.

        Returns
        -------
        u, v, tau : (P,) float64 arrays.
        """
        points = np.asarray(points, dtype=np.float64)
        n = len(points)
        u = np.zeros(n)
        v = np.zeros(n)
        tau = np.zeros(n)
        done = np.zeros(n, dtype=bool)
        projections = []
        for cam in self.cameras:
            pix, depth = cam.project(points)
            projections.append((pix, depth - cam.clip_start))
        pix, beyond = projections[-1]
        sel = beyond >= 0
        u[sel], v[sel] = pix[sel, 0], pix[sel, 1]
        tau[sel] = self.i + beyond[sel] / self.scale
        done |= sel
        for j in range(self.i - 1, -1, -1):
            pa, da = projections[j]
            pb, db = projections[j + 1]
            sel = ~done & (da >= 0)
            f = np.clip(da[sel] / np.maximum(da[sel] - db[sel], 1e-30), 0.0, 1.0)
            uv = pa[sel] * (1 - f)[:, None] + pb[sel] * f[:, None]
            u[sel], v[sel], tau[sel] = uv[:, 0], uv[:, 1], j + f
            done |= sel
        rest = ~done  # in front of camera 1's near plane: start at its pixel
        u[rest], v[rest] = projections[0][0][rest, 0], projections[0][0][rest, 1]
        return u, v, tau

    def invert(
        self,
        points,
        u,
        v,
        tau,
        iterations=8,
        scale=None,
        with_jacobian=False,
        tolerance=NEWTON_TOLERANCE,
    ):
        """Newton's method for (u, v, tau) with R_i(u, v, tau) = point.

        Parameters
        ----------
        points : (P, 3) float64 world points.
        u, v, tau : (P,) float64 starting values (``start`` or a nearby solution).
        iterations : int or (P,) ints, at most this many steps (for each point);
            points already within ``tolerance`` of ``scale`` stop early.
        scale : (P,) float64 world lengths or None (camera i's near distance), the
            local scale the tolerance is a fraction of (see ``solve``).
        with_jacobian : bool, also return the last dR/du and dR/dv computed.
        tolerance : float, Newton stops below this fraction of ``scale``.

        Returns
        -------
        u, v, tau : (P,) float64. error : (P,) float64, remaining distance to the point,
        world units. tangent : (P, 3) float64, dR/dtau at the solution.
        jac_u, jac_v : (P, 3) float64, world units per pixel, at the last iterate where
        they were computed (with ``with_jacobian``).
        """
        points = np.asarray(points, dtype=np.float64)
        n = len(points)
        u, v, tau = (np.array(a, dtype=np.float64) for a in (u, v, tau))
        active = np.arange(n)
        error = np.full(n, np.inf)
        tangent = np.zeros((n, 3))
        jac_u, jac_v = np.zeros((n, 3)), np.zeros((n, 3))
        tol = tolerance * (self.scale if scale is None else scale)
        tol = np.broadcast_to(tol, (n,))
        its = np.broadcast_to(np.asarray(iterations), (n,))
        most = int(its.max(initial=0))
        for it in range(most + 1):
            last = it == most
            if last or it % JACOBIAN_EVERY:
                p, t = self.evaluate(u[active], v[active], tau[active])
            else:
                p, t, ju, jv = self.evaluate(u[active], v[active], tau[active], jacobian=True)
                jac_u[active], jac_v[active] = ju, jv
            r = p - points[active]
            err = np.sqrt(dot3(r, r))
            error[active] = err
            tangent[active] = t
            keep = (err > tol[active]) & (its[active] > it)
            if last or not keep.any():
                break
            active, r, t, ju, jv = active[keep], r[keep], t[keep], ju[keep], jv[keep]
            step = solve3(ju, jv, t, -r)
            # a step out of the family's domain (a direction at right angles to a view
            # axis) would poison the parameters: leave those points where they are
            step[~np.isfinite(step).all(axis=1)] = 0.0
            u[active] += step[:, 0]
            v[active] += step[:, 1]
            tau[active] = np.maximum(tau[active] + step[:, 2], 0.0)
        if with_jacobian:
            return u, v, tau, error, tangent, jac_u, jac_v
        return u, v, tau, error, tangent

    def invert_damped(self, points, u, v, tau, iterations, scale, tolerance=NEWTON_TOLERANCE):
        """Newton's method for (u, v, tau) with R_i(u, v, tau) = point, each step halved
        until the distance to the point falls (at most ``RETRY_HALVINGS`` times; then
        the last halved step is taken). The distance never grows, so a run from a poor
        start cannot diverge; it may stop short at a local minimum of the distance.

        Parameters
        ----------
        points : (P, 3) float64 world points. u, v, tau : (P,) float64 starting values.
        iterations : int, at most this many steps. scale : (P,) float64 world lengths;
        a point within ``tolerance`` x ``scale`` stops.

        Returns
        -------
        u, v, tau : (P,) float64. error : (P,) float64, world units. tangent : (P, 3)
        float64, dR/dtau at the solution.
        """
        points = np.asarray(points, dtype=np.float64)
        u, v, tau = (np.array(a, dtype=np.float64) for a in (u, v, tau))
        tol = tolerance * np.broadcast_to(scale, (len(points),))
        p, t, ju, jv = self.evaluate(u, v, tau, jacobian=True)
        err = np.sqrt(dot3(p - points, p - points))
        for _ in range(iterations):
            act = np.flatnonzero(~(err <= tol))
            if not len(act):
                break
            step = solve3(ju[act], jv[act], t[act], points[act] - p[act])
            step[~np.isfinite(step).all(axis=1)] = 0.0
            for halving in range(RETRY_HALVINGS + 1):
                un, vn = u[act] + step[:, 0], v[act] + step[:, 1]
                tn = np.maximum(tau[act] + step[:, 2], 0.0)
                pn, tg, jun, jvn = self.evaluate(un, vn, tn, jacobian=True)
                en = np.sqrt(dot3(pn - points[act], pn - points[act]))
                ok = (en < err[act]) | (halving == RETRY_HALVINGS)
                sel = act[ok]
                u[sel], v[sel], tau[sel], err[sel] = un[ok], vn[ok], tn[ok], en[ok]
                p[sel], t[sel], ju[sel], jv[sel] = pn[ok], tg[ok], jun[ok], jvn[ok]
                act, step = act[~ok], step[~ok] * 0.5
                if not len(act):
                    break
        return u, v, tau, err, t

    def solve(
        self,
        points,
        u,
        v,
        tau,
        iterations=8,
        scale=None,
        with_jacobian=False,
        tolerance=NEWTON_TOLERANCE,
    ):
        """``invert``, retried from camera 1's pixel where it misses.

        Newton can miss from a poor start (a stale warm start, or ``start``'s guess off to
        the side of a camera's view, where its projection runs wild); it is retried, damped
        (``invert_damped``), from the pixel of camera 1 that sees the point. Points it
        still misses by more than ``LOST_TOLERANCE`` keep camera 1's pinhole direction as
        their tangent, and are counted.

        ``scale``: (P,) float64 world lengths, the local scale the tolerances are
        fractions of (nested grids pass their scale field: far upstream of a small
        camera, a fraction of its own near distance would ask for far more than the
        cells there resolve); default camera i's near distance.

        ``iterations``: int or (P,) ints, and ``tolerance``, as ``invert``.

        Returns
        -------
        u, v, tau : (P,) float64. tangent : (P, 3) float64, unit and finite.
        missed : int, points whose tangent is camera 1's direction; with
            ``with_jacobian``, (P,) bool, which points they are.
        jacobian : with ``with_jacobian``, (jac_u, jac_v, dR/dtau, ok): the family's
            Jacobian columns, (P, 3) float64 each, near the solution, and (P,) bool,
            where they hold (Newton converged without a retry).
        """
        points = np.asarray(points, dtype=np.float64)
        scale = self.scale if scale is None else scale
        u, v, tau, err, tangent, jac_u, jac_v = self.invert(
            points, u, v, tau, iterations, scale, with_jacobian=True, tolerance=tolerance
        )
        raw = tangent.copy() if with_jacobian else None
        scales = np.broadcast_to(scale, err.shape)
        first = self.cameras[0]
        miss = np.flatnonzero(~(err <= RETRY_TOLERANCE * scale))
        retried = miss
        # most misses are a warm start one or two Newton steps short: a few more plain
        # steps from there finish them for a few evaluations; only what that leaves is
        # retried, damped, from afar (each retry takes dozens of evaluations)
        if len(miss):
            u2, v2, t2, err2, tan2 = self.invert(
                points[miss],
                u[miss],
                v[miss],
                tau[miss],
                CONTINUE_ITERATIONS,
                scales[miss],
                tolerance=tolerance,
            )
            # ... to the tolerance asked for, as the retry would: a point stopped short of
            # it keeps a tangent off by about as much
            done = err2 <= tolerance * scales[miss]
            sel = miss[done]
            u[sel], v[sel], tau[sel], err[sel], tangent[sel] = (
                u2[done],
                v2[done],
                t2[done],
                err2[done],
                tan2[done],
            )
            miss = miss[~done]
        # tau from the distances to the near planes, not where the missed run went; then,
        # for what that leaves, from the middle of the last guide (the run from the plane's
        # end can stall in a local minimum of the distance there)
        for attempt in range(2):
            if not len(miss):
                break
            x, y = first.project(points[miss])[0].T
            t0 = self.start(points[miss])[2] if attempt == 0 else np.full(len(miss), self.i - 0.5)
            u2, v2, t2, err2, tan2 = self.invert_damped(
                points[miss], x, y, np.maximum(t0, 0.0), RETRY_ITERATIONS, scales[miss], tolerance
            )
            better = err2 < np.nan_to_num(err[miss], nan=np.inf)
            sel = miss[better]
            u[sel], v[sel], tau[sel], err[sel], tangent[sel] = (
                u2[better],
                v2[better],
                t2[better],
                err2[better],
                tan2[better],
            )
            miss = miss[~(err[miss] <= RETRY_TOLERANCE * scales[miss])]
        norm = np.sqrt(dot3(tangent, tangent))
        lost = ~(err <= LOST_TOLERANCE * scale) | ~(norm > 0)
        out = tangent / np.where(lost, 1.0, norm)[:, None]
        if lost.any():
            rel = points[lost] - self.cameras[0].eye
            out[lost] = rel / np.sqrt(dot3(rel, rel))[:, None]
            bad = np.flatnonzero(lost)
            u[bad], v[bad], tau[bad] = self.start(points[bad])
        if with_jacobian:
            ok = np.ones(len(points), dtype=bool)
            ok[retried] = False
            return u, v, tau, out, lost, (jac_u, jac_v, raw, ok)
        return u, v, tau, out, int(lost.sum())
