"""A simulated device served in this process over a real pty link, for the link tests.

The server runs on its own thread, driving the simulated rig, so tests can compare what
crossed the link with what the rig produces directly (:func:`reference`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import serial

from lamina_device.acquisition import acquire
from lamina_device.extract import ExtractSettings
from lamina_device.hardware import Hardware
from lamina_device.server import DeviceServer, ServerSettings
from lamina_device.sim import open_sim
from lamina_host.link.client import DeviceClient
from lamina_host.link.spawn import PtyBridge
from lamina_shared.link import Channel
from lamina_shared.messages import Welcome
from lamina_shared.protocol import quantise_segment
from lamina_shared.types import ScanPlan, Segment

OBJECT = "cylinder:d=19.05"
"""The object every served rig holds (a 3/4 inch rod), seed 3."""

Transform = Callable[[bytes, str], bytes]


class SilentStream:
    """A byte stream that never delivers anything and swallows what is written."""

    timeout: float | None = 0.0
    in_waiting = 0

    def read(self, size: int = 1) -> bytes:
        """Return nothing: no peer ever speaks."""
        return b""

    def write(self, data: bytes) -> int:
        """Accept ``data`` and drop it."""
        return len(data)


@dataclass
class Served:
    """The device end of a served rig and the host's still unopened-to-protocol port."""

    server: DeviceServer
    hardware: Hardware
    thread: threading.Thread
    host_port: serial.Serial


@dataclass
class Link:
    """A served rig and a handshaken host client."""

    client: DeviceClient
    server: DeviceServer
    hardware: Hardware
    faults: Transform | None
    info: Welcome


@contextmanager
def serve(
    transform: Transform | None = None,
    settings: ServerSettings | None = None,
    server_class: type[DeviceServer] = DeviceServer,
    write_timeout_s: float = 10.0,
    object_spec: str = OBJECT,
    noise: str = "thesis",
) -> Iterator[Served]:
    """Serve the sim rig over a pty bridge (``transform`` alters bytes in flight)."""
    bridge = PtyBridge(transform)
    hardware = open_sim(object_spec, seed=3, noise=noise)
    device_port = serial.Serial(bridge.device_port, timeout=0.02)
    server = server_class(Channel(device_port, write_timeout_s=write_timeout_s), hardware, settings)
    thread = threading.Thread(target=server.serve, daemon=True)
    thread.start()
    host_port = serial.Serial(bridge.host_port, timeout=0.02)
    try:
        yield Served(server, hardware, thread, host_port)
    finally:
        server.running = False
        thread.join(timeout=15)
        host_port.close()
        device_port.close()
        hardware.close()
        bridge.close()


@contextmanager
def link(
    faults: Transform | None = None,
    settings: ServerSettings | None = None,
    server_class: type[DeviceServer] = DeviceServer,
    object_spec: str = OBJECT,
    noise: str = "thesis",
) -> Iterator[Link]:
    """A served sim rig and a host client that has completed the handshake."""
    with serve(faults, settings, server_class, object_spec=object_spec, noise=noise) as ends:
        client = DeviceClient(Channel(ends.host_port), idle_timeout_s=20)
        info = client.hello()
        yield Link(client, ends.server, ends.hardware, faults, info)


def reference(
    plan: ScanPlan, target: str = "object", settings: ExtractSettings | None = None
) -> list[Segment]:
    """What the same rig gives for ``plan`` without any link, quantised as it travels."""
    hardware = open_sim(OBJECT, seed=3)
    segments: list[Segment] = []
    try:
        acquire(hardware, target, plan, segments.append, settings=settings)
    finally:
        hardware.close()
    return [quantise_segment(s) for s in segments]
