"""The scan library a job works in: opened once, shared by every step and thread."""

from __future__ import annotations

import threading
from pathlib import Path

from lamina_host.store.files import PRIVATE_FOLDER
from lamina_host.store.library import Library, ScanSummary
from lamina_shared.errors import InputError

EXPORT_NAMES = ("mesh.ply", "mesh.obj", "mesh.stl", "report.json")
"""What an export writes into its folder: the mesh in three formats and the scan report."""


class LibraryAccess:
    """The job's scan library: the one handed in, or its own, opened on first use."""

    def __init__(self, path: Path | None = None, library: Library | None = None) -> None:
        self.path = library.path if library is not None else path
        self._given = library
        self._own: Library | None = None
        self._lock = threading.Lock()

    def library(self) -> Library:
        """Return the job's scan library, opened on first use and kept until :meth:`close`.

        One connection for every step and thread of the job (a :class:`Library` serialises
        its calls), so a process holds one rather than one per step; a library handed in
        at construction is used instead and left to its owner to close.
        """
        if self._given is not None:
            return self._given
        with self._lock:
            if self._own is None:
                self._own = Library(self.path)
            return self._own

    def close(self) -> None:
        """Close the job's own library (opened again if a later step needs it)."""
        with self._lock:
            own, self._own = self._own, None
        if own is not None:
            own.close()

    def scans(self) -> list[ScanSummary]:
        """Return the library's scans, oldest first."""
        return self.library().scans()

    def export_scan(self, scan_id: int, folder: Path) -> list[Path]:
        """Export a processed library scan (mesh and report) into ``folder`` (new or empty)."""
        if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
            raise InputError(f"{folder} is not an empty folder; choose a new one")
        folder.mkdir(parents=True, exist_ok=True, mode=PRIVATE_FOLDER)
        library = self.library()
        return [library.export(scan_id, folder / name) for name in EXPORT_NAMES]
