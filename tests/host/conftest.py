"""A library holding one small processed scan of the simulator, shared by the export tests."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

SUBJECT = "P001-left"


@pytest.fixture(scope="session")
def scanned_library(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Return a library whose scan 1 is a processed 4-section scan of a simulated ellipsoid."""
    tmp = tmp_path_factory.mktemp("scanned")
    library = tmp / "library.sqlite"
    done = subprocess.run(
        [
            sys.executable, "-m", "lamina_host", "scan", "--device", "sim",
            "--object", "ellipsoid:a=10,b=6.5,c=20,z=-1", "--sections", "4", "--pitch", "2",
            "--views", "6", "--subject", SUBJECT, "--side", "left", "--library", str(library),
            "-o", str(tmp / "scan"),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return library
