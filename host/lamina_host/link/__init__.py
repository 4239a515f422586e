"""The link to the device, the host's end of ``shared/PROTOCOL.md``.

A DEVICE is a serial port path (``/dev/ttyACM0``), ``local`` or ``socket://HOST:PORT``
(the box's device service), another pyserial URL (``spy://PORT?file=LOG`` logs the
wire, ``loop://``), or ``sim`` / ``replay:CAPTURE_DIR`` (a device program the host
starts itself). :func:`lamina_host.link.connect.open_device` opens any of them and
handshakes; :class:`lamina_host.link.client.DeviceClient` then runs requests.
"""
