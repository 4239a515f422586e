"""Timing helpers shared by the benchmarks."""

from __future__ import annotations

import time
from collections.abc import Callable


def best_time_s(run: Callable[[], object], repeats: int = 7, batch_s: float = 0.02) -> float:
    """Return the time of one run: the fastest of ``repeats`` batches (least disturbed).

    Runs shorter than ``batch_s`` are timed in batches of that length, so that the
    timer's own resolution and one-off disturbances do not dominate sub-millisecond
    figures; longer runs are timed one at a time.
    """
    start = time.perf_counter()
    run()
    once_s = time.perf_counter() - start
    number = max(1, int(batch_s / max(once_s, 1e-9)))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(number):
            run()
        times.append((time.perf_counter() - start) / number)
    return min(times)
