"""Durations said for the people at the scanner: ``7 min 05 s``, ``42 s``."""

from __future__ import annotations

import math

__all__ = ["duration_text"]


def duration_text(seconds: float) -> str:
    """Return ``seconds`` as a technician reads it out: ``"7 min 05 s"`` or ``"42 s"``.

    Args:
        seconds: the duration; not finite or negative gives ``"unknown"``.

    Returns:
        Whole seconds, with minutes from one minute on.
    """
    if not math.isfinite(seconds) or seconds < 0:
        return "unknown"
    whole = round(seconds)
    return f"{whole // 60} min {whole % 60:02d} s" if whole >= 60 else f"{whole} s"
