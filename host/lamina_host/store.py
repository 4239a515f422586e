"""The scan library: one SQLite file (WAL mode) holding everything a scan produced.

Subjects (by pseudonymous code only), scans with their plans and options, the
calibration each scan used (board image, board geometry, cylinder diameter; the
cylinder's segments are the scan's ``cylinder`` segments), every segment received,
processing results (the report and the output files) and a record of exports.

A segment is committed (``synchronous=FULL``) before :meth:`Library.add_segment`
returns, and the link acknowledges it only after that, so a host killed at any moment
holds every segment the device believes delivered. The file is created readable by
its owner only (mode 0600; SQLite gives its ``-wal`` and ``-shm`` files the same mode).
Use one :class:`Library` per thread; WAL lets several read while one writes.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import tempfile
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np

from lamina_shared.types import BoardSpec, ScanPlan, Segment

SCHEMA_VERSION = 1
STATUSES = ("acquiring", "acquired", "processed")
"""A scan is ``acquiring`` until every planned view is held, ``processed`` once it has a result."""

_SCHEMA = """
CREATE TABLE IF NOT EXISTS subjects (
    id INTEGER PRIMARY KEY,
    code TEXT NOT NULL UNIQUE,
    created TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS scans (
    id INTEGER PRIMARY KEY,
    subject_id INTEGER NOT NULL REFERENCES subjects(id),
    created TEXT NOT NULL,
    status TEXT NOT NULL CHECK (status IN ('acquiring', 'acquired', 'processed')),
    device TEXT NOT NULL,
    options TEXT NOT NULL,
    plans TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS calibrations (
    id INTEGER PRIMARY KEY,
    scan_id INTEGER NOT NULL UNIQUE REFERENCES scans(id) ON DELETE CASCADE,
    created TEXT NOT NULL,
    board TEXT NOT NULL,
    grid_png BLOB NOT NULL,
    cylinder_mm REAL
);
CREATE TABLE IF NOT EXISTS segments (
    scan_id INTEGER NOT NULL REFERENCES scans(id) ON DELETE CASCADE,
    target TEXT NOT NULL,
    seq INTEGER NOT NULL,
    section INTEGER NOT NULL,
    view INTEGER NOT NULL,
    z_mm REAL NOT NULL,
    angle_deg REAL NOT NULL,
    points INTEGER NOT NULL,
    data BLOB NOT NULL,
    PRIMARY KEY (scan_id, target, seq)
);
CREATE TABLE IF NOT EXISTS results (
    scan_id INTEGER PRIMARY KEY REFERENCES scans(id) ON DELETE CASCADE,
    created TEXT NOT NULL,
    report TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS result_files (
    scan_id INTEGER NOT NULL REFERENCES scans(id) ON DELETE CASCADE,
    name TEXT NOT NULL,
    data BLOB NOT NULL,
    PRIMARY KEY (scan_id, name)
);
CREATE TABLE IF NOT EXISTS exports (
    id INTEGER PRIMARY KEY,
    scan_id INTEGER NOT NULL REFERENCES scans(id) ON DELETE CASCADE,
    created TEXT NOT NULL,
    format TEXT NOT NULL,
    path TEXT NOT NULL
);
"""

EXPORT_FORMATS = (".ply", ".obj", ".stl", ".json")


class StoreError(Exception):
    """The library cannot do what was asked; the message says why and what to do."""


@dataclass(frozen=True)
class ScanSummary:
    """One line of the library's list of scans."""

    id: int
    subject: str
    created: str
    status: str
    sections: int
    views: int
    received: int
    has_result: bool


@dataclass(frozen=True)
class ScanRecord:
    """What a scan was asked to be: subject, plans per target, options, device."""

    id: int
    subject: str
    created: str
    status: str
    plans: dict[str, ScanPlan]
    options: dict[str, Any]
    device: dict[str, Any]


@dataclass(frozen=True)
class Calibration:
    """The calibration data a scan used (its cylinder segments are the scan's)."""

    grid_image: np.ndarray
    board: BoardSpec
    cylinder_mm: float | None


def default_library_path() -> Path:
    """Return ``$XDG_DATA_HOME/lamina/library.sqlite`` (``~/.local/share`` if unset)."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "lamina" / "library.sqlite"


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _segment_blob(segment: Segment) -> bytes:
    """Return the segment's arrays, losslessly: cols u16, rows f32, peak, width, confidence u8."""
    return b"".join(
        (
            np.ascontiguousarray(segment.cols, "<u2").tobytes(),
            np.ascontiguousarray(segment.rows, "<f4").tobytes(),
            np.ascontiguousarray(segment.peak, "u1").tobytes(),
            np.ascontiguousarray(segment.width, "u1").tobytes(),
            np.ascontiguousarray(segment.confidence, "u1").tobytes(),
        )
    )


def _segment_from_row(row: sqlite3.Row) -> Segment:
    n, data = row["points"], row["data"]
    # 8 bytes a point before segments carried a confidence (then unknown: zeros), 9 since.
    if len(data) not in (8 * n, 9 * n):
        raise StoreError(f"stored segment {row['seq']} is damaged: restore the library")
    confidence = np.frombuffer(data, "u1", n, 8 * n).copy() if len(data) == 9 * n else None
    return Segment(
        row["target"],
        row["section"],
        row["view"],
        row["z_mm"],
        row["angle_deg"],
        np.frombuffer(data, "<u2", n, 0).astype(np.uint16),
        np.frombuffer(data, "<f4", n, 2 * n).astype(np.float32),
        np.frombuffer(data, "u1", n, 6 * n).copy(),
        np.frombuffer(data, "u1", n, 7 * n).copy(),
        *(() if confidence is None else (confidence,)),
    )


def _create_private(path: Path) -> None:
    """Create ``path`` (and its folder) readable by the owner only, if it does not exist."""
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    os.close(fd)


class Library:
    """The scan library file; a context manager that closes it."""

    def __init__(self, path: Path | None = None) -> None:
        self.path = Path(path) if path is not None else default_library_path()
        try:
            _create_private(self.path)
            self._db = sqlite3.connect(self.path, timeout=30.0)
            self._db.row_factory = sqlite3.Row
            version = self._db.execute("PRAGMA user_version").fetchone()[0]
            if version > SCHEMA_VERSION:
                raise StoreError(
                    f"library {self.path} was written by a newer Lamina (schema {version}): "
                    "upgrade lamina-host"
                )
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=ON")
            with self._db:
                self._db.executescript(_SCHEMA)
                self._db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
        except (sqlite3.Error, OSError) as exc:
            raise StoreError(f"cannot open the scan library {self.path}: {exc}") from None

    def __enter__(self) -> Library:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the file."""
        self._db.close()

    # --- scans -----------------------------------------------------------------------

    def create_scan(
        self,
        subject: str,
        plans: dict[str, ScanPlan],
        options: dict[str, Any] | None = None,
        device: dict[str, Any] | None = None,
    ) -> int:
        """Record a new scan of ``subject`` (a pseudonymous code); return its id."""
        if not subject or len(subject) > 64:
            raise StoreError("a subject code needs 1 to 64 characters")
        with self._db:
            self._db.execute(
                "INSERT OR IGNORE INTO subjects (code, created) VALUES (?, ?)", (subject, _now())
            )
            (subject_id,) = self._db.execute(
                "SELECT id FROM subjects WHERE code = ?", (subject,)
            ).fetchone()
            cursor = self._db.execute(
                "INSERT INTO scans (subject_id, created, status, device, options, plans) "
                "VALUES (?, ?, 'acquiring', ?, ?, ?)",
                (
                    subject_id,
                    _now(),
                    json.dumps(device or {}),
                    json.dumps(options or {}),
                    json.dumps({t: p.to_dict() for t, p in plans.items()}),
                ),
            )
        assert cursor.lastrowid is not None
        return cursor.lastrowid

    def scan(self, scan_id: int) -> ScanRecord:
        """Return what scan ``scan_id`` was asked to be."""
        row = self._db.execute(
            "SELECT scans.*, subjects.code FROM scans JOIN subjects ON subjects.id = subject_id "
            "WHERE scans.id = ?",
            (scan_id,),
        ).fetchone()
        if row is None:
            raise StoreError(f"there is no scan {scan_id} in {self.path}: see lamina scans")
        plans = {t: ScanPlan.from_dict(p) for t, p in json.loads(row["plans"]).items()}
        return ScanRecord(
            row["id"],
            row["code"],
            row["created"],
            row["status"],
            plans,
            json.loads(row["options"]),
            json.loads(row["device"]),
        )

    def scans(self) -> list[ScanSummary]:
        """Return every scan, oldest first."""
        rows = self._db.execute(
            "SELECT scans.id, code, scans.created, status, plans, "
            "(SELECT COUNT(*) FROM segments WHERE scan_id = scans.id AND target = 'object') "
            "AS received, (SELECT COUNT(*) FROM results WHERE scan_id = scans.id) AS results "
            "FROM scans JOIN subjects ON subjects.id = subject_id ORDER BY scans.id"
        ).fetchall()
        out = []
        for row in rows:
            plan = json.loads(row["plans"]).get("object", {"views": []})
            views = plan["views"]
            sections = len({v["section"] for v in views})
            out.append(
                ScanSummary(
                    row["id"],
                    row["code"],
                    row["created"],
                    row["status"],
                    sections,
                    len(views),
                    row["received"],
                    row["results"] > 0,
                )
            )
        return out

    def set_status(self, scan_id: int, status: str) -> None:
        """Set the scan's status (one of :data:`STATUSES`)."""
        if status not in STATUSES:
            raise ValueError(f"unknown scan status {status!r}")
        with self._db:
            self._db.execute("UPDATE scans SET status = ? WHERE id = ?", (status, scan_id))

    def delete_scan(self, scan_id: int) -> None:
        """Remove a scan and everything recorded for it (its subject stays)."""
        self.scan(scan_id)
        with self._db:
            self._db.execute("DELETE FROM scans WHERE id = ?", (scan_id,))

    # --- segments --------------------------------------------------------------------

    def add_segment(self, scan_id: int, seq: int, segment: Segment) -> bool:
        """Commit segment ``seq`` (its plan index) of ``segment.target``; False if already held."""
        with self._db:
            cursor = self._db.execute(
                "INSERT OR IGNORE INTO segments (scan_id, target, seq, section, view, z_mm, "
                "angle_deg, points, data) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    scan_id,
                    segment.target,
                    seq,
                    segment.section,
                    segment.view,
                    segment.z_mm,
                    segment.angle_deg,
                    len(segment),
                    _segment_blob(segment),
                ),
            )
        return cursor.rowcount == 1

    def held(self, scan_id: int, target: str) -> set[int]:
        """Return the plan indices of ``target`` already stored for the scan."""
        rows = self._db.execute(
            "SELECT seq FROM segments WHERE scan_id = ? AND target = ?", (scan_id, target)
        )
        return {row[0] for row in rows}

    def missing(self, scan_id: int, target: str) -> list[int]:
        """Return the plan indices of ``target`` not stored yet."""
        plan = self.scan(scan_id).plans.get(target)
        held = self.held(scan_id, target)
        return [s for s in range(len(plan.views)) if s not in held] if plan else []

    def segments(self, scan_id: int, target: str) -> list[Segment]:
        """Return the stored segments of ``target`` in plan order."""
        rows = self._db.execute(
            "SELECT * FROM segments WHERE scan_id = ? AND target = ? ORDER BY seq",
            (scan_id, target),
        ).fetchall()
        return [_segment_from_row(row) for row in rows]

    # --- calibration and results -----------------------------------------------------

    def save_calibration(
        self, scan_id: int, grid_image: np.ndarray, board: BoardSpec, cylinder_mm: float | None
    ) -> None:
        """Store the calibration board image and geometry the scan uses."""
        ok, png = cv2.imencode(".png", grid_image)
        if not ok:
            raise StoreError("the calibration image could not be encoded")
        with self._db:
            self._db.execute(
                "INSERT OR REPLACE INTO calibrations (scan_id, created, board, grid_png, "
                "cylinder_mm) VALUES (?, ?, ?, ?, ?)",
                (scan_id, _now(), json.dumps(board.to_dict()), png.tobytes(), cylinder_mm),
            )

    def calibration(self, scan_id: int) -> Calibration | None:
        """Return the scan's calibration data, or None if it has none yet."""
        row = self._db.execute(
            "SELECT * FROM calibrations WHERE scan_id = ?", (scan_id,)
        ).fetchone()
        if row is None:
            return None
        image = cv2.imdecode(np.frombuffer(row["grid_png"], np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise StoreError(f"the calibration image of scan {scan_id} is damaged")
        board = BoardSpec.from_dict(json.loads(row["board"]))
        return Calibration(image, board, row["cylinder_mm"])

    def save_result(self, scan_id: int, report: dict[str, Any], files: dict[str, Path]) -> None:
        """Store the processing report and output files (replacing earlier ones)."""
        blobs = {name: Path(path).read_bytes() for name, path in files.items()}
        with self._db:
            self._db.execute("DELETE FROM result_files WHERE scan_id = ?", (scan_id,))
            self._db.execute(
                "INSERT OR REPLACE INTO results (scan_id, created, report) VALUES (?, ?, ?)",
                (scan_id, _now(), json.dumps(report)),
            )
            self._db.executemany(
                "INSERT INTO result_files (scan_id, name, data) VALUES (?, ?, ?)",
                [(scan_id, name, data) for name, data in blobs.items()],
            )
            self._db.execute("UPDATE scans SET status = 'processed' WHERE id = ?", (scan_id,))

    def result(self, scan_id: int) -> dict[str, Any] | None:
        """Return the scan's report, or None if it was never processed."""
        row = self._db.execute("SELECT report FROM results WHERE scan_id = ?", (scan_id,))
        found = row.fetchone()
        return json.loads(found[0]) if found else None

    def _result_file(self, scan_id: int, name: str) -> bytes | None:
        row = self._db.execute(
            "SELECT data FROM result_files WHERE scan_id = ? AND name = ?", (scan_id, name)
        ).fetchone()
        return bytes(row[0]) if row else None

    def export(self, scan_id: int, path: Path) -> Path:
        """Write the scan's result to ``path``: mesh as PLY/OBJ/STL by extension, or the report.

        Raises:
            StoreError: unknown extension, existing file, or a scan without that result.
        """
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix not in EXPORT_FORMATS:
            raise StoreError(
                f"cannot export {path.name}: name the file .ply, .obj, .stl (mesh) "
                "or .json (report)"
            )
        if path.exists():
            raise StoreError(f"{path} already exists: choose a new file name")
        self.scan(scan_id)
        report = self.result(scan_id)
        if report is None:
            raise StoreError(
                f"scan {scan_id} has no result yet: finish it with lamina scan --resume {scan_id}"
            )
        if suffix == ".json":
            path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
        else:
            mesh = self._result_file(scan_id, "mesh.ply")
            if mesh is None:
                raise StoreError(f"scan {scan_id} produced no mesh to export")
            _write_mesh(mesh, path)
        with self._db:
            self._db.execute(
                "INSERT INTO exports (scan_id, created, format, path) VALUES (?, ?, ?, ?)",
                (scan_id, _now(), suffix.lstrip("."), str(path.resolve())),
            )
        return path


def _write_mesh(ply: bytes, path: Path) -> None:
    """Write a stored PLY mesh to ``path`` in the format its extension names."""
    if path.suffix.lower() == ".ply":
        path.write_bytes(ply)
        return
    import pymeshlab  # deferred: heavy import, only needed for format conversion

    with tempfile.TemporaryDirectory() as tmp:
        source = Path(tmp) / "mesh.ply"
        source.write_bytes(ply)
        meshes = pymeshlab.MeshSet()
        meshes.load_new_mesh(str(source))
        target = Path(tmp) / f"out{path.suffix.lower()}"
        meshes.save_current_mesh(str(target))
        shutil.move(str(target), path)
