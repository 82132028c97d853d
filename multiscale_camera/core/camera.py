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

    @property
    def rotation(self):
        """(3, 3) float64: orthonormal camera-to-world rotation."""
        m = np.asarray(self.matrix_world, dtype=np.float64)[:3, :3]
        return m / np.linalg.norm(m, axis=0, keepdims=True)

    @property
    def eye(self):
        """(3,) float64: the eye position E_i, world units."""
        return np.asarray(self.matrix_world, dtype=np.float64)[:3, 3].copy()

    @property
    def forward(self):
        """(3,) float64: unit view axis V_i (the camera's local -Z in world space)."""
        return -self.rotation[:, 2]

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
            fit = "HORIZONTAL" if self.pixel_aspect_x * winx >= self.pixel_aspect_y * winy else "VERTICAL"
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
        xmin, xmax, ymin, ymax = self.view_plane()
        px = np.asarray(px, dtype=np.float64)
        py = np.asarray(py, dtype=np.float64)
        local = np.stack(
            [
                xmin + px * ((xmax - xmin) / self.width),
                ymax - py * ((ymax - ymin) / self.height),
                -np.ones_like(px),
            ],
            axis=-1,
        )
        d = local @ self.rotation.T
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def near_points(self, directions):
        """Where rays from the eye along ``directions`` cross the near plane.

        Parameters
        ----------
        directions : (..., 3) float array of unit vectors in front of the camera.

        Returns
        -------
        (..., 3) float64 array: p_i = E_i + v * d_i / (v . V_i), world units.
        """
        cos = np.asarray(directions, dtype=np.float64) @ self.forward
        return self.eye + directions * (self.clip_start / cos)[..., None]

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
        xmin, xmax, ymin, ymax = self.view_plane()
        local = (np.asarray(points, dtype=np.float64) - self.eye) @ self.rotation
        depth = -local[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = local[..., 0] / depth
            v = local[..., 1] / depth
        x = (u - xmin) * (self.width / (xmax - xmin))
        y = (ymax - v) * (self.height / (ymax - ymin))
        return np.stack([x, y], axis=-1), depth


def pixel_centres(width, height):
    """Pixel-centre coordinates of a width x height image.

    Returns
    -------
    px, py : (height, width) float64 arrays, top-left origin, centres at +0.5.
    """
    return np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
