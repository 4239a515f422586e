"""The user-facing error base class every Lamina package derives its errors from.

A :class:`LaminaError` carries a message written for the person at the scanner: one line
that names the problem and what to do. Front ends (the command lines, the terminal UI,
the device's request handler) catch this one class and show the message; anything else
that escapes is a programming error and is reported as such, with its traceback logged.
Each concrete error also keeps its traditional built-in base (``ValueError`` for bad
input, ``ConnectionError`` for the link...) so callers may still catch by kind.
"""

from __future__ import annotations

import unicodedata

__all__ = ["InputError", "LaminaError", "printable"]


class LaminaError(Exception):
    """A problem the user can act on; ``str(error)`` is the one line to show them."""


class InputError(LaminaError, ValueError):
    """A value typed by the user is refused; the text names it and what to enter."""


def printable(text: str) -> str:
    """Return ``text`` with control and format characters (escapes, newlines) shown escaped.

    Idempotent: text already printable is returned unchanged.
    """
    return "".join(
        ch.encode("unicode_escape").decode("ascii") if unicodedata.category(ch)[0] == "C" else ch
        for ch in text
    )
