"""Keep freed memory in the process: no page goes back to the kernel while audio runs.

The frame loop allocates and frees megabytes per frame (read-back images, llvmpipe's tiles, numpy temporaries).
glibc returns such memory to the kernel (``munmap`` of large chunks, trimming the top of the heap) and the next
frame faults it back in, zeroed. On a virtual machine with free-page reporting (the virtio-balloon device of the
machines here has it) freed pages probably also go back to the host, and touching them again stalls the whole
virtual CPU there (the mechanism is inferred; the effect is measured). Measured with ``cyclictest -p 90`` beside
``sonicverse audio loopback-test --load frames``, three 30 s runs each: the worst wake-up of a FIFO-90 thread was
8.7-18 ms with glibc's defaults (longer than a 5.3 ms JACK period: the xruns), 2.1-3.3 ms with the heap kept from
process start, and 8.4-9.2 ms when the settings came only after the renderer was up. So the processes of a live
session keep their heap from the start (the environment below for the workers; ``sonicverse vr``, ``audio`` and
``bench vr`` call :func:`keep_heap` before anything else): large blocks come from the heap instead of ``mmap``, and
the heap top is never trimmed. The price is that a process's resident size stays at its high-water mark.
"""
from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
MMAP_THRESHOLD = 32 << 20  # glibc's largest allowed value on 64-bit
TRIM_THRESHOLD = (1 << 31) - 1  # mallopt takes an int: effectively never trim
TOP_PAD = 256 << 20  # the heap grows in 256 MiB steps (address space; pages become resident when touched)
#: the same settings for a process about to start (glibc reads them before its first allocation)
ENV = {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD), "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD),
       "MALLOC_TOP_PAD_": str(TOP_PAD)}

_kept = None


def keep_heap() -> bool:
    """Tune this process's glibc allocator as above (idempotent); False where the C library is not glibc."""
    global _kept
    if _kept is None:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            mallopt = libc.mallopt
        except (OSError, AttributeError):
            _kept = False
            return _kept
        mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
        _kept = all(mallopt(p, v) == 1 for p, v in ((M_MMAP_THRESHOLD, MMAP_THRESHOLD),
                                                       (M_TRIM_THRESHOLD, TRIM_THRESHOLD), (M_TOP_PAD, TOP_PAD)))
    return _kept
