"""How each outline of a scan was closed, or why it could not be: the one list of statuses.

The pipeline sets them, ``report.json`` records them, and the summary, the Results screen
and the clinical measurements read them; all import them from here.
"""

from __future__ import annotations

from enum import StrEnum


class OutlineStatus(StrEnum):
    """The status of one outline (a str, so it is written to JSON as its value).

    ``MEASURED``: seen all round. ``BRIDGED``: small unseen gaps closed by EFD.
    ``INTERPOLATED``: a wide gap filled from the neighbouring sections' EFD. ``OPEN``: a
    gap too wide and no neighbour to fill it; not meshed. ``FAILED``: the outline could
    not be processed (the report gives the reason); not meshed, the others are.
    """

    MEASURED = "measured"
    BRIDGED = "bridged"
    INTERPOLATED = "interpolated"
    OPEN = "open"
    FAILED = "failed"


ESTIMATED = (OutlineStatus.BRIDGED, OutlineStatus.INTERPOLATED)
"""Closed outlines with stretches estimated rather than measured."""

CLOSED = (OutlineStatus.MEASURED, *ESTIMATED)
"""The statuses of outlines that are closed (and meshed)."""
