"""Exceptions raised by the core; the Blender side turns them into user messages."""


class RigError(ValueError):
    """The camera rig or its masks cannot produce an image; the message says what to change."""


class SolverDidNotConverge(RuntimeError):
    """An iterative solve stopped before reaching its tolerance."""


class Cancelled(Exception):
    """The user asked long work to stop (Esc); nothing is wrong."""


class VolumeError(RigError):
    """A volume source cannot be read or used; the message names it and what to change.

    A RigError, so every place that reports a scene the renderer cannot use reports it.
    """
