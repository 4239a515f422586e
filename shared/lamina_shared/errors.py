"""The user-facing error base class every Lamina package derives its errors from.

A :class:`LaminaError` carries a message written for the person at the scanner: one line
that names the problem and what to do. Front ends (the command lines, the terminal UI,
the device's request handler) catch this one class and show the message; anything else
that escapes is a programming error and is reported as such, with its traceback logged.
Each concrete error also keeps its traditional built-in base (``ValueError`` for bad
input, ``ConnectionError`` for the link...) so callers may still catch by kind.
"""

from __future__ import annotations

__all__ = ["LaminaError"]


class LaminaError(Exception):
    """A problem the user can act on; ``str(error)`` is the one line to show them."""
