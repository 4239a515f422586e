"""The scan library: one SQLite file (WAL mode) holding everything a scan produced.

Subjects (by pseudonymous code only), scans with their plans and options, the
calibration each scan used (board image, board geometry, cylinder diameter; the
cylinder's segments are the scan's ``cylinder`` segments), every segment received,
processing results (the report and the output files) and a record of exports.

A segment is committed (``synchronous=FULL``) before :meth:`Library.add_segment`
returns, and the link acknowledges it only after that, so a host killed at any moment
holds every segment the device believes delivered. The file is created readable by
its owner only (mode 0600; SQLite gives its ``-wal`` and ``-shm`` files the same mode).
A library file found readable by others is made owner-only (:attr:`Library.notices`
says so).

Many processes may use one library at once (scans, listings, exports, the terminal UI):
WAL lets them read while one writes, and a writer waits for another's commit. That holds
because nothing but SQLite ever opens the file: POSIX record locks belong to a process,
and closing any other descriptor of the file would silently drop the locks of every
connection the process holds, letting another process delete the WAL under them (issue
19). A process keeps one :class:`Library` (it may be shared by its threads), and opening
one checks the file (``PRAGMA quick_check``): a damaged library is refused in one line and
left untouched.

Each scan records the identity of what acquired it (device serial, software, hardware,
source object or capture, calibration, extraction settings; see
:func:`lamina_host.link.identity.scan_identity`). Segments and calibration are only added
under that identity (:meth:`Library.add_segment`), so one scan never mixes two
acquisitions. Schema 2 added the identity; a schema-1 library is migrated on opening,
its scans given a ``legacy`` identity rebuilt from what they recorded. Schema 3 lets a
segment's blob carry its points' colour (``_segment_blob``): schema-2 data reads
unchanged, and an older Lamina refuses the library instead of taking colour for damage.
Schema 4 added the limb side of each scan (:data:`SIDES`: a clinic's history must tell
the left arm from the right); older libraries are migrated on opening, their scans given
side ``none`` (nothing else changes, so nothing is lost) until set with
:meth:`Library.set_side`. Schema 5 lets a scan be marked as a test (a calibration check, a
phantom, a trial run under a subject's code: :meth:`Library.set_test`), so it stays in the
library but out of the subject's trend and comparisons; older libraries are migrated on
opening with no scan marked. Schema 6 keeps each calibration's lift reference (the
calibration cylinder's two grooves, from which the lift's scale is measured); calibrations
recorded before it have none, and their scans' heights stay as the lift commanded them.
"""

from __future__ import annotations

import json
import os
import sqlite3
import tempfile
import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from types import MappingProxyType
from typing import Any

import cv2
import numpy as np

from lamina_host.link.identity import (
    count_restarted,
    identity_difference,
    laser_off_turn_later,
    legacy_identity,
    row_turn_deg,
    spawned_source,
)
from lamina_host.reconstruct.mesh import load_coloured_ply, obj_bytes, stl_bytes
from lamina_host.store.files import (
    OutputError,
    json_text,
    new_file_problem,
    tighten,
    write_new_file,
)
from lamina_host.store.subjects import check_subject
from lamina_shared.errors import InputError, LaminaError
from lamina_shared.scoped import Scoped
from lamina_shared.types import BoardSpec, LiftReference, ScanPlan, Segment, from_first_turn

SCHEMA_VERSION = 7
SIDES = ("none", "left", "right")
"""The limb side a scan records; ``none`` for anything that is not one of a pair."""
BUSY_TIMEOUT_S = 30.0
"""How long a connection waits for another's write to end before it gives up."""
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
    plans TEXT NOT NULL,
    identity TEXT NOT NULL DEFAULT '{}',
    side TEXT NOT NULL DEFAULT 'none' CHECK (side IN ('none', 'left', 'right')),
    test INTEGER NOT NULL DEFAULT 0 CHECK (test IN (0, 1))
);
CREATE TABLE IF NOT EXISTS calibrations (
    id INTEGER PRIMARY KEY,
    scan_id INTEGER NOT NULL UNIQUE REFERENCES scans(id) ON DELETE CASCADE,
    created TEXT NOT NULL,
    board TEXT NOT NULL,
    grid_png BLOB NOT NULL,
    cylinder_mm REAL,
    lift_reference TEXT
);
CREATE TABLE IF NOT EXISTS segments (
    scan_id INTEGER NOT NULL REFERENCES scans(id) ON DELETE CASCADE,
    target TEXT NOT NULL,
    seq INTEGER NOT NULL,
    section INTEGER NOT NULL,
    view INTEGER NOT NULL,
    z_mm REAL NOT NULL,
    angle_deg REAL NOT NULL,
    turns INTEGER NOT NULL DEFAULT 0,
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

EXPORT_FORMATS: Mapping[str, str] = MappingProxyType(
    {".ply": "mesh", ".obj": "mesh", ".stl": "mesh", ".json": "report"}
)
"""What :meth:`Library.export` writes, by extension, with what each holds; ``lamina export``
adds ``.dcm`` and ``.lrec`` (:data:`lamina_host.workflow.exports.EXPORTERS`)."""


def formats_text(formats: Mapping[str, str]) -> str:
    """Return export formats as a user reads them: ``.ply, .obj (mesh) or .json (report)``.

    Args:
        formats: what each extension holds, in the order to name them.
    """
    groups: list[tuple[list[str], str]] = []
    for suffix, what in formats.items():
        if groups and groups[-1][1] == what:
            groups[-1][0].append(suffix)
        else:
            groups.append(([suffix], what))
    named = [f"{', '.join(suffixes)} ({what})" for suffixes, what in groups]
    return " or ".join([", ".join(named[:-1]), named[-1]]) if len(named) > 1 else named[0]


def unknown_format(path: Path, formats: Mapping[str, str]) -> StoreError:
    """Return the refusal of an export named with none of the ``formats``' extensions."""
    return StoreError(f"cannot export {path.name}: name the file {formats_text(formats)}")


class StoreError(LaminaError):
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
    side: str = SIDES[0]
    test: bool = False
    """Marked as a test scan: kept, but out of trends and comparisons."""


@dataclass(frozen=True)
class ScanRecord:
    """What a scan was asked to be: subject, plans per target, options, device, identity."""

    id: int
    subject: str
    created: str
    status: str
    plans: dict[str, ScanPlan]
    options: dict[str, Any]
    device: dict[str, Any]
    identity: dict[str, Any]
    side: str = SIDES[0]
    test: bool = False


@dataclass(frozen=True)
class Calibration:
    """The calibration data a scan used (its cylinder segments are the scan's)."""

    grid_image: np.ndarray
    board: BoardSpec
    cylinder_mm: float | None
    lift_reference: LiftReference | None = None
    """The cylinder's marks that calibrate the lift (None: the lift is trusted)."""


@dataclass(frozen=True)
class ScanInputs:
    """Everything a scan's reprocessing needs, read from the library (picklable, no handles).

    ``options`` is the processing options its stored result recorded ({} if none).
    """

    scan_id: int
    subject: str
    created: str
    grid_image: np.ndarray
    board: BoardSpec
    cylinder: list[Segment]
    cylinder_mm: float
    segments: list[Segment]
    options: dict[str, Any]
    device: dict[str, Any]
    lift_reference: LiftReference | None = None
    row_turn_deg: float = 0.0
    """The table's turn per image row in its object views (0.0 unless continuous)."""
    laser_off_turn_later: bool = False
    """Its continuous views took their laser-off frames a turn of the count later."""


def no_result_line(scan: ScanRecord) -> str:
    """Return the line saying ``scan`` has no result yet, and what gives it one.

    A scan still acquiring is finished by resuming it; one whose views are all in (its
    processing failed, or never ran) is processed again: resuming it would do no more.
    """
    if scan.status == "acquired":
        return (
            f"scan {scan.id} has no result yet: its views are all in; process it again with "
            f"lamina process {scan.id} [options] (or p on the terminal UI's Library screen)"
        )
    return f"scan {scan.id} has no result yet: finish it with lamina scan --resume {scan.id}"


def check_side(side: str) -> str:
    """Return ``side`` if it is one of :data:`SIDES`, else raise StoreError (one line)."""
    if side not in SIDES:
        raise StoreError(f"limb side {side[:20]!r} must be one of {', '.join(SIDES)}")
    return side


def default_library_path() -> Path:
    """Return ``$XDG_DATA_HOME/lamina/library.sqlite`` (``~/.local/share`` if unset)."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "lamina" / "library.sqlite"


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _segment_blob(segment: Segment) -> bytes:
    """Return the segment's arrays, losslessly: cols u16, rows f32, peak, width, confidence u8.

    A coloured segment appends its r, g, b bytes per point (12 bytes a point in all).
    """
    return b"".join(
        (
            np.ascontiguousarray(segment.cols, "<u2").tobytes(),
            np.ascontiguousarray(segment.rows, "<f4").tobytes(),
            np.ascontiguousarray(segment.peak, "u1").tobytes(),
            np.ascontiguousarray(segment.width, "u1").tobytes(),
            np.ascontiguousarray(segment.confidence, "u1").tobytes(),
            np.ascontiguousarray(segment.colour, "u1").tobytes() if segment.has_colour else b"",
        )
    )


def _segment_from_row(row: sqlite3.Row) -> Segment:
    n, data = row["points"], row["data"]
    # 8 bytes a point before segments carried a confidence (then unknown: zeros), 9 since,
    # 12 with colour.
    if len(data) not in (8 * n, 9 * n, 12 * n):
        raise StoreError(f"stored segment {row['seq']} is damaged: restore the library")
    confidence = np.frombuffer(data, "u1", n, 8 * n).copy() if len(data) >= 9 * n else None
    colour = np.zeros((0, 3), np.uint8)
    if n and len(data) == 12 * n:
        colour = np.frombuffer(data, "u1", 3 * n, 9 * n).reshape(n, 3).copy()
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
        np.zeros(n, np.uint8) if confidence is None else confidence,  # unknown
        colour,
        row["turns"],
    )


def _create_private(path: Path) -> bool:
    """Create ``path`` (and its folder) owner-only; return True if an existing one was widened.

    Nothing here opens the library file itself: POSIX record locks belong to the process,
    so closing any descriptor of the file would drop the locks of every SQLite connection
    this process holds on it (and another process could then checkpoint and delete the
    WAL under them). A new file is made as a private temporary file and hard-linked into
    place (never over an existing one); an existing file and its ``-wal``/``-shm``
    companions readable by others are made owner-only by path.
    """
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    if not os.path.lexists(path):
        _link_new_private(path)
    widened = [tighten(path.with_name(path.name + end)) for end in ("", "-wal", "-shm")]
    return any(widened)


def _link_new_private(path: Path) -> None:
    """Put an empty owner-only file at ``path`` unless something is there already.

    The descriptor opened is the temporary file's, closed before the link exists, so no
    connection can hold a lock on it. Where hard links are not supported (FAT, which has
    no permissions to keep anyway) SQLite creates the file itself.
    """
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)  # 0600
    os.close(fd)
    try:
        os.link(name, path)
    except FileExistsError:
        pass  # another process made it meanwhile: it is SQLite's now
    except OSError:
        pass  # no hard links here
    finally:
        os.unlink(name)


_NOT_DAMAGE = frozenset(
    (
        sqlite3.SQLITE_PERM,
        sqlite3.SQLITE_BUSY,
        sqlite3.SQLITE_LOCKED,
        sqlite3.SQLITE_NOMEM,
        sqlite3.SQLITE_READONLY,
        sqlite3.SQLITE_IOERR,
        sqlite3.SQLITE_FULL,
        sqlite3.SQLITE_CANTOPEN,
        sqlite3.SQLITE_PROTOCOL,
        sqlite3.SQLITE_NOLFS,
        sqlite3.SQLITE_AUTH,
    )
)
"""SQLite's errors that say something about the machine (locks, disk, permissions), not the file."""


def _is_damage(exc: sqlite3.Error) -> bool:
    """Return True if an error met reading a library says the file itself is damaged.

    Not only SQLITE_CORRUPT and SQLITE_NOTADB: a damaged header gives a plain error
    ("unsupported file format").
    """
    code = getattr(exc, "sqlite_errorcode", None)
    return isinstance(code, int) and (code & 0xFF) not in _NOT_DAMAGE


def _legacy_identity(device: dict[str, Any], options: dict[str, Any]) -> dict[str, Any]:
    """Return the identity a schema-1 scan can be given from what it recorded."""
    spawned = None
    if isinstance(options.get("device"), str):
        spawned = spawned_source(
            options["device"],
            options.get("object"),
            options.get("seed"),
            options.get("noise"),
            options.get("rig"),
        )
    return legacy_identity(device, spawned)


class Library(Scoped):
    """The scan library file; a context manager that closes it.

    One :class:`Library` serves every thread of a process (its calls are serialised), so a
    program keeps one open rather than one per step. Each write is one ``BEGIN IMMEDIATE``
    transaction, so a writer in another process is waited for (up to
    :data:`BUSY_TIMEOUT_S`) rather than failed.

    Raises:
        StoreError: the file cannot be opened, was written by a newer Lamina, or is damaged
            (``PRAGMA quick_check``; then nothing is written to it).
    """

    def __init__(self, path: Path | None = None) -> None:
        self.path = Path(path) if path is not None else default_library_path()
        self.notices: list[str] = []
        """Things the user should know once (a library made owner-only)."""
        self._guards: dict[int, tuple[dict[str, Any], dict[str, ScanPlan]]] = {}
        self._lock = threading.RLock()
        try:
            if _create_private(self.path):
                self.notices.append(
                    f"the scan library {self.path} was readable by other users; "
                    "it is now readable by its owner only"
                )
            # Autocommit: every transaction below is begun explicitly (see _write).
            self._db = sqlite3.connect(
                self.path, timeout=BUSY_TIMEOUT_S, isolation_level=None, check_same_thread=False
            )
        except (sqlite3.Error, OSError) as exc:
            raise StoreError(f"cannot open the scan library {self.path}: {exc}") from None
        try:
            self._open()
        except BaseException:
            self._db.close()
            raise

    def _open(self) -> None:
        """Check the file is whole, then set the connection up and bring the schema up to date."""
        self._db.row_factory = sqlite3.Row
        try:
            self._check_intact()
            version = self._db.execute("PRAGMA user_version").fetchone()[0]
            self._refuse_newer(version)
            if self._db.execute("PRAGMA journal_mode").fetchone()[0] != "wal":
                self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=ON")
            if version != SCHEMA_VERSION:
                self._upgrade()
        except sqlite3.Error as exc:
            if _is_damage(exc):
                raise self._damaged(str(exc)) from None
            raise StoreError(f"cannot open the scan library {self.path}: {exc}") from None

    def _check_intact(self) -> None:
        """Refuse a library whose pages are damaged, before anything is written to it.

        ``quick_check`` sees damage to the file's structure (pages, b-trees, overflow chains,
        the header); SQLite keeps no checksum of the data itself.
        """
        problems = [str(row[0]) for row in self._db.execute("PRAGMA quick_check")]
        if problems != ["ok"]:
            lines = [line for text in problems for line in text.splitlines()]
            found = [line for line in lines if line.strip() and not line.startswith("***")]
            raise self._damaged(found[0] if found else "quick_check failed")

    def _damaged(self, problem: str) -> StoreError:
        """Return the one-line refusal of a damaged library file."""
        return StoreError(
            f"the scan library {self.path} is damaged ({' '.join(problem.split())[:120]}): "
            "it was left as it is; restore it from a backup (or name another with --library)"
        )

    def _refuse_newer(self, version: int) -> None:
        if version > SCHEMA_VERSION:
            raise StoreError(
                f"library {self.path} was written by a newer Lamina (schema {version}): "
                "upgrade lamina-host"
            )

    def _upgrade(self) -> None:
        """Create or migrate the schema in one transaction (one opener at a time does it)."""
        with self._write() as db:
            version = db.execute("PRAGMA user_version").fetchone()[0]
            self._refuse_newer(version)
            if version == 1:
                self._migrate_from_1()
            if 1 <= version <= 3:
                self._migrate_side()
            if 1 <= version <= 4:
                self._migrate_test()
            if 1 <= version <= 5:
                self._migrate_lift_reference()
            if 1 <= version <= 6:
                self._migrate_turns()
            for statement in _SCHEMA.split(";"):
                if statement.strip():
                    db.execute(statement)
            db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """Hold the connection for one write transaction, committed when the block ends.

        ``BEGIN IMMEDIATE`` takes the write lock first, so another process's writer is
        waited for; a read upgraded to a write could instead fail at once as busy.
        """
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                if self._db.in_transaction:  # SQLite may have rolled back already
                    self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    def _rows(self, sql: str, parameters: tuple[Any, ...] = ()) -> list[sqlite3.Row]:
        """Return every row of one query (a read of its own)."""
        with self._lock:
            return self._db.execute(sql, parameters).fetchall()

    def _row(self, sql: str, parameters: tuple[Any, ...] = ()) -> sqlite3.Row | None:
        """Return the first row of one query, or None."""
        rows = self._rows(sql, parameters)
        return rows[0] if rows else None

    def _migrate_from_1(self) -> None:
        """Add the scans' identity column, with legacy identities from what they recorded."""
        self._db.execute("ALTER TABLE scans ADD COLUMN identity TEXT NOT NULL DEFAULT '{}'")
        rows = self._db.execute("SELECT id, device, options FROM scans").fetchall()
        for row in rows:
            identity = _legacy_identity(json.loads(row["device"]), json.loads(row["options"]))
            self._db.execute(
                "UPDATE scans SET identity = ? WHERE id = ?", (json.dumps(identity), row["id"])
            )

    def _migrate_side(self) -> None:
        """Add the scans' limb side, ``none`` for every scan already recorded."""
        self._db.execute(
            "ALTER TABLE scans ADD COLUMN side TEXT NOT NULL DEFAULT 'none' "
            "CHECK (side IN ('none', 'left', 'right'))"
        )

    def _migrate_test(self) -> None:
        """Add the scans' test mark, unset for every scan already recorded."""
        self._db.execute(
            "ALTER TABLE scans ADD COLUMN test INTEGER NOT NULL DEFAULT 0 CHECK (test IN (0, 1))"
        )

    def _migrate_lift_reference(self) -> None:
        """Add the calibrations' lift reference (none for scans recorded before it)."""
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(calibrations)")}
        # No table yet (schema 1): the schema below makes it whole. A library marked older
        # than it is may have the column already.
        if columns and "lift_reference" not in columns:
            self._db.execute("ALTER TABLE calibrations ADD COLUMN lift_reference TEXT")

    def _migrate_turns(self) -> None:
        """Add each segment's whole turns (0 for segments recorded before devices sent them:
        their scans are corrected within the turn, as they were)."""
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(segments)")}
        if columns and "turns" not in columns:
            self._db.execute("ALTER TABLE segments ADD COLUMN turns INTEGER NOT NULL DEFAULT 0")

    def leave(self) -> None:
        """Close the file at the end of a ``with`` block."""
        self.close()

    def close(self) -> None:
        """Close the file (after any call another thread is making)."""
        with self._lock:
            self._db.close()

    # --- scans -----------------------------------------------------------------------

    def create_scan(
        self,
        subject: str,
        plans: dict[str, ScanPlan],
        options: dict[str, Any] | None = None,
        device: dict[str, Any] | None = None,
        identity: dict[str, Any] | None = None,
        side: str = SIDES[0],
    ) -> int:
        """Record a new scan of ``subject`` (a pseudonymous code); return its id.

        ``identity`` (:func:`lamina_host.link.identity.scan_identity`) is what acquires it;
        segments are then only accepted under the same identity. ``side`` is the limb
        scanned (:data:`SIDES`).
        """
        try:
            check_subject(subject)
        except InputError as exc:
            raise StoreError(str(exc)) from None
        check_side(side)
        with self._write():
            self._db.execute(
                "INSERT OR IGNORE INTO subjects (code, created) VALUES (?, ?)", (subject, _now())
            )
            (subject_id,) = self._db.execute(
                "SELECT id FROM subjects WHERE code = ?", (subject,)
            ).fetchone()
            cursor = self._db.execute(
                "INSERT INTO scans (subject_id, created, status, device, options, plans, identity, "
                "side) VALUES (?, ?, 'acquiring', ?, ?, ?, ?, ?)",
                (
                    subject_id,
                    _now(),
                    json.dumps(device or {}),
                    json.dumps(options or {}),
                    json.dumps({t: p.to_dict() for t, p in plans.items()}),
                    json.dumps(identity or {}, sort_keys=True),
                    side,
                ),
            )
        assert cursor.lastrowid is not None
        return cursor.lastrowid

    def scan(self, scan_id: int) -> ScanRecord:
        """Return what scan ``scan_id`` was asked to be."""
        row = self._row(
            "SELECT scans.*, subjects.code FROM scans JOIN subjects ON subjects.id = subject_id "
            "WHERE scans.id = ?",
            (scan_id,),
        )
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
            json.loads(row["identity"]),
            row["side"],
            bool(row["test"]),
        )

    def check_identity(self, scan_id: int, identity: dict[str, Any] | None) -> None:
        """Refuse (StoreError, one line) unless ``identity`` is the one scan ``scan_id`` records.

        A scan recorded without an identity accepts only a caller without one.
        """
        recorded = self._guard(scan_id)[0]
        if not recorded and not identity:
            return
        if identity is None:
            raise StoreError(
                f"scan {scan_id} records the device that acquired it: "
                "add to it only through a connected device"
            )
        difference = identity_difference(recorded, identity)
        if difference is not None and count_restarted(recorded, identity):
            raise StoreError(
                f"scan {scan_id} was begun before the device's program last started: its "
                "turntable has no index and counts its angle afresh from wherever the table "
                "stood, so views taken now would not line up with those held; start a new "
                "scan (the views held stay in the library)"
            )
        if difference is not None:
            raise StoreError(
                f"scan {scan_id} was acquired by another device or setup ({difference}): "
                "resume it with the device, object and settings it began with, "
                "or start a new scan"
            )

    def _guard(self, scan_id: int) -> tuple[dict[str, Any], dict[str, ScanPlan]]:
        """Return the scan's recorded identity and plans (they never change; kept)."""
        if scan_id not in self._guards:
            record = self.scan(scan_id)
            self._guards[scan_id] = (record.identity, record.plans)
        return self._guards[scan_id]

    def scans(self, subject: str | None = None) -> list[ScanSummary]:
        """Return every scan (of the subject code ``subject`` only, if given), oldest first."""
        where, parameters = ("WHERE code = ? ", (subject,)) if subject is not None else ("", ())
        rows = self._rows(
            "SELECT scans.id, code, scans.created, status, plans, side, test, "
            "(SELECT COUNT(*) FROM segments WHERE scan_id = scans.id AND target = 'object') "
            "AS received, (SELECT COUNT(*) FROM results WHERE scan_id = scans.id) AS results "
            f"FROM scans JOIN subjects ON subjects.id = subject_id {where}ORDER BY scans.id",
            parameters,
        )
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
                    row["side"],
                    bool(row["test"]),
                )
            )
        return out

    def set_side(self, scan_id: int, side: str) -> None:
        """Record which limb scan ``scan_id`` is (:data:`SIDES`)."""
        check_side(side)
        self.scan(scan_id)
        with self._write():
            self._db.execute("UPDATE scans SET side = ? WHERE id = ?", (side, scan_id))

    def set_test(self, scan_id: int, test: bool = True) -> None:
        """Mark scan ``scan_id`` as a test scan (or, ``test=False``, as a visit again).

        A test scan (a phantom, a calibration check, a trial run under a subject's code)
        stays in the library with everything it recorded, but is left out of the subject's
        trend and refused as the scan a report compares with.

        Raises:
            StoreError: there is no such scan.
        """
        self.scan(scan_id)
        with self._write():
            self._db.execute("UPDATE scans SET test = ? WHERE id = ?", (int(test), scan_id))

    def set_status(self, scan_id: int, status: str) -> None:
        """Set the scan's status (one of :data:`STATUSES`)."""
        if status not in STATUSES:
            raise ValueError(f"unknown scan status {status!r}")
        with self._write():
            self._db.execute("UPDATE scans SET status = ? WHERE id = ?", (status, scan_id))

    def delete_scan(self, scan_id: int) -> None:
        """Remove a scan and everything recorded for it (its subject stays)."""
        self.scan(scan_id)
        with self._write():
            self._db.execute("DELETE FROM scans WHERE id = ?", (scan_id,))
        self._guards.pop(scan_id, None)  # SQLite may give a later scan the same id

    # --- segments --------------------------------------------------------------------

    def add_segment(
        self, scan_id: int, seq: int, segment: Segment, identity: dict[str, Any] | None = None
    ) -> bool:
        """Commit segment ``seq`` (its plan index) of ``segment.target``; False if already held.

        Raises:
            StoreError: ``identity`` is not the scan's, or the segment is not view ``seq``
                of the scan's plan for its target.
        """
        self.check_identity(scan_id, identity)
        plan = self._guard(scan_id)[1].get(segment.target)
        labels = (segment.section, segment.z_mm, segment.angle_deg)
        if plan is None or not plan.labels(seq, *labels):
            raise StoreError(
                f"segment {seq} of {segment.target} is not a view scan {scan_id} planned: "
                "it is not stored"
            )
        with self._write():
            cursor = self._db.execute(
                "INSERT OR IGNORE INTO segments (scan_id, target, seq, section, view, z_mm, "
                "angle_deg, turns, points, data) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    scan_id,
                    segment.target,
                    seq,
                    segment.section,
                    segment.view,
                    segment.z_mm,
                    segment.angle_deg,
                    segment.turns,
                    len(segment),
                    _segment_blob(segment),
                ),
            )
        return cursor.rowcount == 1

    def held(self, scan_id: int, target: str) -> set[int]:
        """Return the plan indices of ``target`` already stored for the scan."""
        rows = self._rows(
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
        return list(self.held_segments(scan_id, target).values())

    def held_segments(self, scan_id: int, target: str) -> dict[int, Segment]:
        """Return the stored segments of ``target`` by plan index, in plan order (one read)."""
        rows = self._rows(
            "SELECT * FROM segments WHERE scan_id = ? AND target = ? ORDER BY seq",
            (scan_id, target),
        )
        return {row["seq"]: _segment_from_row(row) for row in rows}

    # --- calibration and results -----------------------------------------------------

    def save_calibration(
        self,
        scan_id: int,
        grid_image: np.ndarray,
        board: BoardSpec,
        cylinder_mm: float | None,
        identity: dict[str, Any] | None = None,
        lift_reference: LiftReference | None = None,
    ) -> None:
        """Store the calibration board image and geometry the scan uses (under its identity),
        with the calibration cylinder's lift reference when the device has one."""
        self.check_identity(scan_id, identity)
        ok, png = cv2.imencode(".png", grid_image)
        if not ok:
            raise StoreError("the calibration image could not be encoded")
        reference = json.dumps(lift_reference.to_dict()) if lift_reference else None
        with self._write():
            self._db.execute(
                "INSERT OR REPLACE INTO calibrations (scan_id, created, board, grid_png, "
                "cylinder_mm, lift_reference) VALUES (?, ?, ?, ?, ?, ?)",
                (scan_id, _now(), json.dumps(board.to_dict()), png.tobytes(), cylinder_mm,
                 reference),
            )  # fmt: skip

    def calibration(self, scan_id: int) -> Calibration | None:
        """Return the scan's calibration data, or None if it has none yet."""
        row = self._row("SELECT * FROM calibrations WHERE scan_id = ?", (scan_id,))
        if row is None:
            return None
        image = cv2.imdecode(np.frombuffer(row["grid_png"], np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise StoreError(f"the calibration image of scan {scan_id} is damaged")
        board = BoardSpec.from_dict(json.loads(row["board"]))
        reference = row["lift_reference"]
        try:
            lift = LiftReference.from_dict(json.loads(reference)) if reference else None
        except (KeyError, TypeError, ValueError) as exc:
            raise StoreError(f"the lift reference of scan {scan_id} is damaged ({exc})") from None
        return Calibration(image, board, row["cylinder_mm"], lift)

    def inputs(self, scan_id: int) -> ScanInputs:
        """Return what reprocessing scan ``scan_id`` needs, each target's segments with
        their turns counted from its own first (:func:`~lamina_shared.types.from_first_turn`).

        Raises:
            StoreError: no such scan, or it lacks its calibration or the cylinder diameter.
        """
        record = self.scan(scan_id)
        calibration = self.calibration(scan_id)
        if calibration is None or calibration.cylinder_mm is None:
            raise StoreError(
                f"scan {scan_id} has no complete calibration: finish it with "
                f"lamina scan --resume {scan_id}"
            )
        report = self.result(scan_id) or {}
        return ScanInputs(
            scan_id,
            record.subject,
            record.created,
            calibration.grid_image,
            calibration.board,
            from_first_turn(self.segments(scan_id, "cylinder")),
            float(calibration.cylinder_mm),
            from_first_turn(self.segments(scan_id, "object")),
            dict(report.get("options", {})),
            dict(record.device),
            calibration.lift_reference,
            row_turn_deg(record.identity, record.plans.get("object")),
            laser_off_turn_later(record.identity, record.plans.get("object")),
        )

    def save_result(self, scan_id: int, report: dict[str, Any], files: dict[str, Path]) -> None:
        """Store the processing report and output files (replacing earlier ones)."""
        blobs = {name: Path(path).read_bytes() for name, path in files.items()}
        with self._write():
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
        found = self._row("SELECT report FROM results WHERE scan_id = ?", (scan_id,))
        return json.loads(found[0]) if found else None

    def _result_file(self, scan_id: int, name: str) -> bytes | None:
        row = self._row(
            "SELECT data FROM result_files WHERE scan_id = ? AND name = ?", (scan_id, name)
        )
        return bytes(row[0]) if row else None

    def result_mesh(self, scan_id: int) -> bytes:
        """Return the scan's stored mesh (PLY bytes).

        Raises:
            StoreError: the scan has no result, or its result has no mesh.
        """
        scan = self.scan(scan_id)
        if self.result(scan_id) is None:
            raise StoreError(no_result_line(scan))
        return self._stored_mesh(scan_id)

    def _stored_mesh(self, scan_id: int) -> bytes:
        """Return the mesh of a scan known to have a result (StoreError: it made none)."""
        mesh = self._result_file(scan_id, "mesh.ply")
        if mesh is None:
            raise StoreError(f"scan {scan_id} produced no mesh to export")
        return mesh

    def export(self, scan_id: int, path: Path) -> Path:
        """Write the scan's result to ``path``: mesh as PLY/OBJ/STL by extension, or the report.

        Raises:
            StoreError: unknown extension, existing file, or a scan without that result.
        """
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix not in EXPORT_FORMATS:
            raise unknown_format(path, EXPORT_FORMATS)
        check_new_file(path)
        scan = self.scan(scan_id)
        report = self.result(scan_id)
        if report is None:
            raise StoreError(no_result_line(scan))
        if suffix == ".json":
            data = json_text(report).encode()  # strict JSON, also of a report stored with NaN
        else:
            data = _convert_mesh(self._stored_mesh(scan_id), suffix)
        return self.write_export(scan_id, path, data)

    def write_export(self, scan_id: int, path: Path, data: bytes) -> Path:
        """Write ``data`` to the new file ``path`` (0600) and record it as an export of the scan.

        Raises:
            StoreError: the file exists or cannot be written.
        """
        try:
            write_new_file(path, data)
        except OutputError as exc:
            raise StoreError(str(exc)) from None
        with self._write():
            self._db.execute(
                "INSERT INTO exports (scan_id, created, format, path) VALUES (?, ?, ?, ?)",
                (scan_id, _now(), path.suffix.lower().lstrip("."), str(path.resolve())),
            )
        return path


def check_new_file(path: Path) -> None:
    """Refuse (StoreError, one line) an export path that cannot be new (:func:`new_file_problem`),
    before the export's data is made."""
    if problem := new_file_problem(path):
        raise StoreError(problem)


def _convert_mesh(ply: bytes, suffix: str) -> bytes:
    """Return a stored PLY mesh in the format ``suffix`` names (.ply, .obj or .stl)."""
    if suffix == ".ply":
        return ply
    vertices, faces, colours = load_coloured_ply(ply)
    if suffix == ".obj":
        return obj_bytes(vertices, faces, colours)  # vertex colours kept
    return stl_bytes(vertices, faces)  # numpy only: no MeshLab needed
