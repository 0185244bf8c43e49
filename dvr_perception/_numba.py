"""Where the numba kernels come from: numba when it can be imported and is not switched off."""

from __future__ import annotations

import importlib
import os
import sys
from contextlib import contextmanager

#: Below this much work (cached entries, pixels: the caller's count) a parallel kernel runs
#: on the calling thread alone: waking numba's threads for a region costs more than they save
#: (tens of microseconds on an idle machine, milliseconds on a busy one), and the optimiser
#: runs hundreds of such small regions.  Every kernel gives the same numbers on any number
#: of threads (the work is split by rays or rows), so this changes timing only.
SERIAL_WORK = 1 << 16


def kernels(module: str):
    """Return the kernel module ``module`` (imported), or None without numba.

    None when numba cannot be imported or the environment variable
    ``DVR_PERCEPTION_NO_NUMBA`` is set to anything but ``""`` or ``"0"``; the callers then
    use their numpy code.
    """
    if os.environ.get("DVR_PERCEPTION_NO_NUMBA", "").strip() not in ("", "0"):
        return None
    try:
        return importlib.import_module(module)
    except ImportError:
        return None


@contextmanager
def serial_below(work: int, limit: int = SERIAL_WORK):
    """Run the numba kernels called inside on this thread alone when ``work < limit``.

    ``numba.set_num_threads(1)`` for the block (numba's thread count is per calling thread;
    the previous one is restored).  Nothing changes when numba is not in use here or the
    work is large enough.
    """
    numba = sys.modules.get("numba")
    if work >= limit or numba is None:
        yield
        return
    try:
        before = numba.get_num_threads()
    except (AttributeError, RuntimeError, ValueError):  # no threading layer available
        yield
        return
    if before == 1:
        yield
        return
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(before)
