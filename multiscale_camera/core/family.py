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

# Newton stops when the point error is below this fraction of camera i's near distance.
NEWTON_TOLERANCE = 1e-9
# Finite-difference steps for the Jacobian: pixels, and tau units.
FD_PIXEL = 1e-3
FD_TAU = 1e-5


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

    def _near(self, j, u, v):
        cam = self.cameras[j]
        d = cam.directions(u, v)
        return cam.near_points(d), d

    def evaluate(self, u, v, tau):
        """Points and tangents of the family.

        Parameters
        ----------
        u, v, tau : (P,) float64 arrays.

        Returns
        -------
        point : (P, 3) float64, world units.
        tangent : (P, 3) float64, dR/dtau (not normalised), world units per tau unit.
        """
        u, v, tau = (np.asarray(a, dtype=np.float64) for a in (u, v, tau))
        point = np.empty((len(u), 3))
        tangent = np.empty((len(u), 3))
        stage = np.clip(np.floor(tau), 0, self.i).astype(np.int64)
        for j in range(self.i + 1):
            sel = np.flatnonzero(stage == j)
            if len(sel) == 0:
                continue
            uu, vv, tt = u[sel], v[sel], tau[sel] - j
            p0, d0 = self._near(j, uu, vv)
            if j == self.i:
                point[sel] = p0 + d0 * (tt * self.scale)[:, None]
                tangent[sel] = d0 * self.scale
                continue
            p3, d3 = self._near(j + 1, uu, vv)
            chord = np.sqrt(((p3 - p0) ** 2).sum(-1))
            out = self.beta * chord
            into = np.minimum(out, GUARD_FRACTION * self.cameras[j + 1].clip_start)
            q1 = p0 + d0 * out[:, None]
            q2 = p3 - d3 * into[:, None]
            t = tt[:, None]
            s = 1.0 - t
            point[sel] = s**3 * p0 + 3 * s * s * t * q1 + 3 * s * t * t * q2 + t**3 * p3
            tangent[sel] = 3 * s * s * (q1 - p0) + 6 * s * t * (q2 - q1) + 3 * t * t * (p3 - q2)
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

    def invert(self, points, u, v, tau, iterations=8):
        """Newton's method for (u, v, tau) with R_i(u, v, tau) = point.

        Parameters
        ----------
        points : (P, 3) float64 world points.
        u, v, tau : (P,) float64 starting values (``start`` or a nearby solution).
        iterations : int, at most this many steps; points already within
            ``NEWTON_TOLERANCE`` stop early.

        Returns
        -------
        u, v, tau : (P,) float64. error : (P,) float64, remaining distance to the point,
        world units. tangent : (P, 3) float64, dR/dtau at the solution.
        """
        points = np.asarray(points, dtype=np.float64)
        u, v, tau = (np.array(a, dtype=np.float64) for a in (u, v, tau))
        active = np.arange(len(points))
        error = np.full(len(points), np.inf)
        tangent = np.zeros((len(points), 3))
        tol = NEWTON_TOLERANCE * self.scale
        for _ in range(iterations + 1):
            p, t = self.evaluate(u[active], v[active], tau[active])
            r = p - points[active]
            err = np.sqrt((r * r).sum(-1))
            error[active] = err
            tangent[active] = t
            keep = err > tol
            active, r, t, p = active[keep], r[keep], t[keep], p[keep]
            if len(active) == 0 or _ == iterations:
                break
            m = len(active)
            both, _t = self.evaluate(
                np.concatenate([u[active] + FD_PIXEL, u[active]]),
                np.concatenate([v[active], v[active] + FD_PIXEL]),
                np.concatenate([tau[active], tau[active]]),
            )
            step = solve3((both[:m] - p) / FD_PIXEL, (both[m:] - p) / FD_PIXEL, t, -r)
            u[active] += step[:, 0]
            v[active] += step[:, 1]
            tau[active] = np.maximum(tau[active] + step[:, 2], 0.0)
        return u, v, tau, error, tangent


def solve3(a, b, c, r):
    """Solve [a b c] x = r for many 3x3 systems by Cramer's rule.

    Parameters
    ----------
    a, b, c : (P, 3) float64, the matrix columns. r : (P, 3) float64.

    Returns
    -------
    (P, 3) float64; rows of singular systems are zero.
    """
    bc = np.cross(b, c)
    det = (a * bc).sum(-1)
    safe = np.where(np.abs(det) > 1e-300, det, np.inf)
    return np.stack(
        [(r * bc).sum(-1), (a * np.cross(r, c)).sum(-1), (a * np.cross(b, r)).sum(-1)], axis=-1
    ) / safe[:, None]
