"""What travels between the parent and a worker: pickled messages over a pipe, each
preceded by its length, and task payloads whose large arrays travel as shared-memory
handles (``shared.Handle``) rather than bytes.

A worker writes ``MARKER`` on a line of its own before its first message: whatever a
host program printed before (Blender's banner) is skipped up to it.
"""

import io
import pickle
import struct

import numpy as np

from .shared import Handle, Segment, attach

# The line a worker writes before its first message.
MARKER = b"\x00multiscale-camera worker protocol 1\n"
_LENGTH = struct.Struct("<Q")
PROTOCOL = pickle.HIGHEST_PROTOCOL
# Arrays smaller than this travel inside the pickle: a segment costs a system call, a
# page fault and a name; below a few hundred kB the copy through the pipe costs less.
INLINE_BYTES = 256 * 1024


def encode(message):
    """bytes: ``message`` pickled.

    Raises
    ------
    pickle.PicklingError, TypeError, AttributeError when it cannot be pickled.
    """
    return pickle.dumps(message, protocol=PROTOCOL)


def write_frame(stream, data):
    """Write ``data`` (``encode``) onto the binary ``stream``, length first, and flush."""
    stream.write(_LENGTH.pack(len(data)))
    stream.write(data)
    stream.flush()


def write_message(stream, message):
    """Pickle ``message`` onto the binary ``stream``, length first, and flush."""
    write_frame(stream, encode(message))


def read_message(stream):
    """The next message from the binary ``stream``, or None at its end."""
    head = stream.read(_LENGTH.size)
    if len(head) < _LENGTH.size:
        return None
    (length,) = _LENGTH.unpack(head)
    data = stream.read(length)
    if len(data) < length:
        return None
    return pickle.loads(data)


def skip_to_marker(stream):
    """Read ``stream`` up to and including the MARKER line; False at its end first."""
    while True:
        line = stream.readline()
        if not line:
            return False
        if line == MARKER:
            return True


class _Pickler(pickle.Pickler):
    """A pickler that hands every ndarray to ``publish`` (array -> Handle or None)."""

    def __init__(self, file, publish):
        super().__init__(file, protocol=PROTOCOL)
        self._publish = publish

    def persistent_id(self, obj):
        if type(obj) is np.ndarray:
            return self._publish(obj)
        return None


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, segments):
        super().__init__(file)
        self._segments = segments

    def persistent_load(self, pid):
        if not isinstance(pid, Handle):
            raise pickle.UnpicklingError(f"unknown persistent id {pid!r}")
        return attach(pid, self._segments)


def dump_payload(obj, shared, copies):
    """``obj`` pickled for workers: arrays in ``shared`` (``SharedArrays``) travel as
    handles to their own memory (what workers write there, the parent sees); other
    arrays of ``INLINE_BYTES`` or more are copied into new segments, appended to
    ``copies`` (the caller unlinks them when no worker needs to map them any more).

    Raises
    ------
    pickle.PicklingError, TypeError, AttributeError when ``obj`` cannot be pickled.
    OSError when shared memory cannot be had.
    """
    seen = {}  # id -> (array, handle): an array met twice is copied once

    def publish(array):
        known = seen.get(id(array))
        if known is not None:
            return known[1]
        handle = shared.handle(array)
        if handle is None and array.nbytes >= INLINE_BYTES and not array.dtype.hasobject:
            seg = Segment.holding(array)
            copies.append(seg)
            handle = Handle(seg.name, seg.size, 0, array.shape, None, array.dtype)
        seen[id(array)] = (array, handle)
        return handle

    out = io.BytesIO()
    _Pickler(out, publish).dump(obj)
    return out.getvalue()


def load_payload(data, segments):
    """The object ``dump_payload`` pickled, its arrays mapped into ``segments`` (dict
    name -> Segment, kept for as long as the object is used)."""
    return _Unpickler(io.BytesIO(data), segments).load()
