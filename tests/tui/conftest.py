"""Fixtures for the terminal UI tests: a scan library with one processed simulated scan."""

from __future__ import annotations

import sqlite3
import sys
from pathlib import Path

import pytest

from lamina_host.tui.adapter import Session, parse_plan

# The helpers in drive.py sit beside the tests; pytest's importlib mode does not add
# this folder to the import path by itself.
sys.path.insert(0, str(Path(__file__).parent))

FIXED_CREATED = "2025-01-01T09:00:00+00:00"


@pytest.fixture(scope="session")
def scanned_library(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Return a library holding one 2 x 8 scan of the simulated 19.05 mm cylinder, processed."""
    path = tmp_path_factory.mktemp("library") / "library.sqlite"
    session = Session("sim", path)
    try:
        session.connect()
        session.calibrate_grid()
        session.accept_grid(True)
        session.calibrate_axis()
        session.scan_object("CYL-1", parse_plan("2", "2", "8"))
        session.process(harmonics=5)
    finally:
        session.close()
    # Snapshots must not show the clock: give the scan a fixed creation time.
    with sqlite3.connect(path) as db:
        db.execute("UPDATE scans SET created = ?", (FIXED_CREATED,))
    return path
