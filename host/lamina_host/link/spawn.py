"""Device programs the host starts itself (``sim``, ``replay:DIR``) and the cable to them.

The host runs ``lamina-device serve`` as a child process and joins the two programs
with a :class:`PtyBridge`: two real pseudo-terminal pairs and a relay, so both ends use
pyserial on a real tty exactly as they would over a USB cable. :class:`StderrTail`
keeps the program's last words for the one line the host prints when it exits.
"""

from __future__ import annotations

import os
import select
import subprocess
import sys
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from contextlib import suppress
from dataclasses import dataclass
from typing import IO

from lamina_shared.spawned import PARENT_PID_ENV


class PtyBridge:
    """A software null-modem cable: two pseudo-terminal pairs joined by a relay thread.

    ``host_port`` and ``device_port`` are tty paths each end opens with pyserial.
    ``transform`` (for fault-injection tests, e.g. ``lamina_host.testing.LineFaults``)
    may alter bytes in flight.
    """

    def __init__(self, transform: Callable[[bytes, str], bytes] | None = None) -> None:
        self._a_master, self._a_slave = os.openpty()
        self._b_master, self._b_slave = os.openpty()
        for fd in (self._a_master, self._a_slave, self._b_master, self._b_slave):
            # Raw from the start: a cooked slave would echo and mangle binary frames
            # before pyserial has configured it.
            tty.setraw(fd)
        self.host_port = os.ttyname(self._a_slave)
        self.device_port = os.ttyname(self._b_slave)
        self._transform = transform
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._relay, name="pty-bridge", daemon=True)
        self._thread.start()

    def _relay(self) -> None:
        route = {
            self._a_master: (self._b_master, "to-device"),
            self._b_master: (self._a_master, "to-host"),
        }
        while not self._stop.is_set():
            ready, _, _ = select.select(list(route), [], [], 0.05)
            for fd in ready:
                try:
                    data = os.read(fd, 65536)
                except OSError:
                    time.sleep(0.01)  # the other end closed (EIO): do not spin
                    continue
                out, direction = route[fd]
                if self._transform is not None:
                    data = self._transform(data, direction)
                with suppress(OSError):
                    os.write(out, data)

    def close(self) -> None:
        """Stop relaying and close all four descriptors."""
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self._a_master, self._a_slave, self._b_master, self._b_slave):
            with suppress(OSError):
                os.close(fd)


@dataclass
class StderrTail:
    """Read a device program's stderr while it runs, keeping its last lines.

    A pipe holds about 64 KB: a program that writes more to a pipe nobody reads blocks,
    and the host would wait for an answer that cannot come.
    """

    KEEP_LINES = 50
    LINE_BYTES = 64 * 1024

    def __init__(self, stream: IO[bytes]) -> None:
        self._lines: deque[str] = deque(maxlen=self.KEEP_LINES)
        self._thread = threading.Thread(
            target=self._read, args=(stream,), name="device-stderr", daemon=True
        )
        self._thread.start()

    def _read(self, stream: IO[bytes]) -> None:
        with suppress(OSError, ValueError):  # the stream closed under us: nothing more to read
            # Empty at the end of the stream, whether it yields bytes or (a caller's) text.
            while raw := stream.readline(self.LINE_BYTES):
                line = raw.decode(errors="replace") if isinstance(raw, bytes) else raw
                self._lines.append(line.strip())

    def lines(self, wait_s: float = 2.0) -> list[str]:
        """Return the last non-empty lines, after up to ``wait_s`` for an exited program's rest.

        Args:
            wait_s: how long to wait for the stream's end (call it once the program exited).

        Returns:
            The kept lines, oldest first.
        """
        self._thread.join(wait_s)
        return [line for line in self._lines if line]


SINGLE_THREADED = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENCV_FOR_THREADS_NUM": "1",
}
"""Thread limits for a device program started on the host's own machine."""


def device_environment() -> dict[str, str]:
    """Return the environment for a simulated or replaying device started here.

    The real device is a computer of its own. One started beside the host stands in
    for it, so its numerical libraries get one thread each: left to themselves they
    take every core while rendering, and the host (its terminal UI above all) then
    answers keys late. It is told this process's id, so that it ends when the host does
    (:mod:`lamina_shared.spawned`).
    """
    return {**os.environ, **SINGLE_THREADED, PARENT_PID_ENV: str(os.getpid())}


def device_command(
    hardware: str,
    port: str,
    object_spec: str | None,
    seed: int,
    noise: str,
    rig: str = "thesis",
    sway: str = "none",
) -> list[str]:
    """Return the command line that starts a device program on ``port``."""
    command = [
        sys.executable,
        "-m",
        "lamina_device",
        "serve",
        "--port",
        port,
        "--hardware",
        hardware,
        "--seed",
        str(seed),
        "--noise",
        noise,
    ]
    if object_spec:
        command += ["--object", object_spec]
    if rig != "thesis":
        command += ["--rig", rig]
    if sway != "none":
        command += ["--sway", sway]
    return command


def start_device_program(command: list[str]) -> subprocess.Popen[bytes]:
    """Start a device program with :func:`device_environment`, its stderr piped for a
    :class:`StderrTail` and nothing on its stdin or stdout."""
    return subprocess.Popen(
        command,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=device_environment(),
    )
