"""The host end of the link: find or start the device, handshake, run requests.

A DEVICE is a serial port path, ``sim`` or ``replay:CAPTURE_DIR``. For the last two
the host starts ``lamina-device serve`` itself and joins the two programs with a
:class:`PtyBridge`: two real pseudo-terminal pairs and a relay, so both ends use
pyserial on a real tty exactly as they would over a USB cable.
"""

from __future__ import annotations

import os
import select
import subprocess
import sys
import threading
import time
import tty
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import serial

from lamina_shared.link import Channel, LinkClosed
from lamina_shared.protocol import (
    PROTOCOL_VERSION,
    Chunk,
    Kind,
    Message,
    SegmentEvent,
    encode_json,
)
from lamina_shared.types import BoardSpec, ScanPlan, Segment


class DeviceError(RuntimeError):
    """The device is missing, incompatible or refused a request; the text says what to do."""


@dataclass(frozen=True)
class DeviceInfo:
    """What the device reported about itself at the handshake."""

    protocol: int
    software: str
    hardware: str
    description: str
    image_size: tuple[int, int]
    board: BoardSpec | None
    cylinder_diameter_mm: float | None
    default_plans: dict[str, ScanPlan]

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DeviceInfo:
        """Build from the WELCOME body; raise DeviceError if it is malformed."""
        try:
            width, height = (int(v) for v in data["image_size"])
            board = BoardSpec.from_dict(data["board"]) if data.get("board") else None
            plans = {k: ScanPlan.from_dict(v) for k, v in (data.get("default_plans") or {}).items()}
            diameter = data.get("cylinder_diameter_mm")
            return cls(
                int(data["protocol"]),
                str(data.get("software", "?")),
                str(data["hardware"]),
                str(data.get("description", "")),
                (width, height),
                board,
                float(diameter) if diameter is not None else None,
                plans,
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise DeviceError(f"the device's handshake is malformed ({exc})") from None


class PtyBridge:
    """A software null-modem cable: two pseudo-terminal pairs joined by a relay thread.

    ``host_port`` and ``device_port`` are tty paths each end opens with pyserial.
    ``transform`` (for fault-injection tests) may alter bytes in flight.
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


EventHandler = Callable[[Message], None]


class DeviceClient:
    """Requests and replies over a :class:`Channel`, with the device's events passed on."""

    def __init__(
        self,
        channel: Channel,
        process: subprocess.Popen[bytes] | None = None,
        idle_timeout_s: float = 30.0,
    ) -> None:
        self.channel = channel
        self.process = process
        self.idle_timeout_s = idle_timeout_s
        self.info: DeviceInfo | None = None
        self._next_id = 1

    def _device_exit_message(self) -> str | None:
        if self.process is None or self.process.poll() is None:
            return None
        err = self.process.stderr.read().decode(errors="replace") if self.process.stderr else ""
        lines = [line for line in err.strip().splitlines() if line.strip()]
        return lines[-1] if lines else f"the device program exited ({self.process.returncode})"

    def hello(self, timeout_s: float = 20.0) -> DeviceInfo:
        """Handshake; return the device's information or raise :class:`DeviceError`."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            # Repeat HELLO: a device that opened its port late flushed the earlier ones.
            self.channel.send(
                encode_json(Kind.HELLO, {"protocol": PROTOCOL_VERSION, "software": "lamina-host"})
            )
            message = self.channel.receive(timeout_s=0.5)
            if message is not None and message.kind is Kind.WELCOME:
                info = DeviceInfo.from_dict(message.body)
                if info.protocol != PROTOCOL_VERSION:
                    raise DeviceError(
                        f"the device speaks protocol version {info.protocol}, this host speaks "
                        f"{PROTOCOL_VERSION}: install matching lamina-device and lamina-host "
                        "versions"
                    )
                self.info = info
                return info
            if (exit_message := self._device_exit_message()) is not None:
                raise DeviceError(exit_message)
        raise DeviceError(
            "no answer from the device: check the cable and that lamina-device serve is running"
        )

    def request(
        self, op: str, args: dict[str, Any] | None = None, on_event: EventHandler | None = None
    ) -> dict[str, Any]:
        """Send one request; pass its events to ``on_event``; return the reply's result."""
        request_id = self._next_id
        self._next_id += 1
        self.channel.send(
            encode_json(Kind.REQUEST, {"id": request_id, "op": op, "args": args or {}})
        )
        while True:
            message = self.channel.receive(timeout_s=self.idle_timeout_s)
            if message is None:
                exit_message = self._device_exit_message()
                raise DeviceError(
                    exit_message or f"the device stopped answering during {op}: check the cable"
                )
            if message.kind is Kind.REPLY and message.body.get("id") == request_id:
                if message.body.get("ok"):
                    result = message.body.get("result", {})
                    return result if isinstance(result, dict) else {}
                error = message.body.get("error") or {}
                raise DeviceError(f"the device refused {op}: {error.get('message', 'no reason')}")
            if on_event is not None and _request_id(message) == request_id:
                on_event(message)

    def grab_grid(self) -> tuple[np.ndarray, BoardSpec]:
        """Fetch the calibration board image and the board's geometry."""
        received = bytearray()

        def take(message: Message) -> None:
            if isinstance(message.body, Chunk) and message.body.offset == len(received):
                received.extend(message.body.data)

        result = self.request("grab_grid", on_event=take)
        if len(received) != result.get("bytes") or zlib.crc32(received) != result.get("crc32"):
            raise DeviceError("the calibration image arrived incomplete: try again")
        image = cv2.imdecode(np.frombuffer(bytes(received), np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise DeviceError("the calibration image could not be decoded")
        if result.get("board") is None:
            raise DeviceError("the device does not know its calibration board: configure it")
        return image, BoardSpec.from_dict(result["board"])

    def scan(
        self,
        target: str,
        plan: ScanPlan | None = None,
        on_progress: Callable[[dict[str, Any]], None] | None = None,
    ) -> list[Segment]:
        """Scan ``target`` (``cylinder`` or ``object``); return its segments in order."""
        segments: list[Segment] = []

        def take(message: Message) -> None:
            if isinstance(message.body, SegmentEvent):
                segments.append(message.body.segment)
            elif message.kind is Kind.EVENT and on_progress is not None:
                on_progress(message.body)

        args = {"target": target, "plan": plan.to_dict() if plan else None}
        result = self.request("scan", args, on_event=take)
        if result.get("segments") != len(segments):
            raise DeviceError(f"{result.get('segments')} segments sent, {len(segments)} received")
        return segments

    def close(self) -> None:
        """Ask a device this host started to stop, then wait for it."""
        if self.process is not None:
            with suppress(DeviceError, LinkClosed):
                self.channel.send(encode_json(Kind.REQUEST, {"id": 0, "op": "shutdown"}))
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def _request_id(message: Message) -> int | None:
    body = message.body
    if isinstance(body, Chunk | SegmentEvent):
        return body.request_id
    return body.get("id") if isinstance(body, dict) else None


def device_command(
    hardware: str, port: str, object_spec: str | None, seed: int, noise: str
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
    return command


@contextmanager
def open_device(
    device: str,
    object_spec: str | None = None,
    seed: int = 0,
    noise: str = "thesis",
    transform: Callable[[bytes, str], bytes] | None = None,
) -> Iterator[DeviceClient]:
    """Connect to DEVICE (a port path, ``sim`` or ``replay:DIR``) and handshake."""
    if device == "sim" or device.startswith("replay:"):
        with _spawned_device(device, object_spec, seed, noise, transform) as client:
            yield client
        return
    if object_spec:
        raise DeviceError("--object only applies to the simulated device (--device sim)")
    if not os.path.exists(device):
        raise DeviceError(
            f"serial port {device} does not exist: connect the scanner's USB cable or name its "
            "port (e.g. /dev/ttyACM0), or use --device sim"
        )
    try:
        port = serial.Serial(device, baudrate=115200, timeout=0.05, exclusive=True)
    except (serial.SerialException, OSError) as exc:
        raise DeviceError(f"cannot open serial port {device}: {exc}") from None
    with port:
        client = DeviceClient(Channel(port))
        client.hello()
        yield client


@contextmanager
def _spawned_device(
    device: str,
    object_spec: str | None,
    seed: int,
    noise: str,
    transform: Callable[[bytes, str], bytes] | None,
) -> Iterator[DeviceClient]:
    bridge = PtyBridge(transform)
    command = device_command(device, bridge.device_port, object_spec, seed, noise)
    process = subprocess.Popen(
        command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    client: DeviceClient | None = None
    try:
        port = serial.Serial(bridge.host_port, baudrate=115200, timeout=0.05)
        with port:
            client = DeviceClient(Channel(port), process)
            client.hello()
            yield client
            client.close()
    finally:
        if process.poll() is None:
            process.kill()
        process.wait()
        if process.stderr:
            process.stderr.close()
        bridge.close()
