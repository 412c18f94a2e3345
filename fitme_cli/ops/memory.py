"""Process-wide memory policy for the CPU hot loops.

glibc serves blocks above its mmap threshold (128 KiB, growing to at most 32 MiB) with fresh mmaps and
returns them to the kernel when freed, so every render's 512^2 texture gradients and every GAN layer's
activations come back as new pages: one page fault per 4 KiB on first touch. Measured here (2-core VM,
render + backward at 256^2, all effects): faulting in the 7 MB of texture gradients cost 3 ms serially
and 14 ms when two threads faulted at once; with freed memory kept in the heap the
same zeroing costs 0.4 ms. The price is that the process keeps its peak heap mapped (its peak RSS is
unchanged)."""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ["retain_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_done = False


def retain_freed_memory(mmap_threshold_mib: int = 256, trim_threshold_mib: int = 1024) -> bool:
    """Serve blocks below ``mmap_threshold_mib`` from the heap and keep up to ``trim_threshold_mib`` of
    freed heap mapped. Called by the ``fitme`` commands and worker processes, not at import. Returns
    False where it does not apply (not glibc)."""
    global _done
    if _done:
        return True
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others: no mallopt
        return False
    ok = bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold_mib << 20)) and bool(mallopt(_M_TRIM_THRESHOLD, trim_threshold_mib << 20))
    _done = ok
    return ok
