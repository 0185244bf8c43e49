"""Wall-clock timing of a step (the benchmarks of ``dvr-perception bench`` and the report)."""

from __future__ import annotations

import statistics
import time

__all__ = ["median_time"]


def median_time(fn, repeat: int) -> float:
    """Median wall-clock seconds of ``repeat`` calls of ``fn()``.

    Examples
    --------
    >>> calls = []
    >>> median_time(lambda: calls.append(1), 3) >= 0.0, len(calls)
    (True, 3)
    """
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(statistics.median(times))
