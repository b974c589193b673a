"""The C allocator of a long diagnosis process: freed arrays go back to the system.

glibc's ``malloc`` serves a block of at least ``M_MMAP_THRESHOLD`` bytes by a mapping of
its own, returned to the system when freed; smaller blocks come from the heap, whose freed
memory the process keeps.  The threshold starts at 128 kB and *rises* to the size of each
mapped block freed (up to 32 MB), so after the first arrays of a few MB are dropped, every
array below that size lives on the heap for the rest of the process: a ``diagnose`` round
of a 2-h bag (arrays of 1-20 MB made and dropped by each stage) kept ≈ 90 MB it no longer
used at its peak (doc/benchmarks.md, "the allocator").  :func:`return_freed_arrays` fixes
the threshold (which also stops it rising).  The numbers computed are the same: only where
the bytes live changes.  :func:`trim_freed` then hands back, between a round's stages, the
heap's free pages that smaller blocks left (``malloc_trim``): ≈ 45 MB after the 2-h bag's
read, ≈ 50 MB after its screening run, which the next stage's mapped arrays would otherwise
have sat beside.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import sys
from collections.abc import Iterator

#: glibc's ``mallopt`` parameter number of the mapping threshold
M_MMAP_THRESHOLD = -3
#: blocks of at least this many bytes are mapped (and unmapped when freed): 8 MB.  A
#: mapped block's pages are faulted in afresh each time (≈ 900 faults for a 2-h table's
#: 457 000-row column of 3.7 MB, 1 800 for its stacked u, v or (n, 2) columns); below the
#: threshold the heap reuses the pages a freed temporary left.  numpy asks for huge pages
#: on arrays of 4 MB and more (``madvise``): a mapped one faults once per 2 MB.  The 2-h
#: round (doc/benchmarks.md, H237): 1 MB 1.71 M faults, 5.5 s system CPU, 489 MB peak; 4 MB
#: 0.86 M, 3.2 s, 490 MB; 8 MB 0.62 M, 2.4 s, 491 MB; 32 MB 0.56 M, 2.2 s, 501 MB
MMAP_THRESHOLD = 1 << 23
#: glibc's own environment setting of the same; a user's value is left alone
ENV = "MALLOC_MMAP_THRESHOLD_"
#: glibc's ``malloc_trim``, once :func:`return_freed_arrays` set the threshold here
_TRIM: list = [None]


def return_freed_arrays(threshold: int = MMAP_THRESHOLD) -> bool:
    """Fix glibc's mapping threshold at ``threshold`` bytes; whether it was set.

    Nothing on another C library or platform, or where the user set :data:`ENV`.
    """
    if not sys.platform.startswith("linux") or ENV in os.environ:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    if not mallopt(M_MMAP_THRESHOLD, int(threshold)):
        return False
    try:
        malloc_trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        malloc_trim = None
    else:
        malloc_trim.argtypes = [ctypes.c_size_t]
        malloc_trim.restype = ctypes.c_int
    _TRIM[0] = malloc_trim
    return True


def trim_freed() -> bool:
    """Return the heap's free pages to the system (glibc's ``malloc_trim(0)``); whether done.

    Only where :func:`return_freed_arrays` set the threshold (a diagnosis process, its
    workers).  A few ms on a 2-h round's heap; the pages a later stage touches again are
    faulted in afresh.
    """
    if _TRIM[0] is None:
        return False
    _TRIM[0](0)
    return True


@contextlib.contextmanager
def frozen_objects() -> Iterator[None]:
    """The objects alive now left out of the cyclic collector's passes while the block runs.

    ``gc.freeze`` (undone by ``gc.unfreeze`` at the end): a diagnosis process holds
    ~100 000 objects of its imports (numba's, scipy's) that every full collection walked
    again, ≈ 60 ms each, 8 on a 2-h round (0.48 of its 0.64 CPU-s in the collector).  No
    number changes: only which objects a collection visits; garbage among the frozen ones
    is collected again after the block.  Where objects are frozen already (a calibrator
    node freezes its start-up's) nothing is done: ``gc.unfreeze`` would thaw them too.
    """
    if gc.get_freeze_count():
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
