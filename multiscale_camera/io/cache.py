"""The field cache: built ray fields kept in memory and on disk, keyed by ``field_key``.

A field depends only on the cameras, the masks, the method and its settings (the digest
``core.methods.field_key``), so moving a light or editing a material renders again
without a rebuild, and a field built yesterday is still good today. Fields live

- in memory: the ``KEEP_IN_MEMORY`` newest, for renders in a row;
- on disk: one ``<key>.npz`` per field (``io.fields.field_to_arrays``) in the
  extension's user folder (``bpy.utils.extension_path_user(__package__, "cache")``),
  the least recently used removed first once the folder outgrows its size limit.

A scene may name its own folder (``use_folder``), such as one beside the .blend on a
render farm's shared storage; there several processes share it: ``build_lock`` gives
one of them the build of a field (``io.locks``), and ``record_build`` notes in
``builds.jsonl`` who built which field, when and in how many seconds.

The field service (``render.fields.SERVICE``) owns the one cache every caller uses.
Only ``default_folder`` touches bpy; the rest is plain Python and numpy.
"""

import hashlib
import json
import os
import tempfile
import threading
import time
import zipfile

import numpy as np

from ..core.quality import MB
from .fields import field_from_arrays, field_to_arrays
from .locks import BuildLock, holder_id

# Fields kept in memory, newest last: two covers a render after a preview build.
KEEP_IN_MEMORY = 2
# Default size limit of the disk cache, megabytes: a few 1080p three-camera fields.
DEFAULT_LIMIT_MB = 2048
# Environment variable that overrides the cache folder (scripts, tests, farms).
FOLDER_ENV = "MULTISCALE_CACHE_DIR"
SUFFIX = ".npz"
# Fields read or written this recently are in use (a farm's other workers may be about
# to read them): trimming leaves them, seconds.
IN_USE_SECONDS = 600.0
# One JSON line per field built into a folder: {"key", "host", "pid", "time", "seconds"}.
BUILDS_LOG = "builds.jsonl"
# The array of an entry that holds the checksum of all the others (``checksum``).
CHECKSUM = "checksum"
# What the user reads when a disk entry is refused (deleted; the field is built again).
DAMAGED = (
    "The cached field '{name}' was damaged ({why}): it was deleted and the field is built again"
)
UNUSABLE = (
    "The field cache folder '{folder}' cannot be used ({err}): fields are kept in memory "
    "only, for this session; point ${env} at a writable folder to keep them on disk"
)


def default_folder():
    """The cache folder: $MULTISCALE_CACHE_DIR, else the extension's user folder
    ``cache`` (created), else (the package loaded as a plain add-on) ``multiscale_camera/
    cache`` in Blender's user config folder."""
    env = os.environ.get(FOLDER_ENV)
    if env:
        os.makedirs(env, exist_ok=True)
        return env
    import bpy  # here only: the rest of the cache runs in plain Python, without Blender

    package = __package__.rpartition(".")[0]  # the package, not its io module
    try:
        return bpy.utils.extension_path_user(package, path="cache", create=True)
    except ValueError:  # not installed as an extension
        folder = os.path.join(bpy.utils.user_resource("CONFIG"), "multiscale_camera", "cache")
        os.makedirs(folder, exist_ok=True)
        return folder


class FieldCache:
    """Ray fields by key, in memory and in ``folder`` on disk.

    Parameters
    ----------
    folder : str or None, the disk cache (None: memory only, or ``default_folder()``
        on first use when ``lazy_folder``).
    limit_mb : float, size limit of the disk cache, megabytes.

    Attributes
    ----------
    hits, misses : int, counted by ``get`` (a hit in memory or on disk, or a miss).
    disk_hits : int, the hits read from disk.
    """

    def __init__(self, folder=None, limit_mb=DEFAULT_LIMIT_MB, lazy_folder=False):
        self._folder = folder
        self._lazy = lazy_folder and folder is None
        self._chosen = None  # use_folder's, e.g. a scene's folder beside its .blend
        self.limit_mb = float(limit_mb)
        self.memory = {}
        # the memory entries are read by the live picture's thread too (get, trim)
        self._memory_lock = threading.RLock()
        self.hits = self.misses = self.disk_hits = 0
        self._notices = []

    @property
    def folder(self):
        """The folder in use: the one ``use_folder`` chose, else the default, or None
        (memory only: none was given, or the default could not be used, which
        ``take_notices`` then says)."""
        if self._chosen:
            return self._chosen
        if self._folder is None and self._lazy:
            self._lazy = False
            try:
                self._folder = default_folder()
            except OSError as err:  # a file in its place, no permission: memory only
                where = getattr(err, "filename", None) or os.environ.get(FOLDER_ENV, "")
                self._notices.append(
                    UNUSABLE.format(folder=where, err=err.strerror or err, env=FOLDER_ENV)
                )
        return self._folder

    def use_folder(self, folder):
        """Keep fields in ``folder`` from now on (None or "": the default folder again).
        The fields in memory stay: their keys say what they are, wherever they came
        from."""
        self._chosen = folder or None

    def peek(self, key, rig):
        """The field under ``key`` on disk, or None, without counting a hit or a miss
        (a process waiting for another one's build looks again and again)."""
        fld = self.memory.get(key)
        if fld is not None:
            return fld
        fld = self._read(key, rig) if self.folder else None
        if fld is not None:
            self._remember(key, fld)
        return fld

    def build_lock(self, key):
        """The ``io.locks.BuildLock`` of ``key``'s field in the folder (created), or
        None without a disk cache or when the folder cannot be made (the field is then
        built here, and ``put`` says why it is not kept)."""
        if not self.folder:
            return None
        try:
            os.makedirs(self.folder, exist_ok=True)
        except OSError:
            return None
        return BuildLock(self.folder, key)

    def record_build(self, key, seconds):
        """Note in ``builds.jsonl`` that this process built ``key``'s field (one
        appended line: concurrent writers do not interleave). Errors are ignored: the
        note is for people reading the folder."""
        if not self.folder:
            return
        line = json.dumps({"key": key, **holder_id(), "time": time.time(), "seconds": seconds})
        try:
            with open(os.path.join(self.folder, BUILDS_LOG), "a") as out:
                out.write(line + "\n")
        except OSError:
            pass

    def builds(self):
        """[dict] of ``builds.jsonl``, oldest first ([] without one)."""
        try:
            with open(os.path.join(self.folder, BUILDS_LOG)) as f:
                return [json.loads(line) for line in f if line.strip()]
        except (OSError, TypeError):
            return []

    def take_notices(self):
        """What the cache had to say since last asked (damaged entries deleted, an
        unusable folder), oldest first; forgotten once taken."""
        said, self._notices = self._notices, []
        return said

    def path(self, key):
        return os.path.join(self.folder, key + SUFFIX)

    def get(self, key, rig):
        """The field stored under ``key`` (for ``rig``, the rig it was built from), or
        None. A disk entry that cannot be read is removed and counts as a miss."""
        with self._memory_lock:
            if key in self.memory:
                fld = self.memory[key] = self.memory.pop(key)
                self.hits += 1
                return fld
        fld = self._read(key, rig) if self.folder else None
        if fld is None:
            self.misses += 1
            return None
        self.hits += 1
        self.disk_hits += 1
        self._remember(key, fld)
        return fld

    def put(self, key, fld):
        """Keep ``fld`` under ``key`` in memory and on disk (then trim to the limit).
        A disk that refuses the write leaves the memory entry; the error is returned
        as a message (None when all went well)."""
        self._remember(key, fld)
        if not self.folder:
            return None
        try:
            self._write(key, fld)
        except OSError as err:
            return f"The field cache could not be written ({err}); builds are not kept on disk"
        self.trim()
        return None

    def _remember(self, key, fld):
        with self._memory_lock:
            self.memory.pop(key, None)
            self.memory[key] = fld
            while len(self.memory) > KEEP_IN_MEMORY:
                self.memory.pop(next(iter(self.memory)))

    def _write(self, key, fld):
        """Write the entry atomically: into a temporary file of a unique name in the
        same folder, then renamed over ``path(key)`` (``os.replace``): a reader in
        another process sees the old entry or the new one, never part of one; two
        writers of the same key leave one whole entry."""
        arrays = field_to_arrays(fld)
        arrays[CHECKSUM] = checksum(arrays)
        os.makedirs(self.folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".writing-", suffix=SUFFIX, dir=self.folder)
        try:
            with os.fdopen(fd, "wb") as out:
                np.savez(out, **arrays)
            os.replace(tmp, self.path(key))
        except BaseException:
            if os.path.exists(tmp):
                os.remove(tmp)
            raise

    def _read(self, key, rig):
        """The entry's field, or None. An entry that does not load, or whose arrays do
        not match their checksum, is deleted (and said: ``take_notices``)."""
        path = self.path(key)
        if not os.path.isfile(path):
            return None
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
            stored = arrays.pop(CHECKSUM, None)
            if stored is None:
                raise ValueError("it has no checksum")
            if not np.array_equal(stored, checksum(arrays)):
                raise ValueError("its arrays do not match their checksum")
            fld = field_from_arrays(arrays, rig)
        except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as err:
            self._notices.append(DAMAGED.format(name=os.path.basename(path), why=err))
            try:
                os.remove(path)
            except OSError:  # another process removed it first
                pass
            return None
        os.utime(path)  # least recently used goes first
        return fld

    def entries(self):
        """[(path, bytes, mtime)] of the disk cache, oldest first."""
        folder = self.folder
        if not folder or not os.path.isdir(folder):
            return []
        out = []
        for name in os.listdir(folder):
            if name.endswith(SUFFIX) and not name.startswith(".writing-"):
                p = os.path.join(folder, name)
                try:
                    st = os.stat(p)
                except OSError:
                    continue
                out.append((p, st.st_size, st.st_mtime))
        return sorted(out, key=lambda e: e[2])

    def size_bytes(self):
        """Bytes the disk cache holds."""
        return sum(size for _p, size, _t in self.entries())

    def trim(self, limit_mb=None):
        """Remove the least recently used disk entries until the cache fits its limit
        (the newest entry stays even if it alone is larger, and so do the entries used
        in the last ``IN_USE_SECONDS``: in a folder shared by a farm's workers, fields
        a running job still needs). The limit is in MB of 2**20 bytes (``core.quality.MB``,
        as Blender and the Memory Budget count). Returns the files removed."""
        limit = (self.limit_mb if limit_mb is None else float(limit_mb)) * MB
        entries = self.entries()
        total = sum(e[1] for e in entries)
        removed = 0
        now = time.time()
        for p, size, used in entries[:-1]:
            if total <= limit or now - used < IN_USE_SECONDS:
                break  # oldest first: the rest are newer still
            try:
                os.remove(p)
            except OSError:
                continue
            total -= size
            removed += 1
        return removed

    def clear(self, disk=True):
        """Forget every field in memory and (``disk``) on disk: in the folder in use and
        in the default one (a scene's own folder, ``use_folder``, may be the one in use
        while the next scene reads the default). Returns files removed."""
        with self._memory_lock:
            self.memory.clear()
        removed = 0
        if disk:
            chosen = self._chosen
            try:
                for choice in dict.fromkeys((chosen, None)):
                    self._chosen = choice
                    for p, _size, _t in self.entries():
                        try:
                            os.remove(p)
                            removed += 1
                        except OSError:
                            pass
            finally:
                self._chosen = chosen
        return removed


def checksum(arrays):
    """(32,) uint8 BLAKE2b digest of a dict of arrays: every name, dtype, shape and
    byte, in the order of the sorted names."""
    digest = hashlib.blake2b(digest_size=32)
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        digest.update(a.tobytes())
    return np.frombuffer(digest.digest(), dtype=np.uint8)
