"""Subject codes: pseudonyms of a fixed character set, never free text.

A code could otherwise hold a patient's name or terminal escapes; the library refuses
any other code, and both front ends check what is typed against the same rule.
"""

from __future__ import annotations

import re

from lamina_shared.errors import InputError, printable

SUBJECT_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,31}")
SUBJECT_RULE = (
    "1 to 32 characters: ASCII letters, digits, '.', '_' and '-', starting with a letter "
    "or digit (a pseudonymous code such as P001-left, never a name)"
)


def check_subject(code: str) -> str:
    """Return ``code`` if it is a valid subject code, else raise :class:`InputError`."""
    if not isinstance(code, str) or SUBJECT_PATTERN.fullmatch(code) is None:
        shown = printable(str(code))[:40]
        raise InputError(f"subject code '{shown}' is not allowed: use {SUBJECT_RULE}")
    return code
