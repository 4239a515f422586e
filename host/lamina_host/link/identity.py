"""What acquired a scan: the device, its software, source, calibration and extraction.

A scan records its identity when it is created; a resume on another device, or on the
same device with another object or calibration, is refused rather than merged into it.
The identity is read from the device's WELCOME and, for a device the host started
itself (``sim``, ``replay:DIR``), from what the host asked it to acquire.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lamina_shared.device_specs import SIM, replay_folder
from lamina_shared.errors import printable
from lamina_shared.messages import Welcome
from lamina_shared.types import ScanPlan


def spawned_source(
    device: str, object_spec: str | None, seed: int | None, noise: str | None, rig: str | None
) -> str | None:
    """Return what a device the host starts itself acquires, as the host asked for it.

    For ``sim`` the object, rig, noise and seed; for ``replay:DIR`` the capture's name and
    the SHA-256 of its ``capture.json``. None for a real device (it reports its own).
    """
    if device == SIM:
        return (
            f"sim object={object_spec or 'default'} rig={rig or 'thesis'} "
            f"noise={noise or 'thesis'} seed={0 if seed is None else seed}"
        )
    if (capture := replay_folder(device)) is not None:
        folder = Path(capture)
        try:
            digest = hashlib.sha256((folder / "capture.json").read_bytes()).hexdigest()
        except OSError:
            digest = "unreadable"
        return f"replay {folder.name} sha256={digest}"
    return None


def _plain(value: Any) -> Any:
    """Return ``value`` as JSON would give it back (tuples become lists, keys strings)."""
    return json.loads(json.dumps(value, sort_keys=True, default=str))


def scan_identity(welcome: Welcome, spawned: str | None = None) -> dict[str, Any]:
    """Return the identity of what acquires a scan, from the device's WELCOME.

    Fields the device does not report (an older device) are left out. The device's own
    ``identity.source`` takes precedence over ``spawned`` (what the host asked a device it
    started to simulate or replay). ``calibration`` is a hash of the calibration setup the
    device reported (board, cylinder and image size).
    """
    identity: dict[str, Any] = {}
    if welcome.identity is not None:
        for key, value in welcome.identity.to_wire().items():
            identity[key] = value
    if "source" not in identity and spawned is not None:
        identity["source"] = spawned
    reported = {
        "software": welcome.software,
        "hardware": welcome.hardware,
        "description": welcome.description,
        "image_size": list(welcome.image_size),
        "protocol": welcome.protocol,
        "extract": welcome.extract.to_wire() if welcome.extract is not None else None,
        "row_turn_deg": welcome.row_turn_deg,
        "off_frames": welcome.off_frames,
    }
    identity.update({key: _plain(value) for key, value in reported.items() if value is not None})
    setup = {
        "board": welcome.board.to_dict() if welcome.board else None,
        "cylinder_diameter_mm": welcome.cylinder_diameter_mm,
        "image_size": list(welcome.image_size),
        # No device reports a calibration record; the key stays in the hashed text so
        # the hashes of scans recorded before the WELCOME was typed still match.
        "calibration": None,
    }
    blob = json.dumps(_plain(setup), sort_keys=True).encode()
    identity["calibration"] = hashlib.sha256(blob).hexdigest()[:16]
    return identity


def row_turn_deg(identity: Mapping[str, Any] | None, plan: ScanPlan | None) -> float:
    """Return the turn per image row to give a scan's object points (0.0: none).

    Only a continuous scan's views were exposed row by row while the table turned; the
    figure is the one its device reported (``row_turn_deg`` of the WELCOME) when the scan
    began, kept in its identity, so reprocessing it later turns its points the same.

    Args:
        identity: the scan's identity (:func:`scan_identity`), None if it has none.
        plan: the scan's object plan, None if unknown.
    """
    value = (identity or {}).get("row_turn_deg")
    if plan is None or not plan.continuous or isinstance(value, bool):
        return 0.0
    return float(value) if isinstance(value, int | float) and math.isfinite(value) else 0.0


def laser_off_turn_later(identity: Mapping[str, Any] | None, plan: ScanPlan | None) -> bool:
    """Return True when a scan's views took their laser-off frames a turn of the count later.

    Only a continuous scan's, on a device that said so (``off_frames`` of the WELCOME)
    when the scan began; the host then warns where its calibration finds the table
    turning short of its count (:func:`lamina_host.reconstruct.axis.next_turn_warning`).

    Args:
        identity: the scan's identity (:func:`scan_identity`), None if it has none.
        plan: the scan's object plan, None if unknown.
    """
    if plan is None or not plan.continuous:
        return False
    return (identity or {}).get("off_frames") == "next-turn"


def legacy_identity(device: Mapping[str, Any], spawned: str | None) -> dict[str, Any]:
    """Return the identity a scan recorded before identities existed can be given.

    Args:
        device: what the scan recorded about its device (``software``, ``hardware``).
        spawned: what the host asked a device it started to acquire
            (:func:`spawned_source`), None for a real device.
    """
    identity: dict[str, Any] = {"legacy": True}
    if spawned is not None:
        identity["source"] = spawned
    for key in ("software", "hardware"):
        if device.get(key) is not None:
            identity[key] = _plain(device[key])
    return identity


def _shown(value: Any) -> str:
    text = "absent" if value is None else json.dumps(value, sort_keys=True)
    text = printable(text)
    return text if len(text) <= 60 else text[:57] + "..."


LATER_KEYS = frozenset({"row_turn_deg", "count_since", "off_frames"})
"""Identity keys added after scans were recorded without them: such a scan is compared
without the key (it is processed as it was recorded, without the figure), so an update
does not leave a half-acquired scan that no resume can finish."""


def count_restarted(recorded: Mapping[str, Any], current: Mapping[str, Any]) -> bool:
    """Return True when the device that recorded a scan is the same but its program has
    started again since: its ``count_since`` changed and nothing else did.

    The box's turntable has no index; its step count starts at 0 wherever the table
    stands, so angles counted before and after cannot be told apart or joined.
    """
    if "count_since" not in recorded or recorded.get("count_since") == current.get("count_since"):
        return False
    others = {k: v for k, v in current.items() if k != "count_since"}
    kept = {k: v for k, v in recorded.items() if k != "count_since"}
    return identity_difference(kept, others) is None


def calibration_mismatch(
    calibrated: Mapping[str, Any], current: Mapping[str, Any], counts_held: bool
) -> str | None:
    """Return why a calibration made on ``calibrated`` cannot serve ``current``, or None.

    The same box whose program started again is still calibrated as far as its camera
    goes (the chessboard), but its turntable now counts from wherever it stood, so
    cylinder views counted before (``counts_held``) cannot be joined to a scan counted
    after; any other difference is another device or setup.

    Args:
        calibrated: the identity of the device when the calibration was captured.
        current: the connected device's identity.
        counts_held: whether cylinder views counted on ``calibrated`` are to be used.

    Returns:
        One line naming the problem and what to do, or None when the calibration serves.
    """
    if count_restarted(calibrated, current):
        if not counts_held:
            return None
        return (
            "the device's program has started again since the calibration cylinder was "
            "scanned, so its turntable now counts from wherever it stood: scan the "
            "cylinder again (Calibrate screen, F4) before scanning"
        )
    difference = identity_difference(calibrated, current)
    if difference is None:
        return None
    return (
        f"the connected device is not the one calibrated ({difference}): calibrate again "
        "(F4) before scanning with it"
    )


def identity_difference(recorded: Mapping[str, Any], current: Mapping[str, Any]) -> str | None:
    """Return what differs between a scan's recorded identity and the current one, or None.

    A scan recorded before identities existed (``legacy``) is compared on what it recorded.
    """
    keys = set(recorded) if recorded.get("legacy") else set(recorded) | set(current)
    keys -= {"legacy", *(LATER_KEYS - set(recorded))}
    current_plain = _plain(dict(current))
    differs = [k for k in sorted(keys) if recorded.get(k) != current_plain.get(k)]
    if not differs:
        return None
    details = "; ".join(
        f"{k} was {_shown(recorded.get(k))}, now {_shown(current_plain.get(k))}"
        for k in differs[:2]
    )
    return f"{', '.join(differs)} {'differs' if len(differs) == 1 else 'differ'}: {details}"
