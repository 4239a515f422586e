"""A device program that a host started beside itself ends when that host ends.

The host starts the simulated or replaying device as its child over a pseudo-terminal.
If the host dies without a word (kill -9, an out-of-memory kill), nothing else would ever
stop the child: it would go on holding its pseudo-terminal and CPU. The host names its own
process id in the child's environment; the child watches its parent and, once the parent
is gone, ends through its own SIGTERM path, which switches the laser off first.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Mapping

PARENT_PID_ENV = "LAMINA_PARENT_PID"
"""Environment variable holding the process id of the host that started the device."""

POLL_S = 0.5
"""How often the child looks for its parent."""


def watch_parent(environ: Mapping[str, str] = os.environ) -> threading.Thread | None:
    """End this process (SIGTERM to itself) once the host that started it has gone.

    Args:
        environ: the environment that may name the parent host (``PARENT_PID_ENV``).

    Returns:
        The watching daemon thread, or None when no parent host is named (a device
        service started on its own, by systemd or by hand, outlives any host).
    """
    text = environ.get(PARENT_PID_ENV, "")
    if not text.isdigit():
        return None
    parent = int(text)
    stop = threading.Event()

    def watch() -> None:
        # A dead parent's child is re-parented (to init or a subreaper): getppid changes.
        while not stop.wait(POLL_S):
            if os.getppid() != parent:
                os.kill(os.getpid(), signal.SIGTERM)
                return

    thread = threading.Thread(target=watch, name="lamina-parent-watch", daemon=True)
    thread.start()
    return thread
