"""The device end of the link: answer the host's handshake and requests.

Requests run one at a time; while a scan runs, its segments and progress go out as
events tagged with the request's id, and the reply follows the last of them.
Nothing received is ever evaluated or used as a file path: requests name an
operation from a fixed table and carry plain numbers.
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Callable
from typing import Any

import cv2

from lamina_device import __version__
from lamina_device.acquisition import Progress, acquire, grab_grid
from lamina_device.camera import CameraError
from lamina_device.hardware import Hardware
from lamina_shared.link import Channel, LinkClosed, error_body, ok_body
from lamina_shared.protocol import (
    CHUNK_BYTES,
    PROTOCOL_VERSION,
    Kind,
    Message,
    encode_chunk,
    encode_json,
    encode_segment,
)
from lamina_shared.types import ScanPlan

log = logging.getLogger(__name__)


class RequestError(Exception):
    """A request the device refuses; ``code`` is machine-readable, the text is for people."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class DeviceServer:
    """Serve one host over ``channel`` until it says goodbye or goes away."""

    def __init__(self, channel: Channel, hardware: Hardware) -> None:
        self.channel = channel
        self.hardware = hardware
        self.greeted = False
        self.running = True
        self._ops: dict[str, Callable[[int, dict[str, Any]], dict[str, Any]]] = {
            "grab_grid": self._grab_grid,
            "scan": self._scan,
            "shutdown": self._shutdown,
        }

    def info(self) -> dict[str, Any]:
        """Return what the device tells the host about itself at the handshake."""
        hw = self.hardware
        width, height = hw.camera.size
        return {
            "protocol": PROTOCOL_VERSION,
            "software": f"lamina-device {__version__}",
            "hardware": hw.kind,
            "description": hw.description,
            "image_size": [width, height],
            "board": hw.board.to_dict() if hw.board else None,
            "cylinder_diameter_mm": hw.cylinder_diameter_mm,
            "default_plans": {t: p.to_dict() for t, p in hw.default_plans.items()},
            "operations": sorted(self._ops),
        }

    def serve(self) -> None:
        """Handle messages until shutdown or until the link closes."""
        try:
            while self.running:
                message = self.channel.receive(timeout_s=1.0)
                if message is not None:
                    self.handle(message)
        except LinkClosed as exc:
            log.info("host went away: %s", exc)
        finally:
            self.hardware.laser.off()

    def handle(self, message: Message) -> None:
        """Answer one message from the host."""
        if message.kind is Kind.HELLO:
            self.greeted = message.body.get("protocol") == PROTOCOL_VERSION
            self.channel.send(encode_json(Kind.WELCOME, self.info()))
        elif message.kind is Kind.REQUEST:
            self._request(message.body)
        else:
            log.warning("ignoring unexpected %s message from the host", message.kind.name)

    def _request(self, body: dict[str, Any]) -> None:
        request_id = body.get("id")
        if not isinstance(request_id, int) or isinstance(request_id, bool) or request_id < 0:
            log.warning("ignoring a request without a valid id")
            return
        try:
            if not self.greeted:
                raise RequestError("handshake", "say HELLO with protocol 1 before any request")
            op = self._ops.get(str(body.get("op")))
            if op is None:
                raise RequestError("unknown-op", f"unknown operation {body.get('op')!r}")
            args = body.get("args", {})
            if not isinstance(args, dict):
                raise RequestError("bad-args", "request args must be an object")
            reply = ok_body(request_id, op(request_id, args))
        except RequestError as exc:
            reply = error_body(request_id, exc.code, str(exc))
        except (CameraError, ValueError, OSError) as exc:
            self.hardware.laser.off()
            reply = error_body(request_id, "failed", str(exc))
        self.channel.send(encode_json(Kind.REPLY, reply))

    def _grab_grid(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        image = grab_grid(self.hardware)
        ok, encoded = cv2.imencode(".png", image)
        if not ok:
            raise RequestError("failed", "could not encode the calibration image")
        data = encoded.tobytes()
        for offset in range(0, len(data), CHUNK_BYTES):
            piece = data[offset : offset + CHUNK_BYTES]
            self.channel.send(encode_chunk(request_id, offset, len(data), piece))
        board = self.hardware.board
        return {
            "bytes": len(data),
            "crc32": zlib.crc32(data),
            "board": board.to_dict() if board else None,
        }

    def _plan(self, target: str, args: dict[str, Any]) -> ScanPlan:
        if args.get("plan") is not None:
            try:
                return ScanPlan.from_dict(args["plan"])
            except (KeyError, TypeError, ValueError) as exc:
                raise RequestError("bad-args", f"invalid scan plan: {exc}") from None
        plan = self.hardware.default_plans.get(target)
        if plan is None:
            raise RequestError("bad-args", f"no {target} views to scan on this device")
        return plan

    def _scan(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        target = args.get("target")
        if target not in ("cylinder", "object"):
            raise RequestError(
                "bad-args", f"scan target must be cylinder or object, not {target!r}"
            )
        plan = self._plan(target, args)

        def send_progress(progress: Progress) -> None:
            self.channel.send(
                encode_json(
                    Kind.EVENT,
                    {
                        "id": request_id,
                        "event": "progress",
                        "target": progress.target,
                        "done": progress.done,
                        "total": progress.total,
                        "section": progress.section,
                    },
                )
            )

        count = acquire(
            self.hardware,
            target,
            plan,
            lambda segment: self.channel.send(encode_segment(request_id, segment)),
            send_progress,
        )
        return {"segments": count, "plan": plan.to_dict()}

    def _shutdown(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        self.running = False
        return {}
