"""Pure-numpy core of Multiscale Camera: camera model, guides, ray generation, metrics.

Nothing in this package imports bpy or mathutils; it runs and is tested in plain Python.
"""

from .errors import RigError, SolverDidNotConverge

__all__ = ["RigError", "SolverDidNotConverge"]
