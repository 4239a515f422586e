"""Which transport a DEVICE names, opened as a pyserial port.

pyserial's :func:`serial.serial_for_url` chooses the transport from the name: a serial
port path (``/dev/ttyACM0``), or one of its URLs, ``loop://`` (a loopback, for tests),
``spy://PORT?file=LOG`` (the port with every byte logged), ``rfc2217://HOST:PORT`` and
the others it knows. ``socket://HOST:PORT`` and the box's ``local`` (``local:PORT``) open
:class:`lamina_host.link.local_box.SocketPort` instead: pyserial's own socket handler,
made to report every byte waiting and to send small frames at once. The devices the host
starts itself (``sim``, ``replay:DIR``) are :mod:`lamina_host.link.connect`'s.
"""

from __future__ import annotations

import os

import serial

from lamina_host.link.errors import DeviceError
from lamina_host.link.local_box import is_endpoint, open_endpoint

BAUD_RATE = 115_200
"""The GPIO UART's rate (USB gadget serial ignores it)."""
READ_TIMEOUT_S = 0.05
"""How long one read waits: the link's reader polls its stop flag this often."""
DEVICE_FORMS = "a serial port (e.g. /dev/ttyACM0), local, socket://HOST:PORT, sim or replay:DIR"
"""What a DEVICE may be, for the line that refuses another."""


def open_port(device: str) -> serial.SerialBase:
    """Open the port DEVICE names (not ``sim`` or ``replay:``); raise DeviceError in one line.

    A serial port is opened exclusively: a second program on the same cable would take
    half of every frame.
    """
    if is_endpoint(device):
        return open_endpoint(device, DeviceError)
    is_url = "://" in device
    if not is_url and not os.path.exists(device):
        raise DeviceError(
            f"serial port {device} does not exist: connect the scanner's USB cable or name its "
            "port (e.g. /dev/ttyACM0), or use --device sim"
        )
    options = {} if is_url else {"exclusive": True}
    try:
        return serial.serial_for_url(device, baudrate=BAUD_RATE, timeout=READ_TIMEOUT_S, **options)
    except ValueError as exc:  # a URL pyserial does not know
        raise DeviceError(f"cannot open {device} ({exc}): name {DEVICE_FORMS}") from None
    except (serial.SerialException, OSError) as exc:
        what = device if is_url else f"serial port {device}"
        raise DeviceError(f"cannot open {what}: {exc}") from None
