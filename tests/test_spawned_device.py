"""A device program the host started ends when the host is killed (kill -9 included)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.helpers.cli import host_command


def _children(pid: int) -> list[int]:
    """Return the ids of the live processes whose parent is ``pid`` (from /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            found.append(int(entry.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.wall_clock
def test_a_process_told_of_a_parent_that_is_not_its_own_ends_by_sigterm() -> None:
    """The watcher sees that its named parent is not (or no longer) its parent."""
    code = (
        "import time\n"
        "from lamina_shared.spawned import watch_parent\n"
        "assert watch_parent({}) is None\n"
        "watch_parent({'LAMINA_PARENT_PID': '1'})\n"
        "time.sleep(30)\n"
    )
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-c", code], timeout=60)
    assert done.returncode == -signal.SIGTERM
    assert time.monotonic() - started < 20


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_the_spawned_simulator_ends_when_its_host_is_killed(tmp_path: Path) -> None:
    """kill -9 of ``lamina scan`` mid-acquisition leaves no device program behind."""
    host = subprocess.Popen(
        host_command(
            "scan",
            "--device",
            "sim",
            "--object",
            "cylinder:d=19.05",
            "--sections",
            "40",
            "--pitch",
            "1",
            "--views",
            "8",
            "--library",
            str(tmp_path / "library.sqlite"),
            "-o",
            str(tmp_path / "scan"),
        ),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        devices: list[int] = []
        while not devices and time.monotonic() < deadline and host.poll() is None:
            time.sleep(0.2)
            devices = _children(host.pid)
        assert devices, "the host started no device program"
        time.sleep(1.0)  # well inside the acquisition
        os.kill(host.pid, signal.SIGKILL)
        host.wait(timeout=30)
        deadline = time.monotonic() + 30
        while any(_alive(d) for d in devices) and time.monotonic() < deadline:
            time.sleep(0.2)
        left = [d for d in devices if _alive(d)]
        for pid in left:
            os.kill(pid, signal.SIGKILL)
        assert not left, "the device program outlived its killed host"
    finally:
        if host.poll() is None:
            host.kill()
            host.wait()
