"""The names of the device programs a host may start beside itself: ``sim`` and ``replay:DIR``.

The host's ``--device sim`` or ``--device replay:DIR`` starts the device program with the
same string as its ``--hardware``; both ends read the string with the functions here, so
what the host spawns and what the device then opens cannot drift apart.
"""

from __future__ import annotations

__all__ = ["REPLAY_PREFIX", "SIM", "replay_folder", "spawns_device"]

SIM = "sim"
"""The simulated rig."""

REPLAY_PREFIX = "replay:"
"""Followed by a capture folder: the recorded capture stands in for the camera."""


def replay_folder(spec: str) -> str | None:
    """Return the capture folder a ``replay:DIR`` spec names ("" if none), else None."""
    return spec.removeprefix(REPLAY_PREFIX) if spec.startswith(REPLAY_PREFIX) else None


def spawns_device(spec: str) -> bool:
    """Return True if ``spec`` names a device program the host starts itself (sim, replay)."""
    return spec == SIM or replay_folder(spec) is not None
