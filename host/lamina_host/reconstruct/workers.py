"""Worker processes: a scan's sections processed on every core, the same result as one.

Each section's stripe fit, assembly, outlier rejection and outline fit depend on that
section alone, so they can run side by side, in batches of whole sections
(:func:`in_batches`). Threads would not help (the work is many small numpy calls, held
by the interpreter's lock), so sections go to forked worker processes, which inherit
the imported pipeline: a freshly spawned one would spend about a second importing
numpy, SciPy and OpenCV, as long as a whole scan's processing on this host. Where
``fork`` does not exist, or inside a process that is itself a worker (``lamina batch``
already keeps every core busy with whole scans), sections are processed one after
another. Results come back in the order the tasks were given, so the outcome is the
same bit for bit whatever the number of workers.

A whole computation can also run apart (:func:`call_apart`): the terminal UI processes
a scan in a forked process of its own, so that the processing never holds the UI
process's interpreter lock while a key waits for an answer.
"""

from __future__ import annotations

import itertools
import multiprocessing
import os
import pickle
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

Task = TypeVar("Task")
Result = TypeVar("Result")

MIN_TASKS_PER_WORKER = 8
"""Sections a worker must be given for its start to pay for itself: a pool of two forked
workers starts, runs and stops in 16-19 ms from a small process (more from a large one),
and one section takes ~15-20 ms to process on a 2-core x86 host, more on a Pi."""

CHUNKS_PER_WORKER = 4
"""Chunks each worker takes in turn, so one slow chunk (a many-part section) does not
leave the other workers idle at the end."""


def worker_context() -> multiprocessing.context.BaseContext:
    """Return how worker processes start: forked where possible, so they inherit the
    imported pipeline (numpy, scipy, OpenCV, MeshLab) instead of importing it again."""
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("fork" if "fork" in methods else "spawn")


def usable_cores() -> int:
    """Return the cores this process may run on (its CPU affinity where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def workers_for(tasks: int, requested: int | None = None) -> int:
    """Return how many worker processes ``tasks`` section tasks should be shared among.

    Args:
        tasks: the number of tasks.
        requested: a worker count asked for (None: every usable core); 1 means none.

    Returns:
        1 (process here, one after another) without ``fork``, inside a worker process
        unless ``requested`` says how many (a process computing apart for a caller that
        waits, :func:`call_apart`, may use every core; a batch's worker, which asks for
        none, shares the cores with its siblings), or with fewer than
        ``MIN_TASKS_PER_WORKER`` tasks a worker; else at most ``requested`` workers, each
        given at least ``MIN_TASKS_PER_WORKER`` tasks.
    """
    wanted = usable_cores() if requested is None else max(1, requested)
    nested = requested is None and multiprocessing.parent_process() is not None
    if nested or "fork" not in multiprocessing.get_all_start_methods():
        return 1
    return max(1, min(wanted, tasks // MIN_TASKS_PER_WORKER))


def in_batches(items: Sequence[Task], workers: int) -> list[list[Task]]:
    """Split ``items`` in order into batches for ``workers`` processes to take in turn.

    Args:
        items: the work, in the order its results are wanted.
        workers: the processes that will share it (:func:`workers_for`).

    Returns:
        No batch for no items; one batch of everything for one worker; else
        ``workers * CHUNKS_PER_WORKER`` batches of near-equal length (fewer when there
        are fewer items), in order.
    """
    if not items:
        return []
    count = 1 if workers <= 1 else min(len(items), workers * CHUNKS_PER_WORKER)
    bounds = [len(items) * k // count for k in range(count + 1)]
    return [list(items[a:b]) for a, b in itertools.pairwise(bounds)]


def map_in_workers(
    function: Callable[[Task], Result], tasks: Sequence[Task], workers: int
) -> list[Result]:
    """Return ``[function(t) for t in tasks]``, computed by ``workers`` forked processes.

    ``function`` must be a module-level function and never raise (a section's failure is
    its outcome's, not the scan's). Each task goes to a worker on its own: the caller
    sizes them (:func:`in_batches`). If the pool cannot start or a worker dies (out of
    memory, killed), the tasks are done again here, one after another: a scan is never
    lost to the pool.

    Args:
        function: applied to each task.
        tasks: picklable task arguments.
        workers: processes to use; 1 computes here without a pool.

    Returns:
        The results in the order of ``tasks``.
    """
    if workers <= 1 or len(tasks) < 2 or "fork" not in multiprocessing.get_all_start_methods():
        return [function(t) for t in tasks]
    try:
        context = multiprocessing.get_context("fork")
        with ProcessPoolExecutor(workers, mp_context=context) as pool:
            return list(pool.map(function, tasks))
    except (BrokenProcessPool, OSError):
        return [function(t) for t in tasks]


def call_apart(function: Callable[..., Result], *args: Any, **kwargs: Any) -> Result:
    """Return ``function(*args, **kwargs)``, computed in a forked process of its own.

    Python runs one thread at a time: a thread of many small numpy calls, as a scan's
    processing is, takes the interpreter's lock from the thread that answers the user
    every few milliseconds, and C calls that keep it (a sparse graph's components, a
    garbage collection) hold a key's answer up past 100 ms. A forked process has a lock
    of its own and inherits the imported pipeline, so it starts in milliseconds.

    Args:
        function: a module-level function (or a partial of one), whose result pickles.
        *args: its positional arguments.
        **kwargs: its keyword arguments.

    Returns:
        What ``function`` returned. What it raised is raised here. Without ``fork``, if
        the call does not pickle (a function defined inside another), or if the process
        cannot start or dies (out of memory, killed), it is computed here instead: the
        caller never loses its result to the process.
    """
    if "fork" not in multiprocessing.get_all_start_methods():
        return function(*args, **kwargs)
    try:
        call = pickle.dumps((function, args, kwargs), pickle.HIGHEST_PROTOCOL)
        pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork"))
    except (pickle.PicklingError, AttributeError, TypeError, OSError):
        return function(*args, **kwargs)
    with pool:
        try:
            future = pool.submit(_call_pickled, call)  # the fork happens here
        except OSError:
            future = None
        if future is not None:
            try:
                return future.result()
            except BrokenProcessPool:  # the process died; what the function raised passes
                pass
    return function(*args, **kwargs)


def _call_pickled(call: bytes) -> Any:
    """Return the result of a call pickled by :func:`call_apart` (in its process)."""
    function, args, kwargs = pickle.loads(call)
    return function(*args, **kwargs)
