"""The ray bundle handed from the core to the renderer."""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RayBundle:
    """Bent rays as polylines, one per pixel served.

    Attributes
    ----------
    vertices : (R, K, 3) float32, world units. Vertex 0 lies on camera 1's near plane.
        The last segment is extended by ``reach`` past vertex K-1.
    membership : (R, K) float32, the membership value (camera number, 1-based) at
        each vertex.
    pixels : (R, 2) int32, the (x, y) pixel each ray serves, top-left origin.
    start_depth : (R,) float32, world units: distance from camera 1's eye to vertex 0,
        so depth along the ray is ``start_depth`` plus the arc length.
    reach : (R,) float32, world units: how far the last segment runs on past vertex K-1.
    """

    vertices: np.ndarray
    membership: np.ndarray
    pixels: np.ndarray
    start_depth: np.ndarray
    reach: np.ndarray

    def __len__(self):
        return len(self.vertices)
