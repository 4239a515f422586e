"""Store a scan's DICOM object in a PACS by DICOM C-STORE (``lamina send``).

The object is the one ``lamina export -o FILE.dcm`` writes (:mod:`lamina_host.store.dicom`):
the caller passes its Part 10 bytes, and this module only carries them to the archive with
pynetdicom. Nothing here touches the library: a send that fails leaves it as it was.

Every way a send can fail ends in one :class:`PacsError` whose message names the problem and
what to check: an address not of the form AE_TITLE@HOST:PORT, an unknown host, nothing
listening, no answer within the timeout, an association the PACS rejected (with the AE
titles and the PACS's reason), a PACS that accepts no context for the object's SOP class, and
a C-STORE failure status (its code in hex and its meaning, PS3.4 B.2.3 and PS3.7 C).
"""

from __future__ import annotations

import io
import math
import socket
import time
from dataclasses import dataclass
from typing import Any

import pydicom
from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian

from lamina_shared.errors import LaminaError

DEFAULT_CALLING_AE = "LAMINA"
"""The AE title ``lamina send`` calls from unless ``--calling-ae`` names another."""
DEFAULT_TIMEOUT_S = 30.0
"""How long ``lamina send`` waits for the connection and for each answer of the PACS."""
AE_TITLE_MAX_CHARS = 16
"""An AE title is a DICOM AE value: 1 to 16 characters, not all spaces (PS3.5 6.2)."""
TARGET_FORM = "AE_TITLE@HOST:PORT (for example ORTHANC@pacs.example.org:4242)"
"""How ``--to`` is written, for the messages that refuse one."""

STORED = ("Success", "Warning")
"""pynetdicom's categories of a C-STORE status that stored the object (PS3.4 B.2.3)."""


class PacsError(LaminaError):
    """A send to a PACS did not store the object; the message says why and what to check."""


@dataclass(frozen=True)
class PacsTarget:
    """Where a scan is sent: the PACS's AE title and its DICOM host and port."""

    called_ae: str
    host: str
    port: int

    def describe(self) -> str:
        """Return the target as the user writes it (AE_TITLE@HOST:PORT)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.called_ae}@{host}:{self.port}"


@dataclass(frozen=True)
class SendReceipt:
    """What the PACS confirmed: the stored instance and the C-STORE status it answered."""

    sop_instance_uid: str
    status: int
    meaning: str


def check_ae_title(title: str, option: str) -> str:
    """Return ``title`` if it is a valid AE title, else raise PacsError (one line).

    Args:
        title: the AE title as typed.
        option: the option it came from, named in the message (``--to``, ``--calling-ae``).
    """
    if not 0 < len(title) <= AE_TITLE_MAX_CHARS or not title.strip():
        raise PacsError(
            f"{option}: the AE title {title!r} must be 1 to {AE_TITLE_MAX_CHARS} characters, "
            "not all spaces"
        )
    if not all(" " <= ch <= "~" for ch in title) or "\\" in title:
        raise PacsError(
            f"{option}: the AE title {title!r} may hold only printable ASCII characters "
            "other than a backslash"
        )
    return title.strip()


def parse_target(text: str) -> PacsTarget:
    """Return the PACS that ``--to`` names: ``AE_TITLE@HOST:PORT`` (an IPv6 host in [ ]).

    Raises:
        PacsError: anything else (the message gives the form).
    """
    title, at, address = text.rpartition("@")
    host, colon, port_text = address.rpartition(":")
    host = host.removeprefix("[").removesuffix("]")
    if not (at and colon and title and host and port_text.isdigit()):
        raise PacsError(f"--to {text!r} is not an address: write {TARGET_FORM}")
    port = int(port_text)
    if not 0 < port < 65536:
        raise PacsError(f"--to {text!r}: the port must be from 1 to 65535")
    return PacsTarget(check_ae_title(title, "--to"), host, port)


def check_timeout(timeout_s: float) -> float:
    """Return ``timeout_s`` if it is a usable timeout in seconds, else raise PacsError."""
    if not (math.isfinite(timeout_s) and 0 < timeout_s <= 3600):
        raise PacsError(
            f"--timeout-s {timeout_s} must be a number of seconds above 0, at most 3600"
        )
    return float(timeout_s)


def status_meaning(code: int) -> str:
    """Return what a C-STORE status code means (PS3.4 B.2.3, PS3.7 C), or "unknown status"."""
    from pynetdicom.status import STORAGE_SERVICE_CLASS_STATUS  # see _pynetdicom

    if code in STORAGE_SERVICE_CLASS_STATUS:
        category, text = STORAGE_SERVICE_CLASS_STATUS[code]
        return text or category
    return "unknown status"


@dataclass
class _Seen:
    """What the association's events showed (pynetdicom reports failures only as states).

    ``rejection`` is the reason of an A-ASSOCIATE-RJ the PACS sent: taken from the PDU
    itself, since a PACS that closes the connection right after its rejection can leave
    pynetdicom reporting an abort instead.
    """

    connected: bool = False
    answered: bool = False
    rejection: str = ""

    def connection_opened(self, event: Any) -> None:
        """EVT_CONN_OPEN: something accepted the TCP connection."""
        self.connected = True

    def pdu_received(self, event: Any) -> None:
        """EVT_PDU_RECV: the peer answered in DICOM; keep the reason of a rejection."""
        self.answered = True
        if type(event.pdu).__name__ == "A_ASSOCIATE_RJ":
            try:
                self.rejection = str(event.pdu.reason_str)
            except ValueError:  # a reason outside PS3.8 9.3.4
                self.rejection = "reason not given in the standard's terms"


def _resolve(target: PacsTarget) -> None:
    """Refuse (PacsError) a host name that does not resolve, before any connection."""
    try:
        socket.getaddrinfo(target.host, target.port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError):
        raise PacsError(
            f"unknown host {target.host!r} in --to {target.describe()}: check the PACS's "
            "host name or give its IP address"
        ) from None


def _pynetdicom() -> Any:
    """Return pynetdicom, imported on first use: it adds a quarter second to every command."""
    import pynetdicom

    return pynetdicom


def _application_entity(calling_ae: str, sop_class: str, timeout_s: float) -> Any:
    ae = _pynetdicom().AE(ae_title=calling_ae)
    for attribute in ("connection_timeout", "acse_timeout", "dimse_timeout", "network_timeout"):
        setattr(ae, attribute, timeout_s)
    # The object is written explicit VR little endian; pynetdicom re-encodes it as implicit
    # VR for a PACS that accepts only the default transfer syntax.
    ae.add_requested_context(sop_class, [ExplicitVRLittleEndian, ImplicitVRLittleEndian])
    return ae


@dataclass(frozen=True)
class _Attempt:
    """One send: where to, from which AE title, and how long each wait may last."""

    target: PacsTarget
    calling_ae: str
    timeout_s: float

    @property
    def where(self) -> str:
        """Return HOST:PORT, for the messages."""
        return f"{self.target.host}:{self.target.port}"

    def timed_out(self, waited_s: float) -> bool:
        """Return whether a wait of ``waited_s`` ran into the timeout (not an early end)."""
        return waited_s >= 0.9 * self.timeout_s


def _not_associated(assoc: Any, seen: _Seen, attempt: _Attempt, waited_s: float) -> PacsError:
    """Return the error that says why an association was not established."""
    where, timeout_s = attempt.where, attempt.timeout_s
    if assoc.is_rejected or seen.rejection:
        reason = seen.rejection or "no reason given"
        return PacsError(
            f"the PACS at {where} refused the association (called AE "
            f"{attempt.target.called_ae!r}, calling AE {attempt.calling_ae!r}): {reason}; check "
            "both AE titles with the PACS's configuration"
        )
    if not seen.connected and attempt.timed_out(waited_s):
        return PacsError(
            f"no connection to {where} within {timeout_s:g} s: check the address, the "
            "network and any firewall, or raise --timeout-s"
        )
    if not seen.connected:
        return PacsError(
            f"nothing accepts DICOM connections at {where} (connection refused or host "
            "unreachable): check the address and that the PACS is running"
        )
    if not seen.answered and attempt.timed_out(waited_s):
        return PacsError(
            f"{where} accepted the connection but did not answer the association within "
            f"{timeout_s:g} s: check that the port is the PACS's DICOM port, or raise --timeout-s"
        )
    if not seen.answered:
        return PacsError(
            f"{where} accepted the connection but did not answer as a DICOM archive: check "
            "that the port is the PACS's DICOM port (not its web port)"
        )
    if assoc.acceptor.primitive is not None and not assoc.accepted_contexts:
        return PacsError(
            f"the PACS at {where} accepts no presentation context for this object's SOP class: "
            "allow Encapsulated STL (or the exported SOP class) in its configuration"
        )
    return PacsError(f"the PACS at {where} aborted the association: see its log")


def send_dicom(
    data: bytes,
    target: PacsTarget,
    calling_ae: str = DEFAULT_CALLING_AE,
    timeout_s: float = DEFAULT_TIMEOUT_S,
) -> SendReceipt:
    """Store a DICOM Part 10 file in the PACS ``target`` by C-STORE.

    Args:
        data: the file's bytes (as ``lamina export`` writes them).
        target: the PACS (see :func:`parse_target`).
        calling_ae: the AE title Lamina calls from.
        timeout_s: the longest wait for the connection and for each answer.

    Returns:
        The stored instance's UID and the status the PACS answered (success or a warning).

    Raises:
        PacsError: the object was not stored (the message says why).
    """
    ds = pydicom.dcmread(io.BytesIO(data))
    _resolve(target)
    seen = _Seen()
    evt = _pynetdicom().evt
    handlers = [(evt.EVT_CONN_OPEN, seen.connection_opened), (evt.EVT_PDU_RECV, seen.pdu_received)]
    attempt = _Attempt(target, calling_ae, timeout_s)
    ae = _application_entity(calling_ae, str(ds.SOPClassUID), timeout_s)
    started = time.monotonic()
    assoc = ae.associate(target.host, target.port, ae_title=target.called_ae, evt_handlers=handlers)
    if not assoc.is_established:
        raise _not_associated(assoc, seen, attempt, time.monotonic() - started)
    started = time.monotonic()
    try:
        status = assoc.send_c_store(ds)
    finally:
        if assoc.is_established:
            assoc.release()
    return _receipt(status, ds, attempt, time.monotonic() - started)


def _receipt(status: Any, ds: Any, attempt: _Attempt, waited_s: float) -> SendReceipt:
    """Return the receipt of a C-STORE response, or raise PacsError for a failure."""
    if "Status" not in status and attempt.timed_out(waited_s):
        raise PacsError(
            f"the PACS at {attempt.where} did not confirm the store within "
            f"{attempt.timeout_s:g} s: check its log, or raise --timeout-s"
        )
    if "Status" not in status:
        # Orthanc, for one, accepts the association, then ends it at the store of an AE
        # title it does not know.
        raise PacsError(
            f"the PACS at {attempt.where} ended the association without storing the scan: "
            f"it may not accept stores from the calling AE {attempt.calling_ae!r}; check its "
            "configuration and its log"
        )
    code = int(status.Status)
    meaning = status_meaning(code)
    from pynetdicom.status import code_to_category  # see _pynetdicom

    if code_to_category(code) not in STORED:
        comment = str(status.get("ErrorComment", "")).strip()
        raise PacsError(
            f"the PACS at {attempt.where} did not store the scan: status "
            f"0x{code:04X} ({meaning}){f', {comment}' if comment else ''}"
        )
    return SendReceipt(str(ds.SOPInstanceUID), code, meaning)
