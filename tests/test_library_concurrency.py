"""One scan library, many processes: nothing acknowledged is ever lost (issue 19).

Hypothesis picks a schedule: which programs run at once on one library (``lamina scan
--device sim`` with small plans, a scan in the terminal UI with its Library screen
reloading in the same process, and the readers ``lamina scans``, ``export``, ``report``,
``batch`` and the terminal UI's Library screen), when each starts and when, if ever, it is
killed with SIGKILL (with any simulated device it started). Each is a real process.
Afterwards the library passes ``PRAGMA integrity_check``; every process not killed ended
with status 0; every scan that ended holds exactly the segments its program wrote to
``segments.npz`` and ``cylinder-segments.npz`` (all it received, stored and
acknowledged); every segment a
watcher in this process ever saw committed is still there (the lower bound for a scan
killed before it could write its npz files); the processed scan the library began with
is untouched.

``make test`` runs a few schedules; ``make fuzz`` runs ``LAMINA_LIBRARY_RUNS`` of them
(see the Makefile) and appends one JSON line a run to ``LAMINA_LIBRARY_LOG`` if set.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lamina_host.store.library import Library
from lamina_host.store.outputs import load_segments
from lamina_shared.types import Segment
from tests.helpers.cli import host_command

RUNS = int(os.environ.get("LAMINA_LIBRARY_RUNS", "2"))
MAX_PROCESSES = int(os.environ.get("LAMINA_LIBRARY_PROCESSES", "4"))
LOG = os.environ.get("LAMINA_LIBRARY_LOG")
TUI_PROCESS = Path(__file__).parent / "helpers" / "tui_process.py"
SEED_SUBJECT = "SEED-1"
PLAN = ("--sections", "2", "--pitch", "2", "--views", "8")
READS = 6
"""How many times a reader runs again while a scan goes on."""
WAIT_S = 300.0
"""Longest any one program may take (a loaded shared machine); longer is a hang."""

SCANNERS = ("scan", "tui-scan")
READERS = ("scans", "export", "report", "batch", "tui-library")


@dataclass(frozen=True)
class Role:
    """One program of a schedule: what it is, when it starts, when (if ever) it is killed."""

    kind: str
    start_s: float
    kill_after_s: float | None


@dataclass
class Ran:
    """A program that ran: its role, its folder, its process and how it ended."""

    role: Role
    index: int
    attempt: int
    folder: Path
    process: subprocess.Popen[bytes]
    killed: bool = False
    status: int | None = None

    def text(self) -> str:
        """Return what it printed (stdout then stderr)."""
        return "".join(
            (self.folder / name).read_text(errors="replace") for name in ("stdout", "stderr")
        )


@dataclass
class Watcher:
    """Reads the library from this process while the programs run; keeps every segment seen."""

    path: Path
    seen: set[tuple[int, str, int]] = field(default_factory=set)
    stop: threading.Event = field(default_factory=threading.Event)
    errors: list[str] = field(default_factory=list)

    def run(self) -> None:
        """Poll until stopped, connecting afresh each time.

        A connection kept open would hold its lock on the file all along, and so hide the
        failure it watches for: another process's last close deleting the WAL.
        """
        while not self.stop.wait(0.1):
            db = sqlite3.connect(self.path, timeout=30)
            try:
                rows = db.execute("SELECT scan_id, target, seq FROM segments").fetchall()
            except sqlite3.Error as exc:
                self.errors.append(str(exc))
                continue
            finally:
                db.close()
            self.seen.update((int(a), str(b), int(c)) for a, b, c in rows)


def _command(role: Role, index: int, library: Path, folder: Path) -> list[str]:
    """Return the argv of one program of the schedule."""
    own = ("--library", str(library))
    if role.kind == "scan":
        subject = f"RUN-{index}"
        return host_command(
            "scan", "--device", "sim", *PLAN, "--seed", str(index), "--subject", subject,
            *own, "-o", str(folder / "out"),
        )  # fmt: skip
    if role.kind == "tui-scan":
        return [sys.executable, str(TUI_PROCESS), str(library), "scan", f"TUI-{index}",
                str(folder / "out")]  # fmt: skip
    if role.kind == "tui-library":
        return [sys.executable, str(TUI_PROCESS), str(library), "library"]
    if role.kind == "scans":
        return host_command("scans", *own)
    if role.kind == "export":
        return host_command("export", "1", "-o", str(folder / "mesh.ply"), *own)
    if role.kind == "report":
        return host_command("report", "1", "-o", str(folder / "report.csv"), *own)
    assert role.kind == "batch"
    return host_command(
        "batch", "--measure", "--subjects", "SEED*", "--workers", "1",
        "-o", str(folder / "batch.csv"), *own,
    )  # fmt: skip


@pytest.fixture(scope="module")
def seeded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, dict[int, Segment]]]:
    """Return a library holding one processed simulated scan (scan 1) and its segments."""
    folder = tmp_path_factory.mktemp("seed")
    library = folder / "library.sqlite"
    done = subprocess.run(
        host_command(
            "scan",
            "--device",
            "sim",
            *PLAN,
            "--subject",
            SEED_SUBJECT,
            "--library",
            str(library),
            "-o",
            str(folder / "out"),
        ),
        capture_output=True,
        text=True,
        timeout=WAIT_S,
    )
    assert done.returncode == 0, done.stderr
    with Library(library) as opened:
        held = {t: _held(opened, 1, t) for t in ("cylinder", "object")}
    return library, held


def roles() -> st.SearchStrategy[list[Role]]:
    """Schedules: one to three scanners and up to three readers, some killed."""
    kill = st.one_of(st.none(), st.floats(0.2, 15.0))

    def role(kinds: tuple[str, ...]) -> st.SearchStrategy[Role]:
        return st.builds(Role, st.sampled_from(kinds), st.floats(0.0, 6.0), kill)

    scanners = st.lists(role(SCANNERS), min_size=1, max_size=min(3, MAX_PROCESSES - 1))
    readers = st.lists(role(READERS), min_size=1, max_size=3)
    return st.tuples(scanners, readers).map(lambda pair: (pair[0] + pair[1])[:MAX_PROCESSES])


def _run_schedule(schedule: list[Role], library: Path, base: Path) -> list[Ran]:
    """Start, kill and wait for every program of ``schedule``; return how each ended.

    A reader that ends while a scanner still runs is started again (a user refreshing a
    listing), up to :data:`READS` times; a killed program is not.
    """
    ran: list[Ran] = []
    current: dict[int, Ran] = {}
    stopped: set[int] = set()
    start = time.monotonic()
    try:
        while len(stopped) < len(schedule):
            now_s = time.monotonic() - start
            if now_s > WAIT_S:
                raise AssertionError(f"the schedule did not end in {WAIT_S} s: {schedule}")
            scanning = any(
                r.process.poll() is None for k, r in current.items() if r.role.kind in SCANNERS
            ) or any(role.kind in SCANNERS and k not in current for k, role in enumerate(schedule))
            for index, role in enumerate(schedule):
                if index in stopped or now_s < role.start_s:
                    continue
                one = current.get(index)
                if one is None:
                    current[index] = _start(role, index, 0, library, base)
                    ran.append(current[index])
                    continue
                if one.process.poll() is None:
                    if role.kill_after_s is not None and now_s >= role.start_s + role.kill_after_s:
                        # The program and the simulated device it started: a device program
                        # outliving its host holds its pty, which a later scan may be given
                        # again (its exclusive lock then fails; not the library's concern).
                        os.killpg(one.process.pid, signal.SIGKILL)
                        one.killed = True
                        one.status = one.process.wait()
                        stopped.add(index)
                    continue
                one.status = one.process.returncode
                again = role.kind in READERS and scanning and one.attempt + 1 < READS
                if again and one.status == 0:
                    current[index] = _start(role, index, one.attempt + 1, library, base)
                    ran.append(current[index])
                else:
                    stopped.add(index)
            time.sleep(0.02)
    finally:
        for one in ran:
            # SIGKILL stopped the program only; now its group (a simulated device it started).
            with suppress(ProcessLookupError, PermissionError):
                os.killpg(one.process.pid, signal.SIGKILL)
            one.process.wait()
    return ran


def _start(role: Role, index: int, attempt: int, library: Path, base: Path) -> Ran:
    """Start one program in a folder of its own (its output goes to files there)."""
    folder = base / f"p{index}-{role.kind}-{attempt}"
    folder.mkdir()
    with (folder / "stdout").open("wb") as out, (folder / "stderr").open("wb") as err:
        process = subprocess.Popen(
            _command(role, index, library, folder),
            stdout=out,
            stderr=err,
            stdin=subprocess.DEVNULL,
            start_new_session=True,  # its own group: what it starts is ended with it
        )
    return Ran(role, index, attempt, folder, process)


def _held(library: Library, scan_id: int, target: str) -> dict[int, Segment]:
    """Return a scan's stored segments by plan index (read when nothing else writes)."""
    held = sorted(library.held(scan_id, target))
    return dict(zip(held, library.segments(scan_id, target), strict=True))


def _wrote_npz(one: Ran) -> bool:
    """Return True for a scanner that ended by itself and wrote what it acknowledged."""
    out = one.folder / "out"
    return one.role.kind in SCANNERS and not one.killed and (out / "segments.npz").exists()


def _scan_id(one: Ran) -> int:
    """Return the library scan a scanner that ended normally says it wrote."""
    found = re.search(r"^scan (\d+)", one.text(), re.M)
    assert found, f"{one.role}: no scan id in its output:\n{one.text()}"
    return int(found.group(1))


def _lost(one: Ran, library: Library) -> int:
    """Return how many segments a scanner wrote to its npz files are missing from the library.

    Also asserts the library holds no segment of that scan the program did not receive.
    """
    scan_id, lost = _scan_id(one), 0
    for target, name in (("object", "segments.npz"), ("cylinder", "cylinder-segments.npz")):
        acknowledged = load_segments(one.folder / "out" / name)
        held = _held(library, scan_id, target)
        stored = {(s.section, s.view): s for s in held.values()}
        missing = sum(
            (s.section, s.view) not in stored or not stored[(s.section, s.view)].same_as(s)
            for s in acknowledged
        )
        extra = len(held) - (len(acknowledged) - missing)
        assert extra == 0, f"{one.role}: {extra} {target} segments it never received"
        lost += missing
    return lost


def _check(
    schedule: list[Role],
    ran: list[Ran],
    path: Path,
    watcher: Watcher,
    seed: dict[str, dict[int, Segment]],
) -> None:
    """Assert the library is whole and holds everything acknowledged; return the figures."""
    with sqlite3.connect(path) as db:
        integrity = [row[0] for row in db.execute("PRAGMA integrity_check")]
    failed = [one for one in ran if not one.killed and one.status != 0]
    with Library(path) as library:
        # A scanner that ended by itself, failed or not, wrote all it acknowledged.
        lost = sum(_lost(one, library) for one in ran if _wrote_npz(one))
        present = {
            (row_scan, target, seq)
            for row_scan in {s for s, _, _ in watcher.seen}
            for target in ("cylinder", "object")
            for seq in library.held(row_scan, target)
        }
        unseen = watcher.seen - present
        seed_now = {t: _held(library, 1, t) for t in seed}
    seed_whole = all(
        seed_now[t].keys() == seed[t].keys()
        and all(seed_now[t][k].same_as(s) for k, s in v.items())
        for t, v in seed.items()
    )
    figures = {
        "processes": len(ran),
        "killed": sum(one.killed for one in ran),
        "failed": len(failed),
        "lost_acknowledged": lost + len(unseen),
        "segments_seen": len(watcher.seen),
        "integrity": integrity[0] if integrity == ["ok"] else "; ".join(integrity[:3]),
        "seed_whole": seed_whole,
        "schedule": [
            [r.kind, round(r.start_s, 2), r.kill_after_s and round(r.kill_after_s, 2)]
            for r in schedule
        ],
        "ran": [[one.role.kind, one.attempt, one.status, one.killed] for one in ran],
    }
    if LOG:
        with open(LOG, "a") as log:
            log.write(json.dumps(figures) + "\n")
    assert integrity == ["ok"], integrity
    assert not failed, "\n".join(f"{one.role} ended {one.status}:\n{one.text()}" for one in failed)
    assert not watcher.errors, watcher.errors
    assert lost == 0 and not unseen, (lost, sorted(unseen))
    assert seed_whole


@settings(
    max_examples=RUNS,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(schedule=roles())
def test_many_processes_on_one_library_lose_nothing_acknowledged(seeded, tmp_path, schedule):
    seed_library, seed = seeded
    base = tmp_path / f"run-{time.monotonic_ns()}"
    base.mkdir()
    library = base / "library.sqlite"
    shutil.copyfile(seed_library, library)
    library.chmod(0o600)
    watcher = Watcher(library)
    thread = threading.Thread(target=watcher.run, daemon=True)
    thread.start()
    try:
        ran = _run_schedule(schedule, library, base)
    finally:
        watcher.stop.set()
        thread.join()
    _check(schedule, ran, library, watcher, seed)
    shutil.rmtree(base, ignore_errors=True)
