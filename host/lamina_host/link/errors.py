"""What goes wrong on the link, as the host reports it: one line that says what to do."""

from __future__ import annotations

from lamina_shared.errors import LaminaError
from lamina_shared.types import Segment


class DeviceError(LaminaError, RuntimeError):
    """The device is missing, incompatible or refused a request; the text says what to do."""


class RequestRefused(DeviceError):
    """The device answered a request with an error; ``code`` is its machine-readable reason."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class ScanStopped(DeviceError):
    """The scan was aborted on the device; ``segments`` maps plan index to what arrived.

    Every segment in it was handed to ``on_segment`` (stored) and acknowledged; the
    scan resumes with ``have`` = what the caller holds.
    """

    def __init__(self, message: str, segments: dict[int, Segment]) -> None:
        super().__init__(message)
        self.segments = segments
