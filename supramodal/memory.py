"""Freed memory kept for the next array: numpy's temporaries reuse heap pages instead of new ones.

glibc's ``malloc`` gives a request of 128 KiB or more its own fresh pages (``mmap``) and returns
them to the system when freed, and trims the heap's top as soon as 128 KiB lie free there. A
network's epoch or a calibration fit makes dozens of temporaries of that size (2400 windows x 20
units of float64 are 375 KiB), so every one of them costs a page fault per 4 KiB on first touch,
and in a virtual machine a page fault is dear. Measured on this project's 2-core machine
(2026-11-29, one BLAS thread): the whisker reference model's network, 500 epochs, 2.26 s of CPU
with glibc's defaults, 1.04 s with :func:`keep_freed_memory`; its calibration fit 3.83 s and 2.19 s.

:func:`keep_freed_memory` raises both thresholds (:data:`MMAP_THRESHOLD`, :data:`TRIM_THRESHOLD`) for
the whole process: a setting of the application, made by the command line at its start and by the
worker processes of :mod:`supramodal.parallel` and :mod:`supramodal.experiments.runner`; a library
user may call it too. The price is memory: freed heap up to :data:`TRIM_THRESHOLD` per malloc arena (one
per thread that allocates, at most 8 per core) is kept for reuse instead of returned at once, so a
long-running node holds about each thread's peak rather than shrinking after it. Elsewhere than glibc
it does nothing.
"""

from __future__ import annotations

import ctypes
import sys

__all__ = ["MMAP_THRESHOLD", "TRIM_THRESHOLD", "keep_freed_memory"]

#: Requests at least this large still get their own pages (bytes): large arrays are made once.
MMAP_THRESHOLD = 8 * 2**20
#: Free memory at the heap's top beyond this is returned to the system (bytes).
TRIM_THRESHOLD = 32 * 2**20

# glibc's malloc.h
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def keep_freed_memory() -> bool:
    """Keep freed memory for reuse (see the module); return True where the C library took the setting.

    The C library takes it with glibc; False elsewhere. Safe to call more than once and from
    any thread.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):     # no C library symbols here, or one without mallopt
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    # Each on its own: a 32-bit glibc refuses a threshold above 512 KiB and takes the other. musl's
    # mallopt is a stub that answers 0: nothing was set.
    took_mmap = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))
    took_trim = bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return took_mmap and took_trim
