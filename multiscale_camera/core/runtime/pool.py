"""The parent's side: worker processes kept in pools (one a kind of worker, ``Launcher``)
across runs, runs that stream each item's result as it finishes, and what a run did
(``Outcome``).

A run hands its items to its workers one at a time (a worker's next item goes out as
its last result comes in), so workers that are slower, or given up, leave their share
to the others. A worker is given up when its process ends, when it neither finishes
its item nor beats (``Context``) for ``stall_seconds``, or when its task raises there;
its item, and whatever the run has left when no worker is, runs in this process with
the run's ``local`` function. A run's caller may also take items itself from another
thread (``Run.help``), so that this process counts as one of the run's processes.
Cancelling (``should_stop``, or closing the run) stops the items in the workers (their
``Context`` says so) and returns the workers to the pool; only a worker that does not
stop within ``CANCEL_SECONDS`` is ended.
"""

import contextlib
import contextvars
import itertools
import pickle
import queue
import subprocess
import threading
import time
from collections import deque

from ..errors import Cancelled
from .launch import python_launcher
from .outcome import GivenUp, Mapped, Outcome, Reason
from .shared import Segment, SharedArrays
from .wire import dump_payload, encode, read_message, skip_to_marker, write_frame
from .worker import BEAT, CANCEL, CONTROL_WORDS, Context

# How often a run asks ``should_stop`` and looks for stalled workers while it waits.
POLL_SECONDS = 0.1
# A worker that neither finishes its item nor beats for this long is taken for stuck;
# tasks beat at least every fraction of a second.
STALL_SECONDS = 20.0
# The longest a worker may take to start, whatever a run's stall limit: a background
# Blender takes about 1 s, and several times that on a busy machine. A start given up
# leaves the whole kind unused, so a short stall limit must not cut starts short.
START_SECONDS = 20.0
# How long a cancelled run waits for its workers to stop their items before it ends
# them (a worker that stops stays in the pool).
CANCEL_SECONDS = 0.5
# How long shutting a worker down waits for it to end after its input closes.
CLOSE_SECONDS = 2.0


class Worker:
    """One worker process, seen from the parent: its pipes, its control words (beats,
    cancel) in shared memory, and a thread that reads its replies into the ``sink`` of
    the run using it (a queue of (worker, message); ``("exit",)`` when it ends)."""

    def __init__(self, launcher, sink):
        self.sink = sink
        self.ready = threading.Event()
        self.alive = True
        self.started = time.monotonic()
        self._lock = threading.Lock()
        self._segment = Segment.create(CONTROL_WORDS * 8)
        self.control = self._segment.array((CONTROL_WORDS,), "int64")
        try:
            self.process = subprocess.Popen(
                launcher.command(self._segment.name),
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                env=launcher.environment(),
            )
        except BaseException:
            self._segment.unlink()
            raise
        self.pid = self.process.pid
        threading.Thread(target=self._read, name=f"worker {self.pid}", daemon=True).start()

    def _read(self):
        stream = self.process.stdout
        try:
            if skip_to_marker(stream):
                while (message := read_message(stream)) is not None:
                    if message[0] == "ready":
                        self._segment.unlink()  # mapped: its name is needed no more
                        self.ready.set()
                    self._post(message)
        except (OSError, ValueError, EOFError, pickle.UnpicklingError):
            pass
        finally:
            self.alive = False
            self._post(("exit",))

    def _post(self, message):
        with self._lock:
            sink = self.sink
        if sink is not None:
            sink.put((self, message))

    def lend(self, sink):
        """Send replies to ``sink`` (a run's queue), or to nobody (None)."""
        with self._lock:
            self.sink = sink

    def send(self, data):
        """Write an encoded message; False when the pipe is gone (the worker ended)."""
        try:
            write_frame(self.process.stdin, data)
            return True
        except (OSError, ValueError):
            return False

    def kill(self):
        """End the process now and reap it."""
        self.alive = False
        with contextlib.suppress(OSError):
            self.process.kill()
        self._reap(CLOSE_SECONDS)

    def close(self):
        """End the worker: its input closes, it returns; ended if it does not."""
        with contextlib.suppress(OSError, ValueError):
            self.process.stdin.close()
        if not self._reap(CLOSE_SECONDS):
            self.kill()

    def _reap(self, seconds):
        try:
            self.process.wait(timeout=seconds)
        except subprocess.TimeoutExpired:
            return False
        with contextlib.suppress(OSError, ValueError):
            self.process.stdin.close()
        self._segment.unlink()
        return True


class Pool:
    """The workers of one kind, kept across runs; a run checks out the idle ones and
    starts more when it wants more. When a worker fails to start, no more are started
    (``broken`` says why): runs then work in this process."""

    def __init__(self, launcher):
        self.launcher = launcher
        self.workers = []
        self.broken = None
        self._lock = threading.Lock()

    def checkout(self, count, sink):
        """(workers, started, errors): ``count`` workers lent to ``sink`` (fewer when
        processes cannot be had: ``errors`` says why), how many were started now."""
        with self._lock:
            self.workers = [w for w in self.workers if w.alive or w.sink is not None]
            idle = [w for w in self.workers if w.alive and w.sink is None][:count]
            for w in idle:
                w.lend(sink)
            errors, started = [], 0
            while len(idle) < count and self.broken is None:
                try:
                    worker = Worker(self.launcher, sink)
                except OSError as err:  # no processes or memory to be had (limits, sandbox)
                    errors.append(f"{type(err).__name__}: {err}")
                    break
                self.workers.append(worker)
                idle.append(worker)
                started += 1
            return idle, started, errors

    def checkin(self, workers):
        """Take lent workers back (the dead ones are reaped)."""
        for w in workers:
            w.lend(None)
            if not w.alive:
                w.kill()

    def pids(self):
        """list of int, the live workers' pids."""
        with self._lock:
            return [w.pid for w in self.workers if w.alive]

    def close(self):
        with self._lock:
            workers, self.workers = self.workers, []
        for w in workers:
            w.close()


def _last_line(text):
    lines = [line for line in str(text).strip().splitlines() if line.strip()]
    return lines[-1].strip() if lines else ""


class Run:
    """A run's results as its items finish: iterating gives ``(index, result)``;
    ``outcome`` is set when the iteration ends (normally, by an error, by
    cancelling, or by ``close``)."""

    def __init__(
        self, runtime, function, items, processes, should_stop, launcher, local, stall, helped
    ):
        self._runtime = runtime
        self._function = function
        self._items = list(items)
        self._processes = int(processes)
        self._should_stop = should_stop
        self._launcher = launcher
        self._local = function if local is None else local
        self._stall = STALL_SECONDS if stall is None else float(stall)
        self._helped = bool(helped)
        self.outcome = None
        self._given_up = []
        self._state = None
        self._begun = threading.Event()
        self._iterator = self._iterate()

    def __iter__(self):
        return self

    def __next__(self):
        return next(self._iterator)

    def close(self):
        """Stop the run (its workers return to the pool)."""
        self._iterator.close()
        self._begun.set()  # a helper waiting for a run that never began goes
        if self.outcome is None:  # closed before it started: nothing ran
            where = (-1,) * len(self._items)
            self.outcome = Outcome(self._launcher.name, where, 0, (), True, 0.0)

    def mapped(self):
        """Iterate the run to its end: Mapped results in the items' order, and the
        Outcome (raises what the iteration raises: ``Cancelled``, an item's error)."""
        results = [None] * len(self._items)
        for index, result in self:
            results[index] = result
        return Mapped(results, self.outcome)

    @property
    def given_up(self):
        """tuple of GivenUp: the workers given up so far (while the run goes on too)."""
        return tuple(self._given_up)

    def help(self):
        """Run the items no worker has taken yet here, in the calling thread, one at a
        time with the run's ``local`` function, while another thread iterates the run
        (which yields their results too); return when none is left to take (items still
        in workers go on there). For a run made ``helped``: a caller with nothing else
        to do joins the workers rather than waiting for them. An item that raises here
        ends the run with that error, raised where the run is iterated."""
        self._begun.wait()
        state, local = self._state, self._local  # the run lets go of ``local`` as it ends
        if state is None or local is None:
            return
        context = Context(should_stop=self._should_stop)
        while (index := state.claim()) is not None:
            try:
                result = local(self._items[index], context)
            except BaseException as err:  # raised by the iterating thread
                state.sink.put((None, ("raised", None, index, err)))
                return
            state.sink.put((None, ("helped", None, index, result)))

    def _stop_asked(self):
        return self._should_stop is not None and self._should_stop()

    def _iterate(self):
        state = self._state = _State(self, self._runtime.next_job())
        self._begun.set()
        try:
            yield from state.loop()
        except BaseException:
            state.cancelled = True
            raise
        finally:
            state.close()
            self.outcome = state.finish()
            self._runtime.record(self.outcome)
            # what the task holds (shared arrays among it) goes with the caller's last
            # reference, not with a later garbage collection
            self._function = self._local = None
            state.payload = None  # the state stays for a late helper (``Run.help``)


class _State:
    """The bookkeeping of one run (``Run._iterate``)."""

    def __init__(self, run, job):
        self.run = run
        self.job = job
        self.items = run._items
        self.where = [-1] * len(self.items)
        self.todo = deque(range(len(self.items)))
        self.here = deque()
        # ``todo`` and ``here`` are shared with a helping thread (``Run.help``); closed,
        # they hand it nothing more
        self.lock = threading.Lock()
        self.closed = False
        self.given_up = run._given_up
        self.busy = {}  # worker -> index of its item
        self.seen = {}  # worker -> (time of its last progress, its beats then)
        self.used, self.dropped, self.loaded, self.copies = [], set(), set(), []
        self.sink = queue.Queue()
        self.started = 0
        self.cancelled = False
        self.clock = time.monotonic()
        self.pool = None
        self.payload = None

    def begin(self):
        """Check out workers when the run wants two or more (one, for a run its caller
        helps: ``Run.help``)."""
        run = self.run
        want = min(run._processes, len(self.items))
        if want < (1 if run._helped else 2):
            return
        self.pool = run._runtime.pool(run._launcher)
        if self.pool.broken is not None:
            self.given_up.append(GivenUp(0, Reason.NO_START, self.pool.broken))
            return
        try:
            task = dump_payload(run._function, run._runtime.shared, self.copies)
            self.payload = encode(("job", self.job, task))
        except (pickle.PicklingError, TypeError, AttributeError, OSError) as err:
            self.given_up.append(GivenUp(0, Reason.NO_START, f"the task cannot travel: {err}"))
            return
        self.used, self.started, errors = self.pool.checkout(want, self.sink)
        self.given_up += [GivenUp(0, Reason.NO_START, e) for e in errors]
        now = time.monotonic()
        for w in self.used:
            self.seen[w] = (now, int(w.control[BEAT]))

    def give_up(self, worker, reason, detail):
        self.dropped.add(worker)
        index = self.busy.pop(worker, None)
        if index is not None:
            with self.lock:
                self.here.append(index)
        self.given_up.append(GivenUp(worker.pid, reason, detail))
        if reason is Reason.NO_START and self.pool.broken is None:
            self.pool.broken = f"a worker did not start ({detail})"

    def claim(self):
        """The index of an item to run in this process (a helper's, ``Run.help``), taken
        from those no worker has; None when there is none or the run has ended."""
        with self.lock:
            if self.closed:
                return None
            for waiting in (self.here, self.todo):
                if waiting:
                    return waiting.popleft()
            return None

    def close(self):
        """Hand helpers nothing more (the run has ended)."""
        with self.lock:
            self.closed = True

    def feed(self):
        """Give the next items to ready workers that have none."""
        for w in self.used:
            if not self.todo:
                return
            if w in self.dropped or w in self.busy or not w.ready.is_set():
                continue
            if w not in self.loaded:
                if not w.send(self.payload):
                    continue  # it ended: its ("exit",) follows
                self.loaded.add(w)
            with self.lock:
                index = self.todo.popleft() if self.todo else None
            if index is None:
                return
            if not w.send(encode(("item", self.job, index, self.items[index]))):
                with self.lock:
                    self.todo.appendleft(index)
                continue
            self.busy[w] = index
            self.seen[w] = (time.monotonic(), int(w.control[BEAT]))

    def loop(self):
        run = self.run
        self.begin()
        context = Context(should_stop=run._should_stop)
        done = 0
        while done < len(self.items):
            self.feed()
            if all(w in self.dropped for w in self.used):  # no worker left: the rest here
                with self.lock:
                    self.here.extend(self.todo)
                    self.todo.clear()
            with self.lock:
                index = self.here.popleft() if self.here else None
            if index is not None:
                if run._stop_asked():
                    raise Cancelled()
                result = run._local(self.items[index], context)
                self.where[index] = 0
                done += 1
                yield index, result
                continue
            try:
                worker, message = self.sink.get(timeout=POLL_SECONDS)
            except queue.Empty:
                worker = message = None
            if message is not None and worker not in self.dropped:
                index = self.take(worker, message)
                if index is not None:
                    done += 1
                    self.feed()
                    yield index, message[3]
            if run._stop_asked():
                raise Cancelled()
            if message is None:
                self.check_stalls()

    def take(self, worker, message):
        """Handle a worker's message (or a helper's: worker None); the item's index when
        it brings a result."""
        kind = message[0]
        if worker is None:  # a helping thread's item (``Run.help``)
            if kind == "raised":
                raise message[3]
            self.where[message[2]] = 0
            return message[2]
        if kind == "exit":
            worker.kill()  # reaped: its exit status is known
            reason = Reason.DIED if worker.ready.is_set() else Reason.NO_START
            self.give_up(worker, reason, f"exit status {worker.process.returncode}")
        elif kind in ("done", "failed", "cancelled") and message[1] == self.job:
            if self.busy.get(worker) != message[2]:
                return None
            if kind == "done":
                index = self.busy.pop(worker)
                self.where[index] = worker.pid
                self.seen[worker] = (time.monotonic(), int(worker.control[BEAT]))
                return index
            detail = _last_line(message[3]) if kind == "failed" else "its task cancelled itself"
            self.give_up(worker, Reason.FAILED, detail)
        return None

    def check_stalls(self):
        now = time.monotonic()
        stall = self.run._stall
        for w in self.used:
            if w in self.dropped:
                continue
            if not w.ready.is_set():
                start = max(stall, START_SECONDS)
                if now - w.started > start:
                    w.kill()
                    self.give_up(w, Reason.NO_START, f"not ready after {start:g} s")
            elif w in self.busy:
                beats = int(w.control[BEAT])
                since, before = self.seen[w]
                if beats != before:
                    self.seen[w] = (now, beats)
                elif now - since > stall:
                    w.kill()
                    self.give_up(w, Reason.STALLED, f"no item done and no beat for {stall:g} s")

    def finish(self):
        """Stop what is still running in workers, return them to the pool, free the
        run's shared memory; the Outcome."""
        busy = self.busy
        for w in busy:
            w.control[CANCEL] = self.job
        deadline = time.monotonic() + CANCEL_SECONDS
        while busy and (left := deadline - time.monotonic()) > 0:
            try:
                worker, message = self.sink.get(timeout=left)
            except queue.Empty:
                break
            if worker in busy and (
                message[0] == "exit"
                or (message[0] in ("done", "failed", "cancelled") and message[1] == self.job)
            ):
                del busy[worker]
        for w in busy:  # it did not stop in time: end it (the pool starts another)
            w.kill()
        release = encode(("release",))
        for w in self.loaded:
            if w.alive and w not in busy:
                w.send(release)
        if self.pool is not None:
            self.pool.checkin(self.used)
        for seg in self.copies:
            seg.unlink()
            if seg.buffer is not None:
                with contextlib.suppress(BufferError):
                    seg.buffer.close()
        return Outcome(
            kind=self.run._launcher.name,
            where=tuple(self.where),
            started=self.started,
            given_up=tuple(self.given_up),
            cancelled=self.cancelled,
            seconds=time.monotonic() - self.clock,
        )


class Runtime:
    """Worker pools (one a kind of worker, ``Launcher``) kept across runs, the shared arrays workers
    write into, and the journals that collect what runs did."""

    def __init__(self):
        self.shared = SharedArrays()
        self._pools = {}
        self._lock = threading.Lock()
        self._jobs = itertools.count(1)
        self._journals = contextvars.ContextVar(f"journals {id(self)}", default=())

    def next_job(self):
        with self._lock:
            return next(self._jobs)

    def pool(self, launcher):
        """The Pool of ``launcher``'s kind (made on first use)."""
        with self._lock:
            pool = self._pools.get(launcher)
            if pool is None:
                pool = self._pools[launcher] = Pool(launcher)
            return pool

    def shared_array(self, shape, dtype, reserve=True):
        """A zeroed array that workers of any run can write into (``SharedArrays.new``;
        ``reserve`` False: its memory is taken a piece at a time, ``shared.reserve``).

        Raises
        ------
        OSError when shared memory cannot be had.
        """
        return self.shared.new(shape, dtype, reserve)

    def run(
        self,
        function,
        items,
        processes,
        should_stop=None,
        launcher=None,
        local=None,
        stall_seconds=None,
        helped=False,
    ):
        """Start ``function(item, context)`` for every item; a Run to iterate.

        Parameters
        ----------
        function : picklable callable (item, Context) -> picklable result: a module-level
            function, or a ``functools.partial`` of one whose arguments are data (arrays
            of a few hundred kB or more travel through shared memory, and arrays made
            with ``shared_array`` are written in place).
        items : sequence of picklable items. processes : int, workers at most (one an
            item); below 2 (below 1 when ``helped``) every item runs in this process.
        should_stop : callable () -> bool, asked while waiting: True cancels the run.
        launcher : Launcher, the kind of worker (default: a plain Python).
        local : callable like ``function``, what runs an item in this process
            (default: ``function``).
        stall_seconds : float, default ``STALL_SECONDS``.
        helped : bool, the caller runs items too (``Run.help``, from another thread than
            the one iterating): one worker is then worth starting (``processes`` 1).
        """
        launcher = python_launcher() if launcher is None else launcher
        return Run(
            self, function, items, processes, should_stop, launcher, local, stall_seconds, helped
        )

    def map(self, function, items, processes, should_stop=None, **options):
        """``run`` to its end: Mapped results in the items' order, and the Outcome.

        Raises
        ------
        Cancelled when ``should_stop`` says so.
        """
        return self.run(function, items, processes, should_stop, **options).mapped()

    def warm(self, processes, launcher=None, wait=True):
        """Start workers of ``launcher``'s kind (default: plain Python) until the pool has
        ``processes``, and, with ``wait``, wait until they are ready (``START_SECONDS`` at
        most), so that the next run finds them; list of their pids (without ``wait``,
        of those started or idle: the next run waits for them as they come ready)."""
        pool = self.pool(python_launcher() if launcher is None else launcher)
        workers, _started, _errors = pool.checkout(processes, None)
        try:
            if not wait:
                return [w.pid for w in workers if w.alive]
            deadline = time.monotonic() + START_SECONDS
            for w in workers:
                while w.alive and not w.ready.wait(POLL_SECONDS):
                    if time.monotonic() > deadline:
                        break
            return [w.pid for w in workers if w.alive and w.ready.is_set()]
        finally:
            pool.checkin(workers)

    @contextlib.contextmanager
    def journal(self):
        """Collect the Outcome of every run that ends inside the block (in this thread or
        context) into the list it gives."""
        runs = []
        token = self._journals.set((*self._journals.get(), runs))
        try:
            yield runs
        finally:
            self._journals.reset(token)

    def record(self, outcome):
        for runs in self._journals.get():
            runs.append(outcome)

    def pids(self, launcher=None):
        """list of int, the live workers of ``launcher``'s kind (default: of every kind)."""
        with self._lock:
            pools = list(self._pools.values())
        return [pid for p in pools if launcher in (None, p.launcher) for pid in p.pids()]

    def shutdown(self):
        """End every worker and remove every shared-memory name."""
        with self._lock:
            pools, self._pools = list(self._pools.values()), {}
        for pool in pools:
            pool.close()
        self.shared.close()
