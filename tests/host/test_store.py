"""The scan library: SQLite in WAL mode, owner-only, every segment exactly once."""

from __future__ import annotations

import json
import sqlite3
import stat
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pymeshlab
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lamina_host.reconstruct.mesh import save_ply
from lamina_host.store.library import (
    SCHEMA_VERSION,
    Library,
    StoreError,
    default_library_path,
)
from lamina_shared.types import BoardSpec, ScanPlan, Segment

PLANS = {"cylinder": ScanPlan.regular(1, 2.0, 4), "object": ScanPlan.regular(3, 2.0, 4)}
BOARD = BoardSpec((9, 7), 3.0, (-12.0, -9.0))


def segment(seq: int, target: str = "object", n: int = 50) -> Segment:
    rng = np.random.default_rng(seq)
    view = PLANS[target].views[seq]
    return Segment(
        target,
        view.section,
        seq % 4,
        view.z_mm,
        view.angle_deg,
        np.sort(rng.choice(640, n, replace=False)).astype(np.uint16),
        (rng.integers(0, 480 * 64, n) / 64).astype(np.float32),
        rng.integers(0, 256, n).astype(np.uint8),
        rng.integers(1, 20, n).astype(np.uint8),
    )


@pytest.fixture
def library(tmp_path):
    with Library(tmp_path / "lib" / "library.sqlite") as lib:
        yield lib


def test_file_is_private_and_in_wal_mode(library, tmp_path):
    library.create_scan("S-01", PLANS)
    path = tmp_path / "lib" / "library.sqlite"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    wal = path.with_name(path.name + "-wal")
    assert wal.exists() and stat.S_IMODE(wal.stat().st_mode) == 0o600
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_default_path_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))
    assert default_library_path() == tmp_path / "lamina" / "library.sqlite"
    monkeypatch.delenv("XDG_DATA_HOME")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert default_library_path() == tmp_path / ".local/share/lamina/library.sqlite"


def test_segments_are_stored_once_exactly_and_missing_ones_known(library):
    scan_id = library.create_scan("S-01", PLANS, {"seed": 3})
    for seq in (4, 0, 7):
        assert library.add_segment(scan_id, seq, segment(seq))
    assert not library.add_segment(scan_id, 4, segment(4))  # a retransmission
    assert library.held(scan_id, "object") == {0, 4, 7}
    assert library.missing(scan_id, "object") == [1, 2, 3, 5, 6, 8, 9, 10, 11]
    got = library.segments(scan_id, "object")
    assert [s.section for s in got] == [0, 1, 1]
    for seq, s in zip((0, 4, 7), got, strict=True):
        assert s.same_as(segment(seq))
    assert library.scan(scan_id).options == {"seed": 3}
    assert library.scan(scan_id).plans == PLANS


def test_a_second_connection_sees_committed_segments(library):
    scan_id = library.create_scan("S-01", PLANS)
    library.add_segment(scan_id, 2, segment(2))
    with Library(library.path) as other:
        assert other.held(scan_id, "object") == {2}


def test_listing_calibration_result_export_and_delete(library, tmp_path):
    first = library.create_scan("S-01", PLANS)
    second = library.create_scan("S-02", PLANS)
    for seq in range(12):
        library.add_segment(second, seq, segment(seq))
    grid = np.random.default_rng(0).integers(0, 255, (48, 64)).astype(np.uint8)
    library.save_calibration(second, grid, BOARD, 19.05)
    calibration = library.calibration(second)
    assert calibration is not None
    assert np.array_equal(calibration.grid_image, grid) and calibration.board == BOARD
    assert library.calibration(first) is None

    out = tmp_path / "out"
    out.mkdir()
    vertices = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], float)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    save_ply(out / "mesh.ply", vertices, faces)
    (out / "report.json").write_text(json.dumps({"mesh": {"faces": 4}}))
    files = {"mesh.ply": out / "mesh.ply", "report.json": out / "report.json"}
    library.save_result(second, {"mesh": {"faces": 4}}, files)
    summaries = library.scans()
    assert [(s.id, s.subject, s.status, s.sections, s.views, s.received, s.has_result)
            for s in summaries] == [
        (first, "S-01", "acquiring", 3, 12, 0, False),
        (second, "S-02", "processed", 3, 12, 12, True),
    ]  # fmt: skip

    for name in ("m.ply", "m.obj", "m.stl"):
        library.export(second, tmp_path / name)
        meshes = pymeshlab.MeshSet()
        meshes.load_new_mesh(str(tmp_path / name))
        assert meshes.current_mesh().face_number() == 4, name
        assert np.allclose(np.sort(meshes.current_mesh().vertex_matrix(), 0), np.sort(vertices, 0))
    library.export(second, tmp_path / "report.json")
    assert json.loads((tmp_path / "report.json").read_text()) == {"mesh": {"faces": 4}}
    with pytest.raises(StoreError, match="already exists"):
        library.export(second, tmp_path / "m.ply")
    with pytest.raises(StoreError, match=r"\.ply, \.obj, \.stl"):
        library.export(second, tmp_path / "m.xyz")
    with pytest.raises(StoreError, match="no result yet"):
        library.export(first, tmp_path / "other.ply")

    library.delete_scan(second)
    assert [s.id for s in library.scans()] == [first]
    assert library.segments(second, "object") == []
    with pytest.raises(StoreError, match="no scan"):
        library.scan(second)


def test_newer_library_is_refused(tmp_path):
    path = tmp_path / "library.sqlite"
    with sqlite3.connect(path) as db:
        db.execute("PRAGMA user_version=99")
    with pytest.raises(StoreError, match="newer Lamina"):
        Library(path)


def lamina(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "lamina_host", *args], capture_output=True, text=True, timeout=60
    )


def test_cli_lists_and_refuses_with_one_line(tmp_path):
    path = tmp_path / "library.sqlite"
    with Library(path) as library:
        library.create_scan("S-07", PLANS)
    listing = lamina("scans", "--library", str(path))
    assert listing.returncode == 0
    assert "S-07" in listing.stdout and "acquiring" in listing.stdout and "0/12" in listing.stdout
    refused = lamina("export", "1", "-o", str(tmp_path / "x.ply"), "--library", str(path))
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    assert refused.stderr.strip().splitlines() == [
        "lamina: scan 1 has no result yet: finish it with lamina scan --resume 1"
    ]
    with Library(path) as library:
        library.set_status(1, "acquired")  # every view in, its processing failed
    for argv in (
        ["export", "1", "-o", str(tmp_path / "x.stl")],
        ["report", "1", "-o", str(tmp_path / "r.pdf")],
    ):
        refused = lamina(*argv, "--library", str(path))
        assert refused.returncode == 2 and "Traceback" not in refused.stderr
        assert refused.stderr.strip().splitlines() == [
            "lamina: scan 1 has no result yet: its views are all in; process it again with "
            "lamina process 1 [options] (or p on the terminal UI's Library screen)"
        ], argv


def test_a_schema_2_library_gains_a_side_per_scan_and_loses_nothing(tmp_path):
    """Opening a schema-2 library adds side ``none`` to every scan; segments stay intact."""
    path = tmp_path / "library.sqlite"
    with Library(path) as lib:
        first = lib.create_scan("P-01", PLANS)
        lib.add_segment(first, 0, segment(0))
        second = lib.create_scan("P-01", PLANS)
    with sqlite3.connect(path) as db:  # back to schema 2: no side or test column
        db.execute("ALTER TABLE scans DROP COLUMN test")
        db.execute("ALTER TABLE scans DROP COLUMN side")
        db.execute("PRAGMA user_version=2")
        before = [tuple(r) for r in db.execute("SELECT * FROM scans ORDER BY id")]
        held = db.execute("SELECT data FROM segments").fetchall()
    with Library(path) as lib:
        assert [(s.id, s.side) for s in lib.scans()] == [(first, "none"), (second, "none")]
        assert lib.scan(first).side == "none"
        kept = lib.segments(first, "object")
        assert len(kept) == 1 and np.array_equal(kept[0].rows, segment(0).rows)
        lib.set_side(second, "right")
        third = lib.create_scan("P-01", PLANS, side="left")
        assert [s.side for s in lib.scans()] == ["none", "right", "left"]
        with pytest.raises(StoreError, match="must be one of none, left, right"):
            lib.create_scan("P-01", PLANS, side="both")
        with pytest.raises(StoreError, match="no scan"):
            lib.set_side(99, "left")
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        after = [tuple(r)[:-2] for r in db.execute("SELECT * FROM scans WHERE id < ?", (third,))]
        assert after == before
        assert db.execute("SELECT data FROM segments").fetchall() == held


def test_a_schema_4_library_gains_the_test_mark_and_loses_nothing(tmp_path):
    """Opening a schema-4 library adds the test mark, unset, to every scan (sides, segments
    and results kept); a scan can then be marked as a test and unmarked, by the library's
    own method (the one the terminal UI's Library screen calls)."""
    path = tmp_path / "library.sqlite"
    with Library(path) as lib:
        first = lib.create_scan("P-01", PLANS, side="left")
        lib.add_segment(first, 0, segment(0))
        lib.save_result(first, {"volume": 1.0}, {})
        second = lib.create_scan("P-02", PLANS, side="right")
    with sqlite3.connect(path) as db:  # back to schema 4: no test column
        db.execute("ALTER TABLE scans DROP COLUMN test")
        db.execute("PRAGMA user_version=4")
        before = [tuple(r) for r in db.execute("SELECT * FROM scans ORDER BY id")]
    with Library(path) as lib:
        assert [(s.id, s.side, s.test) for s in lib.scans()] == [
            (first, "left", False), (second, "right", False)
        ]  # fmt: skip
        assert lib.result(first) == {"volume": 1.0} and len(lib.segments(first, "object")) == 1
        lib.set_test(first)
        assert lib.scan(first).test and [s.test for s in lib.scans()] == [True, False]
        assert [s.id for s in lib.scans(subject="P-02")] == [second]
        assert lib.scans(subject="P-99") == []
        lib.set_test(first, False)
        assert not lib.scan(first).test
        with pytest.raises(StoreError, match="no scan"):
            lib.set_test(99)
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        assert [tuple(r)[:-1] for r in db.execute("SELECT * FROM scans ORDER BY id")] == before


def test_a_schema_6_library_gains_segment_turns_and_loses_nothing(tmp_path):
    """Opening a schema-6 library gives every segment turn 0 (recorded before devices sent
    them: corrected within the turn, as they were), keeps its points bit for bit, and
    stores the turns of segments added after."""
    path = tmp_path / "library.sqlite"
    with Library(path) as lib:
        scan = lib.create_scan("P-01", PLANS)
        lib.add_segment(scan, 0, segment(0))
    with sqlite3.connect(path) as db:  # back to schema 6: no turns column
        db.execute("ALTER TABLE segments DROP COLUMN turns")
        db.execute("PRAGMA user_version=6")
        held = db.execute("SELECT data FROM segments").fetchall()
    with Library(path) as lib:
        (kept,) = lib.segments(scan, "object")
        assert kept.turns == 0 and kept.same_as(segment(0))
        later = replace(segment(1), turns=41)
        lib.add_segment(scan, 1, later)
        assert lib.segments(scan, "object")[1].same_as(later)
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        assert db.execute("SELECT data FROM segments WHERE seq = 0").fetchall() == held


def test_cli_marks_a_test_scan_and_lists_one_subject(tmp_path):
    """``lamina scans --set-test N`` marks it (listed as test), ``--unset-test N`` unmarks
    it, ``--subject CODE`` lists one subject's scans; a scan given both is one line."""
    path = tmp_path / "library.sqlite"
    with Library(path) as lib:
        lib.create_scan("P-02", PLANS)
        lib.create_scan("P-03", PLANS)
    done = lamina("scans", "--library", str(path), "--set-test", "1")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].rstrip().endswith("result  test")
    assert lines[1].rstrip().endswith("test") and not lines[2].rstrip().endswith("test")
    one = lamina("scans", "--library", str(path), "--subject", "P-03", "--unset-test", "1")
    assert one.returncode == 0 and len(one.stdout.splitlines()) == 2 and "P-02" not in one.stdout
    with Library(path) as lib:
        assert not lib.scan(1).test
    both = lamina("scans", "--library", str(path), "--set-test", "2", "--unset-test", "2")
    assert both.returncode == 2 and len(both.stderr.strip().splitlines()) == 1
    missing = lamina("scans", "--library", str(path), "--set-test", "9")
    assert missing.returncode == 2 and "no scan 9" in missing.stderr


def test_cli_sets_and_lists_the_side(tmp_path):
    """``lamina scans --set-side SCAN SIDE`` records it; a bad side is one line."""
    path = tmp_path / "library.sqlite"
    with Library(path) as lib:
        scan_id = lib.create_scan("P-02", PLANS)
    done = lamina("scans", "--library", str(path), "--set-side", str(scan_id), "left")
    assert done.returncode == 0, done.stderr
    assert "P-02         left" in done.stdout
    bad = lamina("scans", "--library", str(path), "--set-side", str(scan_id), "both")
    assert bad.returncode != 0 and len(bad.stderr.strip().splitlines()) == 1
    assert "must be one of" in bad.stderr


def test_lamina_scan_records_the_side_it_is_given(scanned_library):
    """``lamina scan --side left`` (the shared scanned library) stores side left."""
    with Library(scanned_library) as lib:
        assert lib.scan(1).side == "left"
        assert [s.side for s in lib.scans()] == ["left"]


def _count_in_another_process(path) -> int:
    """Return the object segments another process finds in the library (opened read-write)."""
    code = (
        "import sqlite3, sys\n"
        "db = sqlite3.connect(sys.argv[1], timeout=30)\n"
        "print(db.execute(\"SELECT COUNT(*) FROM segments WHERE target='object'\").fetchone()[0])\n"
        "db.close()\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True
    )
    return int(done.stdout)


def test_a_second_library_in_one_process_keeps_the_first_ones_locks(tmp_path):
    """Issue 19: opening the file outside SQLite dropped this process's locks on it, so another
    process's last close deleted the WAL under the open connection and later commits were lost."""
    path = tmp_path / "library.sqlite"
    with Library(path) as first:
        scan_id = first.create_scan("S-01", PLANS)
        first.add_segment(scan_id, 0, segment(0))
        with Library(path) as second:
            assert second.held(scan_id, "object") == {0}
        # A reader in another process comes and goes: its close must not take the WAL away.
        assert _count_in_another_process(path) == 1
        first.add_segment(scan_id, 1, segment(1))
        assert _count_in_another_process(path) == 2
    assert _count_in_another_process(path) == 2


def _fill(path) -> dict[int, tuple[str, dict[int, Segment]]]:
    """Write two scans whose segments span pages (overflow pages too); return what was written."""
    written = {}
    with Library(path) as library:
        for k, subject in enumerate(("S-01", "S-02")):
            scan_id = library.create_scan(subject, PLANS)
            segments = {seq: segment(seq, n=300 + 300 * k) for seq in range(12)}
            for seq, s in segments.items():
                library.add_segment(scan_id, seq, s)
            written[scan_id] = (subject, segments)
    return written


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    path = tmp_path_factory.mktemp("pristine") / "library.sqlite"
    written = _fill(path)
    return path.read_bytes(), written


def _damage(data: bytes, kind: str, where: float, seed: int) -> bytes:
    """Return ``data`` with one 4096-byte page overwritten, or cut short, or its header hit."""
    rng = np.random.default_rng(seed)
    pages = len(data) // 4096
    page = min(int(where * pages), pages - 1)
    if kind == "truncated":
        return data[: max(page, 1) * 4096]
    if kind == "header":  # the database header's sizes and counts (bytes 16-99)
        start = 16 + int(where * 80)
        return data[:start] + rng.integers(0, 256, 4, np.uint8).tobytes() + data[start + 4 :]
    fill = bytes(4096) if kind == "zeroed" else rng.integers(0, 256, 4096, np.uint8).tobytes()
    return data[: page * 4096] + fill + data[(page + 1) * 4096 :]


@settings(max_examples=40, deadline=None)
@given(
    # Not a zeroed overflow page: SQLite keeps no checksum of the data, so a blob's zeroed
    # tail is unseen (README). Not a file cut to nothing: that is a new, empty library.
    kind=st.sampled_from(["random", "truncated", "header"]),
    where=st.floats(0, 1, exclude_max=True),
    seed=st.integers(0, 2**32 - 1),
)
def test_a_damaged_library_is_refused_untouched_or_reads_back_whole(pristine, kind, where, seed):
    """Issue 19: a library with damaged pages listed "no scans"; now opening it either refuses
    in one line and leaves the file as it was, or every scan and segment reads back exactly."""
    data, written = pristine
    damaged = _damage(data, kind, where, seed)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "library.sqlite"
        path.write_bytes(damaged)
        path.chmod(0o600)
        try:
            library = Library(path)
        except StoreError as exc:
            assert path.read_bytes() == damaged
            assert "\n" not in str(exc)
            if "newer Lamina" in str(exc):  # the header's user_version was hit
                return
            assert f"the scan library {path} is damaged (" in str(exc)
            assert "restore it from a backup" in str(exc)
            return
        with library:
            assert [(s.id, s.subject) for s in library.scans()] == [
                (k, subject) for k, (subject, _) in written.items()
            ]
            for scan_id, (_, segments) in written.items():
                held = library.held_segments(scan_id, "object")
                assert held.keys() == segments.keys()
                assert all(held[seq].same_as(s) for seq, s in segments.items())


def test_cli_refuses_a_damaged_library_in_one_line_and_leaves_it(pristine, tmp_path):
    """Issue 19: ``lamina scans`` said "no scans" (exit 0) and ``export`` "there is no scan 1"
    on a library with damaged pages."""
    data, _ = pristine
    path = tmp_path / "library.sqlite"
    damaged = _damage(data, "random", 0.3, 7)
    path.write_bytes(damaged)
    for args in (("scans",), ("export", "1", "-o", str(tmp_path / "m.ply"))):
        done = lamina(*args, "--library", str(path))
        assert done.returncode == 2 and done.stdout == "", args
        (line,) = done.stderr.strip().splitlines()
        assert line.startswith(f"lamina: the scan library {path} is damaged (")
        assert line.endswith("restore it from a backup (or name another with --library)")
        assert path.read_bytes() == damaged
    assert not (tmp_path / "m.ply").exists()


def test_processes_creating_one_new_library_at_once_all_succeed_and_keep_it_private(tmp_path):
    path = tmp_path / "new" / "library.sqlite"
    code = (
        "import sys\n"
        "from lamina_host.store.library import Library\n"
        "from lamina_shared.types import ScanPlan\n"
        "with Library(sys.argv[1]) as library:\n"
        "    library.create_scan(sys.argv[2], {'object': ScanPlan.regular(1, 2.0, 4)})\n"
    )
    runs = [
        subprocess.Popen([sys.executable, "-c", code, str(path), f"S-{k}"], stderr=subprocess.PIPE)
        for k in range(4)
    ]
    errors = [run.communicate(timeout=120)[1] for run in runs]
    assert [run.returncode for run in runs] == [0] * 4, errors
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left
    with Library(path) as library:
        assert sorted(s.subject for s in library.scans()) == ["S-0", "S-1", "S-2", "S-3"]


READING_COMMANDS = [
    ["scans"],
    ["scans", "--set-test", "1"],
    ["process", "1"],
    ["export", "1", "-o", "out.stl"],
    ["report", "1", "-o", "report.pdf"],
    ["batch", "--subjects", "P-01", "--measure", "-o", "table.csv"],
    ["send", "1", "--to", "ORTHANC@localhost:4242"],
]


@pytest.mark.parametrize("argv", READING_COMMANDS, ids=lambda argv: "-".join(argv[:2]))
def test_a_command_that_reads_refuses_a_missing_library_and_makes_none(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A mistyped ``--library`` is named in one line, exit 2; no empty library (nor its
    folder) is left behind, which a later ``lamina scans`` would list as having no scans."""
    from lamina_host.cli import main

    missing = tmp_path / "typo" / "library.sqlite"
    assert main([*argv, "--library", str(missing)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"lamina: there is no scan library at {missing}: check the --library path "
        "(lamina scan makes the library the first time it records into it)"
    ]
    assert not missing.parent.exists()


def test_lamina_scans_on_a_new_machine_lists_nothing_and_makes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before the first scan the default library is not there: listing says so (exit 0),
    a change asked of a scan is refused (exit 2), and neither makes the library."""
    from lamina_host.cli import main

    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    default = tmp_path / "data" / "lamina" / "library.sqlite"
    assert main(["scans"]) == 0
    assert capsys.readouterr().out.strip() == (
        f"no scans yet: the scan library {default} is made by lamina scan"
    )
    assert main(["scans", "--set-side", "1", "left"]) == 2
    assert capsys.readouterr().err.strip() == (
        f"lamina: there is no scan library at {default} yet: nothing has been scanned here "
        "(lamina scan makes it; --library names a library elsewhere)"
    )
    assert not (tmp_path / "data").exists()
