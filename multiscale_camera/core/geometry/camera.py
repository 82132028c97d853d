"""Pinhole model of a Blender perspective camera.

Pixel ``(x, y)`` counts from the top-left of the final image; its centre is
``(x + 0.5, y + 0.5)``. The view plane follows Blender's own computation
(``BKE_camera_params_compute_viewplane``): sensor fit, shift, pixel aspect and the
render size with its percentage applied, so a pixel here is the pixel Blender renders.
"""

from dataclasses import dataclass

import numpy as np

from ..errors import RigError

SENSOR_FITS = ("AUTO", "HORIZONTAL", "VERTICAL")


@dataclass(frozen=True)
class PinholeCamera:
    """A perspective camera in world space.

    Attributes
    ----------
    name : str
    matrix_world : (4, 4) float64 array
        Camera-to-world transform; the camera looks down its local -Z, +Y is up.
        Scale is ignored (columns are normalised).
    lens : float
        Focal length, millimetres.
    sensor_width, sensor_height : float
        Sensor size, millimetres.
    sensor_fit : str
        One of ``SENSOR_FITS``.
    shift_x, shift_y : float
        Lens shift, in units of the fitted sensor dimension (Blender's convention).
    clip_start, clip_end : float
        Near and far distances along the view axis, Blender units. The near distance is
        the paper's d_i: the camera's near plane holds the start of its preserved rays.
    width, height : int
        Final render size in pixels (percentage already applied).
    pixel_aspect_x, pixel_aspect_y : float
    """

    name: str
    matrix_world: np.ndarray
    lens: float
    sensor_width: float
    sensor_height: float
    sensor_fit: str
    shift_x: float
    shift_y: float
    clip_start: float
    clip_end: float
    width: int
    height: int
    pixel_aspect_x: float = 1.0
    pixel_aspect_y: float = 1.0

    def __post_init__(self):
        m = np.array(self.matrix_world, dtype=np.float64)
        problem = pose_problem(self.name, m, self)
        if problem is not None:
            raise RigError(problem)
        rot = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0, keepdims=True)
        for name, value in (
            ("matrix_world", m),
            ("rotation", rot),
            ("eye", m[:3, 3].copy()),
            ("forward", -rot[:, 2].copy()),
        ):
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        xmin, xmax, ymin, ymax = self.view_plane()
        # pixel -> camera-local point on the plane z = -1: (ax * x + bx, ay * y + by, -1)
        object.__setattr__(
            self,
            "_affine",
            (
                (xmax - xmin) / self.width,
                xmin,
                -(ymax - ymin) / self.height,
                ymax,
            ),
        )

    # rotation : (3, 3) float64, orthonormal camera-to-world rotation.
    # eye : (3,) float64, the eye position E_i, world units.
    # forward : (3,) float64, unit view axis V_i (the camera's local -Z in world space).

    @property
    def image_affine(self):
        """(ax, bx, ay, by) float: pixel (x, y) lies at the camera-local point (ax x + bx,
        ay y + by, -1) on the plane at unit distance (``directions`` and ``project``
        use it; ax is a pixel's width there)."""
        return self._affine

    def view_plane(self):
        """Bounds of the view plane at unit distance, in camera-local units.

        Returns
        -------
        (xmin, xmax, ymin, ymax) : tuple of float
            The image rectangle on the plane z = -1 in camera space.
        """
        winx, winy = float(self.width), float(self.height)
        ycor = self.pixel_aspect_y / self.pixel_aspect_x
        sensor_size = self.sensor_height if self.sensor_fit == "VERTICAL" else self.sensor_width
        fit = self.sensor_fit
        if fit == "AUTO":
            fit = (
                "HORIZONTAL"
                if self.pixel_aspect_x * winx >= self.pixel_aspect_y * winy
                else "VERTICAL"
            )
        viewfac = winx if fit == "HORIZONTAL" else ycor * winy
        pixsize = sensor_size / self.lens / viewfac
        dx = self.shift_x * viewfac
        dy = self.shift_y * viewfac
        return (
            (-0.5 * winx + dx) * pixsize,
            (0.5 * winx + dx) * pixsize,
            (-0.5 * ycor * winy + dy) * pixsize,
            (0.5 * ycor * winy + dy) * pixsize,
        )

    def directions(self, px, py):
        """Unit world-space ray directions v_i through image points.

        Parameters
        ----------
        px, py : array_like float, same shape S
            Continuous image coordinates in this camera's pixels, top-left origin
            (pixel centres at ``x + 0.5``).

        Returns
        -------
        (*S, 3) float64 array of unit vectors.
        """
        ax, bx, ay, by = self._affine
        lx = np.asarray(px, dtype=np.float64) * ax + bx
        ly = np.asarray(py, dtype=np.float64) * ay + by
        r = self.rotation
        d = np.empty((*np.broadcast(lx, ly).shape, 3))
        inv = 1.0 / np.sqrt(lx * lx + ly * ly + 1.0)
        for k in range(3):
            d[..., k] = (r[k, 0] * lx + r[k, 1] * ly - r[k, 2]) * inv
        return d

    def near_points(self, directions):
        """Where rays from the eye along ``directions`` cross the near plane.

        Parameters
        ----------
        directions : (..., 3) float array of unit vectors in front of the camera.

        Returns
        -------
        (..., 3) float64 array: p_i = E_i + v * d_i / (v . V_i), world units.
        """
        d = np.asarray(directions, dtype=np.float64)
        f = self.forward
        cos = d[..., 0] * f[0] + d[..., 1] * f[1] + d[..., 2] * f[2]
        return self.eye + d * (self.clip_start / cos)[..., None]

    def project(self, points):
        """Project world points into this camera's image.

        Parameters
        ----------
        points : (..., 3) float array, world units.

        Returns
        -------
        pixels : (..., 2) float64 array
            Continuous image coordinates (x, y), top-left origin, pixel centres at +0.5.
        depth : (...) float64 array
            Distance along the view axis; points behind the eye have depth <= 0.
        """
        ax, bx, ay, by = self._affine
        rel = np.asarray(points, dtype=np.float64) - self.eye
        r = self.rotation
        lx, ly, lz = (
            rel[..., 0] * r[0, k] + rel[..., 1] * r[1, k] + rel[..., 2] * r[2, k] for k in range(3)
        )
        depth = -lz
        with np.errstate(divide="ignore", invalid="ignore"):
            x = (lx / depth - bx) / ax
            y = (ly / depth - by) / ay
        return np.stack([x, y], axis=-1), depth


def pixel_centres(width, height):
    """Pixel-centre coordinates of a width x height image.

    Returns
    -------
    px, py : (height, width) float64 arrays, top-left origin, centres at +0.5.
    """
    return np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)


# Relative tolerance of the checks of a camera's transform (``pose_problem``).
POSE_TOL = 1e-6
# Where the fix is made, said in every message of ``pose_problem``.
TRANSFORM_FIX = "Object Properties > Transform (and its parents' transforms)"


def pose_problem(name, matrix_world, optics):
    """Why camera ``name`` cannot give rays, or None: its (4, 4) camera-to-world
    ``matrix_world`` is not finite, squashes an axis to nothing (a zero scale), mirrors
    (a negative scale: the image would be flipped) or shears (a non-uniform scale of a
    rotated parent), or one of the lens figures of ``optics`` (an object with ``lens``,
    ``sensor_width``, ``sensor_height``, ``clip_start``, ``clip_end``) is not a positive
    finite number with clip_start < clip_end (``clip_end`` may be +inf: a camera whose
    view is unbounded, as the core's measures allow). Scale is otherwise ignored, as
    Blender's cameras ignore it."""
    m = np.asarray(matrix_world, dtype=np.float64)
    if not np.isfinite(m).all():
        return (
            f"Camera '{name}' has a location, rotation or scale that is not a number "
            f"(NaN or infinite): set its transform again in {TRANSFORM_FIX}"
        )
    axes = m[:3, :3]
    scale = np.linalg.norm(axes, axis=0)
    size = max(float(np.abs(m[:3, 3]).max()), 1.0)
    if scale.min() <= POSE_TOL * max(float(scale.max()), 1e-300) or scale.max() < 1e-12 * size:
        return (
            f"Camera '{name}' has a scale of zero on an axis (world scale "
            f"{_triple(scale)}): give it a non-zero scale, 1 is best, in {TRANSFORM_FIX}"
        )
    unit = axes / scale
    if np.linalg.det(unit) < 0:
        return (
            f"Camera '{name}' is mirrored (a negative scale, its own or a parent's): its "
            f"image would be flipped; make every scale positive in {TRANSFORM_FIX}"
        )
    if np.abs(unit.T @ unit - np.eye(3)).max() > 1e-4:
        return (
            f"Camera '{name}' is sheared (a parent scaled unevenly and rotated): use a "
            f"uniform scale on its parents, or unparent it keeping its transform, in "
            f"{TRANSFORM_FIX}"
        )
    figures = {k: float(getattr(optics, k)) for k in LENS_FIGURES}
    unbounded = figures["clip_end"] == np.inf
    bad = [
        k
        for k, v in figures.items()
        if not ((np.isfinite(v) or (k == "clip_end" and unbounded)) and v > 0)
    ]
    if bad:
        return (
            f"Camera '{name}' has {', '.join(bad)} that is not a positive number: set it "
            "in Camera Properties > Lens and Camera"
        )
    if figures["clip_end"] <= figures["clip_start"]:
        return (
            f"Camera '{name}' has Clip End ({figures['clip_end']:g}) not beyond Clip Start "
            f"({figures['clip_start']:g}): raise Clip End in Camera Properties > Lens"
        )
    return None


# The lens figures ``pose_problem`` checks.
LENS_FIGURES = ("lens", "sensor_width", "sensor_height", "clip_start", "clip_end")


def _triple(v):
    return "(" + ", ".join(f"{x:.3g}" for x in v) + ")"
