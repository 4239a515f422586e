"""Command lines of the two programs, run as this interpreter's modules (no install needed)."""

from __future__ import annotations

import sys


def device_command(*args: str) -> list[str]:
    """Return the argv of ``lamina-device *args``."""
    return [sys.executable, "-m", "lamina_device", *args]


def host_command(*args: str) -> list[str]:
    """Return the argv of ``lamina *args``."""
    return [sys.executable, "-m", "lamina_host", *args]
