"""What a run did: which process ran each item, which workers were given up and why."""

from dataclasses import dataclass
from enum import Enum


class Reason(Enum):
    """Why a worker was given up."""

    DIED = "died"  # its process ended
    STALLED = "stalled"  # no item done and no beat for ``stall_seconds``
    FAILED = "failed"  # its task raised there, or could not be loaded there
    NO_START = "no start"  # no process could be started, or it never became ready


@dataclass(frozen=True)
class GivenUp:
    """A worker a run stopped using: pid (0 when none started), reason, detail (exit
    status, the error's last line, seconds without progress)."""

    pid: int
    reason: Reason
    detail: str


@dataclass(frozen=True)
class Outcome:
    """What a run did.

    kind : str, the kind of worker (``Launcher.name``). where : tuple of int, for each
    item the pid of the worker that ran it, 0 for this process, -1 for not run
    (cancelled). started : int, workers started for the run (0 when the pool had them).
    given_up : tuple of GivenUp. cancelled : bool. seconds : float, wall time.
    """

    kind: str
    where: tuple
    started: int
    given_up: tuple
    cancelled: bool
    seconds: float

    @property
    def in_workers(self):
        """int, items run in worker processes."""
        return sum(1 for pid in self.where if pid > 0)

    @property
    def in_process(self):
        """int, items run in this process."""
        return sum(1 for pid in self.where if pid == 0)

    @property
    def workers(self):
        """tuple of int, the pids that ran items, each once."""
        return tuple(sorted({pid for pid in self.where if pid > 0}))


@dataclass(frozen=True)
class Mapped:
    """results : list, one per item, in the items' order. outcome : Outcome."""

    results: list
    outcome: Outcome
