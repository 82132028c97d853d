"""Named shared memory: arrays that worker processes map by name instead of receiving a
copy through a pipe.

A ``Segment`` is a block of shared memory with a name (POSIX ``shm_open``; a named
mapping of the paging file on Windows), mapped in this process. A worker started
without copying this process (no fork) maps it by that name. Names are removed
(``unlink``) as soon as no worker needs to find them; the memory itself lives on while
any process maps it. The resource tracker of ``multiprocessing`` is told of every name
this process creates, so that a name left by a crashed process is still removed.

``SharedArrays`` makes arrays in segments (``shared_array``): what workers write into
them, the parent sees. ``Handle`` is how an array travels: segment name, offset, shape,
strides, dtype; ``attach`` makes the array again on the other side.
"""

import mmap
import os
import secrets
import threading
import weakref
from dataclasses import dataclass

import numpy as np

# Segment names start with this, then the creating process's id: `ls /dev/shm` shows
# what is left, and whose (macOS allows 31 characters a name).
PREFIX = "msc"

# Bytes written at a time into a segment (``Segment.holding``).
WRITE_BYTES = 1 << 28

if os.name == "nt":
    _posixshmem = None
else:
    import _posixshmem  # what multiprocessing.shared_memory uses on POSIX


def _track(name, register):
    """Tell the resource tracker of ``multiprocessing`` that ``name`` exists (or no
    longer does), so that it removes the name if this process dies first."""
    if _posixshmem is None:
        return
    try:
        from multiprocessing import resource_tracker

        (resource_tracker.register if register else resource_tracker.unregister)(
            "/" + name, "shared_memory"
        )
    except Exception:  # no tracker to be had: the name is still removed by ``unlink``
        pass


def _new_name():
    """A new segment name: PREFIX, this process's id, 8 random hex digits."""
    return f"{PREFIX}{os.getpid()}_{secrets.token_hex(4)}"


def _posix_segment(size, fill):
    """(name, fill's result): a new POSIX segment of ``size`` bytes, ``fill(fd)`` run on
    its open file; the name is removed again if either fails."""
    name = _new_name()
    fd = _posixshmem.shm_open("/" + name, os.O_CREAT | os.O_EXCL | os.O_RDWR, mode=0o600)
    try:
        os.ftruncate(fd, size)
        result = fill(fd)
    except BaseException:
        _posixshmem.shm_unlink("/" + name)
        raise
    finally:
        os.close(fd)
    _track(name, True)
    return name, result


class Segment:
    """A named block of shared memory, mapped in this process.

    Attributes
    ----------
    name : str. size : int, bytes. buffer : mmap.mmap of ``size`` bytes, or None when
    this process does not map it (``holding``). owner : bool, whether this process
    created it (and removes its name).
    """

    def __init__(self, name, size, buffer, owner):
        self.name = name
        self.size = size
        self.buffer = buffer
        self.owner = owner
        self._named = owner

    @classmethod
    def create(cls, size, reserve=True):
        """A new zeroed segment of ``size`` bytes (at least 1).

        ``reserve``: take the memory now (``posix_fallocate``, so that a full /dev/shm
        fails here rather than with SIGBUS on a later write); False leaves it to be
        taken a range at a time (module ``reserve``) before each range is written: a large
        array filled in pieces then holds only what is written so far.

        Raises
        ------
        OSError when the memory cannot be had.
        """
        size = max(int(size), 1)
        if _posixshmem is None:
            name = _new_name()
            return cls(name, size, mmap.mmap(-1, size, tagname=name), True)

        def mapped(fd):
            if reserve and hasattr(os, "posix_fallocate"):
                os.posix_fallocate(fd, 0, size)
            return mmap.mmap(fd, size)

        name, buffer = _posix_segment(size, mapped)
        return cls(name, size, buffer, True)

    @classmethod
    def holding(cls, array):
        """A new segment holding a copy of ``array``'s elements in C order (POSIX: written
        through the file, which is faster than through a mapping, and not mapped here;
        the segment's ``buffer`` is then None).

        Raises
        ------
        OSError when the memory cannot be had.
        """
        data = memoryview(np.ascontiguousarray(array)).cast("B")
        size = max(len(data), 1)
        if _posixshmem is None:
            seg = cls.create(size)
            seg.buffer[: len(data)] = data
            return seg

        def written(fd):
            done = 0
            while done < len(data):
                done += os.pwrite(fd, data[done : done + WRITE_BYTES], done)

        name, _ = _posix_segment(size, written)
        return cls(name, size, None, True)

    @classmethod
    def attach(cls, name, size):
        """The segment ``name`` of ``size`` bytes, made by another process."""
        if _posixshmem is None:
            return cls(name, size, mmap.mmap(-1, size, tagname=name), False)
        fd = _posixshmem.shm_open("/" + name, os.O_RDWR, mode=0o600)
        try:
            buffer = mmap.mmap(fd, size)
        finally:
            os.close(fd)
        return cls(name, size, buffer, False)

    def unlink(self):
        """Remove the name (this process's own segments only; the memory stays mapped
        wherever it is). Idempotent."""
        if self._named:
            self._named = False
            unlink(self.name)

    @property
    def named(self):
        """bool, whether the name still exists (another process can still map it)."""
        return self._named

    def array(self, shape, dtype, offset=0, strides=None):
        """An ndarray over this segment's memory (its ``base`` is the mapping)."""
        return np.ndarray(shape, dtype, buffer=self.buffer, offset=offset, strides=strides)


def reserve(name, offset, length):
    """Take the memory of bytes ``offset`` to ``offset + length`` of segment ``name`` now
    (POSIX, with ``posix_fallocate``; elsewhere the system takes it as it is written),
    while the name exists.

    Raises
    ------
    OSError when the memory cannot be had (/dev/shm is full).
    """
    if _posixshmem is None or not hasattr(os, "posix_fallocate") or length <= 0:
        return
    fd = _posixshmem.shm_open("/" + name, os.O_RDWR, mode=0o600)
    try:
        os.posix_fallocate(fd, int(offset), int(length))
    finally:
        os.close(fd)


def unlink(name):
    """Remove the name of a segment this process made (POSIX; on Windows the memory goes
    with its last mapping)."""
    if _posixshmem is None:
        return
    try:
        _posixshmem.shm_unlink("/" + name)
    except FileNotFoundError:
        pass
    _track(name, False)


@dataclass(frozen=True)
class Handle:
    """How an array in a segment travels to another process.

    segment : str, the segment's name. size : int, its bytes. offset : int, bytes from
    the segment's start to the array's first element. shape : tuple of int. strides :
    tuple of int, or None for C order. dtype : numpy dtype.
    """

    segment: str
    size: int
    offset: int
    shape: tuple
    strides: tuple
    dtype: np.dtype


def attach(handle, segments):
    """The array ``handle`` describes, mapping its segment once into ``segments`` (dict
    name -> Segment, kept by the caller for as long as the arrays are used)."""
    seg = segments.get(handle.segment)
    if seg is None:
        seg = segments[handle.segment] = Segment.attach(handle.segment, handle.size)
    return seg.array(handle.shape, handle.dtype, handle.offset, handle.strides)


def _root(array):
    """The object at the bottom of ``array``'s chain of bases."""
    base = array
    while isinstance(base, np.ndarray):
        base = base.base
    return base


def handle_in(array, buffer, name):
    """The Handle of ``array``, which lies in the mapping ``buffer`` of segment ``name``."""
    size = len(buffer)
    start = np.ndarray((size,), np.uint8, buffer=buffer).ctypes.data
    return Handle(name, size, array.ctypes.data - start, array.shape, array.strides, array.dtype)


class SharedArrays:
    """Arrays made in named segments, which worker processes can write into.

    A segment's name is kept while any array over it lives in this process (so that
    every run it is passed to can map it) and removed when the last goes, or at
    ``close``.
    """

    def __init__(self):
        self._lock = threading.Lock()
        # id of the mapping -> (weak reference to it, segment name); no strong reference,
        # so that the mapping goes with the last array over it
        self._names = {}

    def new(self, shape, dtype, reserve=True):
        """A zeroed ndarray of ``shape`` and ``dtype`` in a new segment; ``reserve``
        False: its memory is taken as ``reserve`` is asked for each piece before it is
        written (``Segment.create``).

        Raises
        ------
        OSError when the memory cannot be had.
        """
        dtype = np.dtype(dtype)
        count = int(np.prod(shape, dtype=np.int64))
        seg = Segment.create(count * dtype.itemsize, reserve)
        array = seg.array(shape, dtype)
        key = id(seg.buffer)
        with self._lock:
            self._names[key] = (weakref.ref(seg.buffer), seg.name)
        # when the mapping goes (with the last array over it), so does its name
        weakref.finalize(seg.buffer, self._forget, key)
        return array

    def _forget(self, key):
        with self._lock:
            entry = self._names.pop(key, None)
        if entry is not None:
            unlink(entry[1])

    def _segment_of(self, array):
        """(mapping, name) of the segment ``array`` lies in, or None."""
        root = _root(array)
        if not isinstance(root, mmap.mmap):
            return None
        with self._lock:
            entry = self._names.get(id(root))
        if entry is None or entry[0]() is not root:
            return None
        return root, entry[1]

    def handle(self, array):
        """The Handle of ``array`` when it lies in one of these segments, else None."""
        found = self._segment_of(array)
        if found is None:
            return None
        return handle_in(array, *found)

    def reserve(self, array):
        """Take the memory under ``array`` now: a C-contiguous piece of an array that
        ``new`` made with ``reserve`` False, before it is written (module ``reserve``).

        Raises
        ------
        OSError when the memory cannot be had. ValueError when ``array`` is not such a
        piece.
        """
        found = self._segment_of(array)
        if found is None or not array.flags.c_contiguous:
            raise ValueError("not a contiguous piece of a shared array")
        reserve(found[1], handle_in(array, *found).offset, array.nbytes)

    def names(self):
        """list of str, the names kept now."""
        with self._lock:
            return [name for _ref, name in self._names.values()]

    def close(self):
        """Remove every name (the arrays stay usable in this process)."""
        with self._lock:
            entries = list(self._names.values())
            self._names.clear()
        for _ref, name in entries:
            unlink(name)
