"""Exceptions raised by the core; the Blender side turns them into user messages."""


class RigError(ValueError):
    """The camera rig or its masks cannot produce an image; the message says what to change."""


class SolverDidNotConverge(RuntimeError):
    """An iterative solve stopped before reaching its tolerance."""


class Cancelled(Exception):
    """The user asked long work to stop (Esc); nothing is wrong."""
