"""Reading a scan library from outside the program that writes it."""

from __future__ import annotations

import sqlite3
from pathlib import Path


def held_segments(library_path: Path) -> int:
    """Return how many object segments the library holds, read-only; 0 if unreadable yet."""
    try:
        with sqlite3.connect(f"file:{library_path}?mode=ro", uri=True) as db:
            return db.execute("SELECT COUNT(*) FROM segments WHERE target='object'").fetchone()[0]
    except sqlite3.Error:
        return 0
