"""Which transport a DEVICE names: pyserial's URLs, serial ports and the box's endpoint."""

from __future__ import annotations

import socket

import pytest
import serial

from lamina_host.link.errors import DeviceError
from lamina_host.link.local_box import SocketPort
from lamina_host.link.spawn import PtyBridge
from lamina_host.link.transport import open_port


def test_a_pyserial_url_chooses_its_transport():
    with open_port("loop://") as port:
        port.write(b"\x00frame\x00")
        assert port.read(7) == b"\x00frame\x00"
        assert port.timeout == 0.05


def test_spy_logs_every_byte_of_a_serial_port(tmp_path):
    bridge = PtyBridge()
    log = tmp_path / "wire.txt"
    try:
        with (
            open_port(f"spy://{bridge.host_port}?file={log}") as host,
            serial.Serial(bridge.device_port, timeout=1) as device,
        ):
            host.write(b"\x00hello\x00")
            assert device.read(7) == b"\x00hello\x00"
            device.write(b"\x00welcome\x00")
            assert host.read(9) == b"\x00welcome\x00"
    finally:
        bridge.close()
    text = log.read_text()
    assert "TX" in text and "RX" in text and "hello" in text and "welcome" in text


def test_a_serial_port_path_is_opened_exclusively():
    bridge = PtyBridge()
    try:
        with open_port(bridge.host_port) as port:
            assert isinstance(port, serial.Serial) and port.exclusive
            with pytest.raises(DeviceError, match=f"cannot open serial port {bridge.host_port}"):
                open_port(bridge.host_port)
    finally:
        bridge.close()


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def test_unusable_device_names_are_refused_in_one_line():
    unused_tcp_port = _free_port()
    with pytest.raises(DeviceError, match="does not exist: connect the scanner's USB cable"):
        open_port("/dev/no-such-port")
    with pytest.raises(DeviceError) as info:
        open_port("bogus://x")
    assert "name a serial port" in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(DeviceError, match="no device service answers"):
        open_port(f"socket://127.0.0.1:{unused_tcp_port}")
    with pytest.raises(DeviceError, match="no device service answers"):
        open_port(f"local:{unused_tcp_port}")


def test_the_box_endpoint_keeps_its_own_socket_port():
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        url = f"socket://127.0.0.1:{server.getsockname()[1]}"
        with open_port(url) as port:
            assert isinstance(port, SocketPort)
