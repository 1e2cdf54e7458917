"""Keep glibc's allocator from handing a frame's tensor memory back to the kernel (the command's process only).

Every frame allocates and frees the same tensors, a few hundred kB to a few MB each (the CNN's activations,
the depth warp, the matcher's tables). glibc serves a block above its mmap threshold (128 kB at start,
raised by later frees, 32 MB at most) with ``mmap`` and returns it with ``munmap`` when freed, and it trims
the free top of its heap above the trim threshold. Either way the next frame's tensors land on fresh pages,
which the kernel zero-fills on first touch: thousands of minor page faults per CNN forward on CPU.

:func:`keep_freed_memory` sets, through glibc's ``mallopt``, the mmap threshold to its maximum (32 MB: a
frame's tensors come from the heap), the trim threshold to 256 MB and the top pad to 64 MB, so freed memory
stays in the process for the next frame. It is what PyTorch's CPU tuning guide gets from jemalloc or
tcmalloc, without a preloaded library. Process-wide and for good (glibc cannot report the values it
replaces), so only a process's owner may call it: ``attnloop-slam`` does (``--system-malloc`` opts out); the
libraries (``attnloop``, ``slam.pipeline``, ``slam.system``) never do.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ["MALLOPT_SETTINGS", "keep_freed_memory"]

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_MB = 1024 * 1024

#: mallopt parameter name -> value set by :func:`keep_freed_memory`.
MALLOPT_SETTINGS = {
    "M_MMAP_THRESHOLD": 32 * _MB,  # glibc's maximum on 64-bit: blocks below it come from the heap
    "M_TRIM_THRESHOLD": 256 * _MB,  # free heap top kept up to this before it is returned
    "M_TOP_PAD": 64 * _MB,  # extra taken with each heap growth, so growth is rare
}
_PARAMS = {"M_MMAP_THRESHOLD": _M_MMAP_THRESHOLD, "M_TRIM_THRESHOLD": _M_TRIM_THRESHOLD, "M_TOP_PAD": _M_TOP_PAD}


def _glibc():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # only glibc has it (musl's mallopt does nothing)  # noqa: B018
        return libc
    except (OSError, AttributeError):
        return None


def keep_freed_memory() -> bool:
    """Set :data:`MALLOPT_SETTINGS` in glibc's allocator for the rest of the process.

    Every setting is tried, each on its own (one glibc refuses does not stop the others); each is a
    performance setting only. With another allocator preloaded (jemalloc, tcmalloc: ``LD_PRELOAD``) glibc's
    settings do nothing, and that allocator already keeps freed memory.

    Returns:
        True when glibc took every setting; False where there is no glibc (macOS, Windows, musl) or it
        refused one.
    """
    libc = _glibc()
    if libc is None:
        return False
    taken = [libc.mallopt(_PARAMS[name], value) == 1 for name, value in MALLOPT_SETTINGS.items()]
    return all(taken)
