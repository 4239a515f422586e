"""Fixtures shared by every test folder: a refused command's one line, the box's device
service on a local endpoint."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def device_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """Run ``lamina-device serve --listen`` on the simulated rig (any free port): its URL.

    The program outlives each host that connects, as the box's service does.
    """
    from lamina_host.link.spawn import SINGLE_THREADED

    log = tmp_path_factory.mktemp("device-service") / "stderr.log"
    command = [sys.executable, "-m", "lamina_device", "serve", "--hardware", "sim"]
    with open(log, "w") as err:
        process = subprocess.Popen(
            [*command, "--listen", "socket://127.0.0.1:0"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=err,
            env={**os.environ, **SINGLE_THREADED},
        )
    try:
        yield _served_url(process, log)
    finally:
        process.terminate()
        process.wait(timeout=20)


def _served_url(process: subprocess.Popen[bytes], log: Path) -> str:
    """Return the URL the device program prints once it listens."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        for line in log.read_text().splitlines():
            if "serving on " in line:
                return line.rpartition("serving on ")[2].strip()
        if process.poll() is not None:
            break
        time.sleep(0.05)
    raise AssertionError(f"the device service did not start: {log.read_text()}")


def one_line_refusal(done: subprocess.CompletedProcess[str]) -> str:
    """Return the one line a refused command wrote on stderr; fail unless status is non-zero."""
    lines = done.stderr.strip().splitlines()
    assert done.returncode != 0, done.stdout
    assert len(lines) == 1, done.stderr
    return lines[0]


@pytest.fixture
def refusal() -> Callable[[subprocess.CompletedProcess[str]], str]:
    """Return the checker of a refusal: non-zero status and one line, which it returns."""
    return one_line_refusal
