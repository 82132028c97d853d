"""The rig: an ordered chain of cameras and their masks, checked for consistency."""

from dataclasses import dataclass, field

import numpy as np

from ..errors import RigError
from .camera import PinholeCamera


@dataclass(frozen=True)
class Rig:
    """Cameras C_1..C_N (largest scale first) and their masks I_1..I_N.

    Attributes
    ----------
    cameras : tuple of PinholeCamera
        All share the final image size (width, height).
    masks : (N, H, W) bool array
        True where camera i's view is preserved; row 0 is the top of the image.
        No pixel is owned by two cameras (``resolve_conflicts`` settles that first).
    beta : float
        Bezier handle length as a fraction of the distance between near planes (eq. 1).
    notices : tuple of str
        Things the user should know that do not stop the render.
    """

    cameras: tuple
    masks: np.ndarray
    beta: float = 0.2
    notices: tuple = field(default=())

    @property
    def size(self):
        """(width, height) of the final image in pixels."""
        return self.cameras[0].width, self.cameras[0].height

    def __post_init__(self):
        if not self.cameras:
            raise RigError("The camera list is empty: add cameras, largest scale first")
        w, h = self.size
        for cam in self.cameras:
            if not isinstance(cam, PinholeCamera):
                raise RigError(f"{cam!r} is not a perspective camera")
            if (cam.width, cam.height) != (w, h):
                raise RigError(f"Camera '{cam.name}' renders {cam.width}x{cam.height}, not {w}x{h}")
        masks = np.asarray(self.masks)
        if masks.shape != (len(self.cameras), h, w) or masks.dtype != bool:
            raise RigError(
                f"Masks must be bool of shape {(len(self.cameras), h, w)}, "
                f"got {masks.dtype} {masks.shape}"
            )
        counts = masks.reshape(len(self.cameras), -1).sum(axis=1)
        if counts.sum() == 0:
            raise RigError(
                "Every mask is empty: paint white where each camera's view should be kept"
            )
        if counts[-1] == 0:
            raise RigError(
                f"The mask of the last camera '{self.cameras[-1].name}' is empty: the smallest "
                "scale must show somewhere (paint it white there), or remove that camera"
            )
        if (masks.sum(axis=0) > 1).any():
            raise RigError("Some pixels are owned by two cameras; resolve the masks first")


def resolve_conflicts(masks, names):
    """Give each pixel owned by several masks to the smallest-scale camera among them.

    Parameters
    ----------
    masks : (N, H, W) bool array
    names : sequence of N str
        Camera names, for the notices.

    Returns
    -------
    masks : (N, H, W) bool array with at most one owner per pixel.
    notices : list of str, one per pair of cameras that shared pixels.
    """
    masks = np.array(masks, dtype=bool, copy=True)
    notices = []
    taken = np.zeros(masks.shape[1:], dtype=bool)
    for i in range(len(masks) - 1, -1, -1):
        clash = masks[i] & taken
        if clash.any():
            later = [names[j] for j in range(i + 1, len(masks)) if (masks[j] & masks[i]).any()]
            notices.append(
                f"{int(clash.sum())} pixels are in the masks of both '{names[i]}' and "
                f"'{later[0]}'; the smaller scale ('{later[0]}') keeps them (erase one of the "
                "masks there to decide yourself)"
            )
            masks[i] &= ~taken
        taken |= masks[i]
    return masks, notices
