"""Timing helpers shared by the benchmarks."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext

import cv2
import numpy as np

from lamina_device.extract import run_opencv_inline


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


def timed_with_subtraction(
    run: Callable[[], object], on: np.ndarray, off: np.ndarray, rounds: int, inline: bool = True
) -> tuple[float, float]:
    """Return the best time of ``run`` and of one subtraction, timed in turn ``rounds`` times.

    Timed in turn, the two meet the same state of a shared machine, so their ratio
    compares like with like. ``inline`` runs OpenCV on the calling thread, as the device
    program does on the box (:func:`run_opencv_inline`); otherwise with OpenCV's own
    threads, as Horus runs.
    """
    subtract_s = run_s = math.inf
    with opencv_inline() if inline else nullcontext():
        for _ in range(rounds):
            subtract_s = min(subtract_s, best_time_s(lambda: np.subtract(on, off, dtype=np.int16)))
            run_s = min(run_s, best_time_s(run))
    return run_s, subtract_s


@contextmanager
def opencv_inline() -> Iterator[None]:
    """Run OpenCV on the calling thread within (as the device program runs it on the box),
    then with OpenCV's default threads again, for whatever runs next."""
    run_opencv_inline()
    try:
        yield
    finally:
        cv2.setNumThreads(-1)
