"""Freed memory handed back to the system.

glibc's allocator serves arrays below its mmap threshold (which rises to 32 MB once an
array that large has been freed) from its heap, and freed heap pages stay with the
process wherever a live block lies above them. A build that traces hundreds of
thousands of rays in rounds frees gigabytes of such temporaries between long-lived
arrays: on the 1000x rig at 960x540 the build's process held 659 MB after the last
merge where 335 MB were live, and then the report's peak came on top of both.
``release_free_memory`` asks glibc to hand every free page back (``malloc_trim``);
elsewhere (macOS, Windows: other allocators) it does nothing.
"""

import ctypes
import ctypes.util


def _malloc_trim():
    """glibc's ``malloc_trim``, or None where the C library has none."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


_TRIM = _malloc_trim()


def release_free_memory():
    """Hand the heap's free pages back to the system. Returns bool: whether any went
    back (False where the C library cannot say: not glibc)."""
    if _TRIM is None:
        return False
    return bool(_TRIM(0))
