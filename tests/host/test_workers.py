"""Sections shared among worker processes: the same result bit for bit, never a lost scan."""

from __future__ import annotations

import functools
import multiprocessing
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from lamina_device.sim import Rig, SimScene
from lamina_host.reconstruct import workers
from lamina_host.reconstruct.pipeline import ProcessOptions, Reconstruction, reconstruct
from lamina_host.reconstruct.workers import (
    CHUNKS_PER_WORKER,
    MIN_TASKS_PER_WORKER,
    call_apart,
    in_batches,
    map_in_workers,
    usable_cores,
    workers_for,
)
from lamina_shared.errors import InputError
from lamina_shared.types import Segment
from tests.helpers.shapes import circle, view_segment

forks = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="fork and /proc/self are Linux's"
)

SECTIONS, VIEWS = 20, 8


def random_scan(seed: int, colour: bool = False) -> tuple[Rig, list[Segment], list[Segment]]:
    """Return a rig, its cylinder's views and a random lobed object's views.

    Each section's outline has its own random lobes; sections 3 and 11 keep one view
    only (nothing confirms their points: failed outlines), section 7 none at all. With
    ``colour`` every object point carries a random colour.
    """
    rig = Rig()
    rng = np.random.default_rng(seed)
    cyl = circle(rig.cylinder_offset_mm, rig.cylinder_diameter_mm / 2.0)
    cylinder = [
        s for v in range(8)
        if (s := view_segment(rig, "cylinder", 0, v, 0.0, 45.0 * v, 45.0 * v, cyl, rng, 0.3))
    ]  # fmt: skip
    phi = np.linspace(0.0, 2.0 * np.pi, 4000, endpoint=False)
    segments = []
    for k in range(SECTIONS):
        lobes = rng.integers(2, 6)
        radius = 9.0 + rng.uniform(0.3, 1.5) * np.cos(lobes * phi + rng.uniform(0, 2 * np.pi))
        outline = radius[:, None] * np.stack([np.cos(phi), np.sin(phi)], axis=1)
        views = {3: 1, 11: 1, 7: 0}.get(k, VIEWS)
        for v in range(views):
            angle = 360.0 * v / VIEWS
            s = view_segment(rig, "object", k, v, 2.0 * k, angle, angle, outline, rng, 0.3)
            if s is not None and colour:
                s = replace(s, colour=rng.integers(0, 256, (len(s), 3), dtype=np.uint8))
            if s is not None:
                segments.append(s)
    return rig, cylinder, segments


def processed(rig: Rig, cylinder: list[Segment], segments: list[Segment], n: int | None) -> Any:
    """Return everything a reconstruction with ``n`` workers reports, in comparable form."""
    grid = SimScene(rig).render("grid", 0.0, 0.0, False)
    result: Reconstruction = reconstruct(
        grid, rig.board, cylinder, rig.cylinder_diameter_mm, segments, ProcessOptions(),
        workers=n,
    )  # fmt: skip
    return (
        [(s.index, s.part, s.status, s.contour.tobytes(), s.measured_contour.tobytes(),
          None if s.colours is None else (s.colour_points.tobytes(), s.colours.tobytes()))
         for s in result.sections],
        [(f.index, f.part, f.points, f.reason) for f in result.failed],
        result.rejected, result.warnings, result.vertices.tobytes(), result.faces.tobytes(),
    )  # fmt: skip


@forks
@pytest.mark.timeout(240)
@pytest.mark.parametrize(("seed", "colour"), [(0, False), (1, True)])
def test_workers_give_the_same_scan_bit_for_bit_as_one_process(
    seed: int, colour: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Random lobed sections, some failing, processed by 1, 2 and 3 workers: the same
    outlines, failures, rejections, warnings, mesh and colours, byte for byte."""
    rig, cylinder, segments = random_scan(seed, colour)
    pools: list[int] = []

    class CountedPool(ProcessPoolExecutor):
        def map(self, *args: Any, **kwargs: Any) -> Any:  # type: ignore[override]
            done = list(super().map(*args, **kwargs))
            pools.append(len(done))
            return iter(done)

    monkeypatch.setattr(workers, "ProcessPoolExecutor", CountedPool)
    one = processed(rig, cylinder, segments, 1)
    assert pools == []  # one worker: no pool
    failed = {f[0] for f in one[1]}
    assert {3, 11} <= failed and 7 not in {s[0] for s in one[0]}
    assert len({s[0] for s in one[0]}) == SECTIONS - 3
    # Colour comes back from the workers with each section's views.
    assert all((s[5] is not None) == colour for s in one[0])
    for n in (2, 3):
        assert processed(rig, cylinder, segments, n) == one
    # Both runs went through a pool (19 sections with stripes: 2 workers' worth, not 3),
    # in batches of whole sections, each worker's share in CHUNKS_PER_WORKER of them.
    assert pools == [2 * CHUNKS_PER_WORKER, 2 * CHUNKS_PER_WORKER]


@forks
def test_tasks_are_shared_among_other_processes_and_come_back_in_order() -> None:
    """Each task is read in a worker (its own /proc/self), the results in task order."""
    tasks = [f"/proc/{name}" for name in ("self", "thread-self")] * 20
    pids = map_in_workers(os.readlink, tasks, 2)
    assert len(pids) == len(tasks)
    assert str(os.getpid()) not in {p.split("/")[0] for p in pids}
    assert [p.count("/") for p in pids] == [0, 2] * 20  # order kept
    assert map_in_workers(abs, list(range(-30, 0)), 2) == list(range(30, 0, -1))


@forks
def test_a_worker_shares_nothing_further_unless_told_how_many() -> None:
    """Inside a worker process (``lamina batch``), sections are processed there; a process
    computing apart for a caller that waits (the terminal UI's) shares them as asked."""
    inside = map_in_workers(functools.partial(workers_for, requested=None), [400] * 16, 2)
    assert inside == [1] * 16
    assert workers_for(400, 4) == min(4, 400 // MIN_TASKS_PER_WORKER)
    told = map_in_workers(functools.partial(workers_for, requested=4), [400] * 16, 2)
    assert told == [min(4, 400 // MIN_TASKS_PER_WORKER)] * 16
    assert call_apart(workers_for, 400, 3) == 3
    assert call_apart(workers_for, 400) == 1


def test_few_tasks_or_one_core_use_no_pool() -> None:
    """A worker is only started for ``MIN_TASKS_PER_WORKER`` tasks of its own."""
    assert workers_for(2 * MIN_TASKS_PER_WORKER - 1, 2) == 1
    assert workers_for(2 * MIN_TASKS_PER_WORKER, 2) == 2
    assert workers_for(100 * MIN_TASKS_PER_WORKER, 1) == 1
    assert workers_for(0, None) == 1
    assert workers_for(10_000, None) == min(usable_cores(), 10_000 // MIN_TASKS_PER_WORKER)


def test_a_pool_that_cannot_start_costs_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    """No process can be forked (memory, limits): every task is done here instead."""

    def refused(*_: Any, **__: Any) -> None:
        raise OSError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(workers, "ProcessPoolExecutor", refused)
    assert map_in_workers(abs, list(range(-30, 0)), 2) == list(range(30, 0, -1))


def dies_in_a_worker(value: int) -> int:
    """Return ``abs(value)`` here; end a worker process abruptly (as the OOM killer would)."""
    if multiprocessing.parent_process() is not None:
        os._exit(137)
    return abs(value)


@forks
def test_a_worker_that_dies_costs_nothing() -> None:
    """A worker killed mid-scan breaks the pool: every task is done again here."""
    assert map_in_workers(dies_in_a_worker, list(range(-30, 0)), 2) == list(range(30, 0, -1))


@pytest.mark.timeout(30)
@pytest.mark.parametrize(
    ("items", "workers", "sizes"),
    [
        (0, 2, []),
        (1, 2, [1]),
        (19, 1, [19]),
        (3, 2, [1, 1, 1]),
        (8, 2, [1] * 8),
        (9, 2, [1, 1, 1, 1, 1, 1, 1, 2]),
        (19, 2, [2, 2, 3, 2, 2, 3, 2, 3]),
        (100, 3, [8, 8, 9, 8, 8, 9, 8, 8, 9, 8, 8, 9]),
    ],
)
def test_batches_keep_every_item_once_in_order_and_near_equal(
    items: int, workers: int, sizes: list[int]
) -> None:
    """Sections split for the workers: none lost, none twice, none reordered; one batch
    for one worker, else CHUNKS_PER_WORKER a worker (fewer for fewer sections), their
    lengths at most one apart."""
    assert CHUNKS_PER_WORKER == 4  # the sizes below are for four batches a worker
    batches = in_batches(list(range(items)), workers)
    assert [x for b in batches for x in b] == list(range(items))
    assert [len(b) for b in batches] == sizes


def refused_apart(reason: str) -> int:
    """Raise the caller's kind of error, naming the process that raised it."""
    raise InputError(f"{reason} in process {os.getpid()}")


@forks
def test_a_call_apart_runs_in_a_process_of_its_own() -> None:
    """The result and what was raised come back; the work was done in another process."""
    assert call_apart(os.getpid) != os.getpid()
    assert call_apart(divmod, 7, 2) == (3, 1)
    assert call_apart(int, "ff", base=16) == 255
    with pytest.raises(InputError, match="no stripe in process") as raised:
        call_apart(refused_apart, "no stripe")
    assert str(os.getpid()) not in str(raised.value)  # raised there, not computed again here


@forks
def test_a_call_apart_whose_process_dies_is_computed_here() -> None:
    """Killed (as the OOM killer would) or never started: the caller still gets its result."""
    assert call_apart(dies_in_a_worker, -5) == 5


def test_a_call_apart_that_cannot_fork_is_computed_here(monkeypatch: pytest.MonkeyPatch) -> None:
    """A call that cannot go (a local function), no process can be forked (memory,
    limits), or fork does not exist: done here."""

    def refused(*_: Any, **__: Any) -> None:
        raise OSError(11, "Resource temporarily unavailable")

    assert call_apart(lambda: os.getpid()) == os.getpid()  # a call that does not pickle
    monkeypatch.setattr(workers, "ProcessPoolExecutor", refused)
    assert call_apart(os.getpid) == os.getpid()
    monkeypatch.setattr(workers.multiprocessing, "get_all_start_methods", lambda: ["spawn"])
    assert call_apart(divmod, 7, 2) == (3, 1)
