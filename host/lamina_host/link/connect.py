"""Connect to a DEVICE and handshake: a port or URL, or a device program started here.

``sim`` and ``replay:CAPTURE_DIR`` start ``lamina-device serve`` beside the host
(:mod:`lamina_host.link.spawn`); anything else is a transport
(:mod:`lamina_host.link.transport`): a serial port path, ``local``, ``socket://HOST:PORT``
or another pyserial URL (``spy://PORT?file=LOG`` logs the wire).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

import serial

from lamina_host.link.client import DeviceClient
from lamina_host.link.errors import DeviceError
from lamina_host.link.identity import spawned_source
from lamina_host.link.spawn import PtyBridge, device_command, start_device_program
from lamina_host.link.transport import BAUD_RATE, READ_TIMEOUT_S, open_port
from lamina_shared.device_specs import spawns_device
from lamina_shared.link import Channel

Transform = Callable[[bytes, str], bytes]
"""Alters bytes in flight between the host and a device started here (fault injection)."""


@contextmanager
def open_device(
    device: str,
    object_spec: str | None = None,
    seed: int = 0,
    noise: str = "thesis",
    transform: Transform | None = None,
    rig: str = "thesis",
    on_notice: Callable[[str], object] | None = None,
    sway: str = "none",
) -> Iterator[DeviceClient]:
    """Connect to DEVICE (a port path, ``local``, ``socket://HOST:PORT``, another pyserial
    URL, ``sim`` or ``replay:DIR``) and handshake.

    ``rig`` picks the simulated rig's geometry (``thesis`` or ``limb``; sim only).
    ``on_notice`` hears about a slow start of a device program started here.
    ``sway`` moves the simulated object as a patient would (sim only).
    """
    if spawns_device(device):
        with _spawned_device(
            device, object_spec, seed, noise, transform, rig, on_notice, sway
        ) as client:
            yield client
        return
    if object_spec:
        raise DeviceError("--object only applies to the simulated device (--device sim)")
    with open_port(device) as port:
        client = DeviceClient(Channel(port))
        try:
            client.hello()
            yield client
        finally:
            client.close()  # the reader stops before its port closes under it


@contextmanager
def _spawned_device(
    device: str,
    object_spec: str | None,
    seed: int,
    noise: str,
    transform: Transform | None,
    rig: str = "thesis",
    on_notice: Callable[[str], object] | None = None,
    sway: str = "none",
) -> Iterator[DeviceClient]:
    try:
        bridge = PtyBridge(transform)
    except OSError as exc:
        raise DeviceError(
            f"cannot open a pseudo-terminal to run the device program here "
            f"({exc.strerror or exc}): mount /dev/pts, or connect a scanner by its serial port"
        ) from None
    process = start_device_program(
        device_command(device, bridge.device_port, object_spec, seed, noise, rig, sway)
    )
    client: DeviceClient | None = None
    try:
        port = serial.Serial(bridge.host_port, baudrate=BAUD_RATE, timeout=READ_TIMEOUT_S)
        with port:
            client = DeviceClient(Channel(port), process)
            client.spawned = spawned_source(device, object_spec, seed, noise, rig)
            client.hello(on_notice=on_notice)
            yield client
            client.close()
    finally:
        if process.poll() is None:
            process.kill()
        process.wait()
        if client is not None and client.stderr_tail is not None:
            client.stderr_tail.lines()  # the reader is done before its stream closes
        if process.stderr:
            process.stderr.close()
        bridge.close()
