"""Pinhole model of a Blender perspective camera.

Pixel ``(x, y)`` counts from the top-left of the final image; its centre is
``(x + 0.5, y + 0.5)``. The view plane follows Blender's own computation
(``BKE_camera_params_compute_viewplane``): sensor fit, shift, pixel aspect and the
render size with its percentage applied, so a pixel here is the pixel Blender renders.
"""

from dataclasses import dataclass

import numpy as np

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
