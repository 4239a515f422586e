"""A careless user and an attacker against the host (issue #11, "Trust").

Each test tries a whole class of mistake or attack, not one example: a scan resumed by
anything but what began it, numbers that are zero, negative or not finite, subject codes
holding escapes or names, output paths that are files, links or unwritable, a damaged
library, a device program that dies. The real CLI runs through ``main()`` (or as a
process where it must be killed), with a real SQLite library and a simulated device on
a real pseudo-terminal link. Every refusal must be one line, exit status 2, and change
nothing already recorded.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import sqlite3
import stat
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import serial

from lamina_device.server import DeviceServer, ServerSettings
from lamina_host import cli
from lamina_host.link import client as link
from lamina_host.link.client import DeviceClient
from lamina_host.link.connect import open_device
from lamina_host.link.errors import DeviceError
from lamina_host.link.identity import identity_difference, legacy_identity, scan_identity
from lamina_host.link.spawn import PtyBridge
from lamina_host.store.library import SCHEMA_VERSION, Library, StoreError
from lamina_host.store.outputs import load_segments
from lamina_host.ui.tui.adapter import UserError, parse_plan
from lamina_host.workflow import check_plan_limits
from lamina_host.workflow.job import DeviceTarget, ScanJob, ScanRequest
from lamina_shared.errors import InputError, printable
from lamina_shared.limits import DeviceLimits
from lamina_shared.link import Channel
from lamina_shared.messages import Welcome
from lamina_shared.protocol import PROTOCOL_VERSION, ROW_SCALE
from lamina_shared.types import ScanPlan, Segment
from tests.helpers.cli import device_command, host_command
from tests.helpers.library import held_segments
from tests.helpers.served import link as served_link

OBJECT = "cylinder:d=19.05"
PLAN = ScanPlan.regular(2, 2.0, 8)
HELD = 4
"""Object views the interrupted scan holds."""


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """Run the CLI in this process; return (status, stdout, stderr)."""
    status = cli.main(list(argv))
    out, err = capsys.readouterr()
    return status, out, err


def one_line(status: int, err: str) -> str:
    """Assert a clean refusal: status 2, no traceback, one line on stderr; return it."""
    assert status == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("lamina: ")
    return lines[0]


def refused(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """Run the CLI; assert it refused cleanly in one line and return the line."""
    status, _, err = run(capsys, *argv)
    return one_line(status, err)


def dump(path: Path) -> list[str]:
    """Return everything the library holds, as SQL."""
    with sqlite3.connect(path) as db:
        return list(db.iterdump())


def scan_count(path: Path) -> int:
    if not path.exists():
        return 0
    with Library(path) as library:
        return len(library.scans())


def tree(folder: Path) -> dict[str, bytes]:
    """Return the files under ``folder`` with their contents."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def interrupted_scan(path: Path, out: Path, options: dict[str, Any]) -> None:
    """Record scan 1 as ``lamina scan --device sim --object OBJECT`` left it when cut off.

    It holds its calibration and the first ``HELD`` object views, stored under the
    identity of the device that acquired them.
    """
    with open_device("sim", OBJECT) as client, Library(path) as library:
        identity = client.identity()
        plans = {"cylinder": client.plan_for("cylinder", None), "object": PLAN}
        device = {"software": client.info.software, "hardware": client.info.hardware}
        scan_id = library.create_scan("P-01", plans, options, device, identity)
        grid, board = client.grab_grid()
        library.save_calibration(scan_id, grid, board, 19.05, identity)
        client.scan(
            "object",
            PLAN,
            have=range(HELD, len(PLAN.views)),
            on_segment=lambda seq, s: library.add_segment(scan_id, seq, s, identity),
        )
    out.mkdir()


@pytest.fixture(scope="module")
def partial(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A library whose scan 1 recorded only its device and folder (as the TUI records)."""
    folder = tmp_path_factory.mktemp("partial")
    interrupted_scan(folder / "library.sqlite", folder / "out", {"device": "sim"})
    return folder


@pytest.fixture
def library_copy(partial: Path, tmp_path: Path) -> tuple[Path, Path]:
    """A private copy of the interrupted scan's library, and its (empty) output folder."""
    path, out = tmp_path / "library.sqlite", tmp_path / "out"
    shutil.copy(partial / "library.sqlite", path)
    out.mkdir()
    with sqlite3.connect(path) as db:
        db.execute(
            "UPDATE scans SET options = ?", (json.dumps({"device": "sim", "out": str(out)}),)
        )
    return path, out


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small recorded capture of another object, for a replay device."""
    out = tmp_path_factory.mktemp("capture") / "sphere"
    plan = ["--object", "sphere:d=25", "--sections", "2", "--views", "8", "--cylinder-views", "8"]
    subprocess.run(
        device_command("record", "--hardware", "sim", "--out", str(out), *plan),
        check=True,
        capture_output=True,
        timeout=300,
    )
    return out


# --- 1. scan identity -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("other", "differs"),
    [
        (["--object", "sphere:d=25"], "source"),
        (["--seed", "5"], "source"),
        (["--noise", "none"], "source"),
        (["--rig", "limb"], "source"),
        (["--device", "replay:CAPTURE"], "hardware"),
    ],
)
def test_resume_by_another_device_or_setup_is_refused_and_changes_nothing(
    capsys, library_copy, capture, other, differs
):
    path, out = library_copy
    before = dump(path)
    argv = ["scan", "--device", "sim", "--library", str(path), "--resume", "1"]
    if other[0] == "--device":
        argv[2] = f"replay:{capture}"
    else:
        argv += other
    line = refused(capsys, *argv)
    assert "scan 1 was acquired by another device or setup" in line and differs in line
    assert dump(path) == before
    assert tree(out) == {}


def test_resume_by_the_same_device_completes_the_scan(capsys, library_copy):
    path, out = library_copy
    status, _, err = run(
        capsys,
        "scan",
        "--device",
        "sim",
        "--object",
        OBJECT,
        "--library",
        str(path),
        "--resume",
        "1",
    )
    assert status == 0, err
    assert f"object: {HELD} of 16 views already held, fetching {16 - HELD}" in err
    with Library(path) as library:
        (summary,) = library.scans()
        assert (summary.received, summary.status) == (16, "processed")
        report = library.result(1)
    assert report is not None and report["device"]["identity"]["source"].startswith("sim object=")
    assert len(load_segments(out / "segments.npz")) == 16


@pytest.mark.parametrize(
    ("flag", "value"),
    [
        ("--object", "sphere:d=25"),
        ("--seed", "4"),
        ("--noise", "none"),
        ("--rig", "limb"),
        ("--trim", "0.2"),
        ("--harmonics", "7"),
        ("--cylinder-mm", "20"),
        ("--expect", "sphere:d=25"),
        ("--subject", "P-02"),
        ("--sections", "3"),
    ],
)
def test_resume_with_options_other_than_the_scans_is_refused(capsys, tmp_path, flag, value):
    path = tmp_path / "library.sqlite"
    options = {
        "device": "sim",
        "out": str(tmp_path / "out"),
        "object": OBJECT,
        "seed": 0,
        "noise": "thesis",
        "rig": "thesis",
        "trim": 0.1,
        "harmonics": None,
        "cylinder_mm": None,
        "expect": None,
    }
    with Library(path) as library:
        library.create_scan("P-01", {"object": PLAN}, options, {}, {"source": "x"})
    before = dump(path)
    line = refused(
        capsys, "scan", "--device", "sim", "--library", str(path), "--resume", "1", flag, value
    )
    assert "scan 1" in line and "resume it without" in line
    assert dump(path) == before
    assert not (tmp_path / "out").exists()


def test_library_adds_segments_only_under_the_scans_identity_and_plan(tmp_path):
    path = tmp_path / "library.sqlite"
    identity = {"serial": "A-1", "source": "sim object=cylinder", "software": "d 1"}
    segment = _segment(PLAN, 0)
    with Library(path) as library:
        scan_id = library.create_scan("P-01", {"object": PLAN}, {}, {}, identity)
        assert library.add_segment(scan_id, 0, segment, dict(identity))
        before = dump(path)
        for other in (
            None,
            {},
            {**identity, "serial": "B-2"},
            {**identity, "source": "sim object=sphere"},
            {**identity, "extract": {"method": "otsu"}},
            {k: v for k, v in identity.items() if k != "software"},
        ):
            with pytest.raises(StoreError, match="scan 1"):
                library.add_segment(scan_id, 1, _segment(PLAN, 1), other)
            with pytest.raises(StoreError, match="scan 1"):
                library.save_calibration(scan_id, np.zeros((4, 4), np.uint8), _board(), 19.0, other)
        # The right identity, but a view the plan does not hold where it claims.
        for seq, bad in ((1, _segment(PLAN, 2)), (16, _segment(PLAN, 0)), (-1, segment)):
            with pytest.raises(StoreError, match="not a view scan 1 planned"):
                library.add_segment(scan_id, seq, bad, identity)
        assert dump(path) == before
        # A later scan given the deleted one's id is guarded by its own identity.
        library.delete_scan(scan_id)
        again = library.create_scan("P-01", {"object": PLAN}, {}, {}, {"serial": "C-3"})
        assert again == scan_id
        with pytest.raises(StoreError, match="serial"):
            library.add_segment(again, 0, segment, identity)
        assert library.add_segment(again, 0, segment, {"serial": "C-3"})


def test_identity_prefers_what_the_device_reports_and_records_only_what_exists():
    body = {
        "protocol": PROTOCOL_VERSION,
        "software": "lamina-device 1",
        "hardware": "sim",
        "image_size": [640, 480],
        "segment_encoding": {"row_scale": ROW_SCALE},
        "identity": {"serial": "rpi-1", "source": "sim cylinder:d=19.05 seed=0"},
        "extract": {"method": "otsu"},
        "board": {"inner_corners": [3, 2], "square_mm": 3.0, "origin_mm": [0.0, 0.0]},
    }
    welcome = Welcome.from_wire(body)
    identity = scan_identity(welcome, "sim object=sphere")
    assert identity["source"] == "sim cylinder:d=19.05 seed=0"
    assert identity["serial"] == "rpi-1" and identity["extract"] == {"method": "otsu"}
    unnamed = scan_identity(Welcome.from_wire({**body, "identity": None}), "sim object=x")
    assert unnamed["source"] == "sim object=x" and "serial" not in unnamed
    older = legacy_identity({"software": "lamina-device 0", "hardware": "sim"}, "sim object=x")
    assert older == {
        "legacy": True,
        "software": "lamina-device 0",
        "hardware": "sim",
        "source": "sim object=x",
    }
    recalibrated = scan_identity(Welcome.from_wire({**body, "cylinder_diameter_mm": 25.0}))
    assert identity_difference(identity, recalibrated) is not None
    assert "calibration" in (identity_difference(identity, recalibrated) or "")
    again = scan_identity(Welcome.from_wire(json.loads(json.dumps(welcome.to_wire()))))
    assert identity_difference(identity, again) is None


def test_a_schema_1_library_is_migrated_and_its_scans_guarded(tmp_path):
    path = tmp_path / "library.sqlite"
    with sqlite3.connect(path) as db:
        db.executescript(
            "CREATE TABLE subjects (id INTEGER PRIMARY KEY, code TEXT NOT NULL UNIQUE, "
            "created TEXT NOT NULL);"
            "CREATE TABLE scans (id INTEGER PRIMARY KEY, subject_id INTEGER NOT NULL, "
            "created TEXT NOT NULL, status TEXT NOT NULL, device TEXT NOT NULL, "
            "options TEXT NOT NULL, plans TEXT NOT NULL);"
            "INSERT INTO subjects VALUES (1, 'P-01', '2025-01-01');"
            "PRAGMA user_version=1;"
        )
        db.execute(
            "INSERT INTO scans VALUES (1, 1, '2025-01-01', 'acquiring', ?, ?, ?)",
            (
                json.dumps({"software": "lamina-device 1", "hardware": "sim"}),
                json.dumps({"device": "sim", "object": OBJECT, "seed": 0}),
                json.dumps({"object": PLAN.to_dict()}),
            ),
        )
    with Library(path) as library:
        record = library.scan(1)
        assert record.identity["legacy"] is True
        assert record.identity["source"] == f"sim object={OBJECT} rig=thesis noise=thesis seed=0"
        same = {
            "software": "lamina-device 1",
            "hardware": "sim",
            "serial": "new",
            "source": record.identity["source"],
        }
        library.check_identity(1, same)  # what it recorded matches; nothing else was known
        with pytest.raises(StoreError, match="source"):
            library.check_identity(1, {**same, "source": "sim object=sphere:d=25"})
    with sqlite3.connect(path) as db:
        # 3: colour, 4: side, 5: test mark, 6: lift reference
        assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION


def test_tui_resume_and_scan_refuse_another_device(library_copy, tmp_path):
    path, _ = library_copy
    before = dump(path)
    other = ScanJob(DeviceTarget("sim", "sphere:d=25"), path)
    try:
        other.connect()
        other.acquisition.open_scan(1)
        with pytest.raises(StoreError, match="another device or setup"):
            other.acquisition.fetch_object()
        assert dump(path) == before
        # Calibrated with one device, then connected to another: no scan may start.
        other.acquisition.calibrate_grid()
        other.acquisition.accept_grid(True)
        other.device.object_spec = OBJECT
        other.connect()
        with pytest.raises(UserError, match="not the one calibrated"):
            other.acquisition.calibrate_axis()
    finally:
        other.close()
    assert dump(path) == before


# --- 2. limits before a scan exists ------------------------------------------------------


def test_plan_beyond_the_devices_view_limit_creates_no_scan(capsys, tmp_path):
    path = tmp_path / "library.sqlite"
    argv = ["scan", "--device", "sim", "--library", str(path), "-o", str(tmp_path / "out")]
    line = refused(capsys, *argv, "--sections", "500", "--views", "360")
    assert "max_views" in line and "180000" in line
    assert scan_count(path) == 0


@pytest.mark.parametrize(
    ("plan", "limit"),
    [
        (ScanPlan.regular(4, 2.0, 7), "max_views"),
        (ScanPlan.regular(5, 2.0, 3), "max_sections"),
        (ScanPlan.regular(1, 2.0, 9), "max_views_per_section"),
    ],
)
def test_every_advertised_limit_is_checked_before_the_scan_exists(tmp_path, plan, limit):
    # The limits hold the simulator's cylinder plan (3 heights of 8 views), not the object's.
    limits = DeviceLimits(max_views=24, max_sections=4, max_views_per_section=8)
    with (
        served(DeviceServer, ServerSettings(limits=limits)) as client,
        Library(tmp_path / "library.sqlite") as library,
    ):
        job = ScanJob(DeviceTarget("sim"), library=library)
        job.attach_for_testing(client)
        with pytest.raises(InputError, match=rf"the object plan .*\({limit}\)"):
            job.acquisition.create(ScanRequest("P-01", plan))
        assert library.scans() == []


def test_limits_unit_names_each_limit():
    limits = DeviceLimits(max_views=10, max_sections=2, max_views_per_section=4)
    check_plan_limits("object", ScanPlan.regular(2, 1.0, 4), limits)
    for plan, name in (
        (ScanPlan.regular(3, 1.0, 3), "max_sections"),
        (ScanPlan.regular(1, 1.0, 5), "max_views_per_section"),
        (ScanPlan.regular(2, 1.0, 4), None),
    ):
        if name:
            with pytest.raises(InputError, match=name):
                check_plan_limits("object", plan, limits)
    with pytest.raises(InputError, match="max_views"):
        check_plan_limits("object", ScanPlan.regular(2, 1.0, 6), DeviceLimits(max_views=11))


# --- 3. validate before acting, never substitute -----------------------------------------

BAD_OPTIONS = [
    (["--sections", "0"], "sections 0"),
    (["--sections", "-2"], "sections -2"),
    (["--sections", "501"], "sections 501"),
    (["--views", "0"], "views 0"),
    (["--views", "-8"], "views -8"),
    (["--views", "2"], "views 2"),
    (["--pitch", "0"], "pitch 0 mm"),
    (["--pitch", "-2"], "pitch -2 mm"),
    (["--pitch", "nan"], "pitch nan mm"),
    (["--pitch", "inf"], "pitch inf mm"),
    (["--pitch=-inf"], "pitch -inf mm"),
    (["--cylinder-mm", "nan"], "--cylinder-mm nan"),
    (["--cylinder-mm", "inf"], "--cylinder-mm inf"),
    (["--cylinder-mm", "0"], "--cylinder-mm 0 mm"),
    (["--cylinder-mm", "-19"], "--cylinder-mm -19 mm"),
    (["--trim", "nan"], "--trim nan"),
    (["--trim", "-0.1"], "--trim -0.1"),
    (["--trim", "0.5"], "--trim 0.5"),
    (["--harmonics", "0"], "--harmonics 0"),
    (["--harmonics", "-3"], "--harmonics -3"),
    (["--seed", "-1"], "--seed -1"),
    (["--split-gap", "nan"], "--split-gap"),
    (["--split-gap", "-1"], "--split-gap"),
    (["--expect", "cylinder:d=nan"], "--expect"),
    (["--expect", "cylinder:d=0"], "--expect"),
    (["--subject", "Jane Doe"], "subject code"),
    (["--subject", "P1\nP2"], "subject code"),
    (["--subject", "P1\x1b[2J"], "subject code"),
    (["--subject", "x" * 33], "subject code"),
    (["--subject", ".."], "subject code"),
    (["--subject", ""], "subject code"),
    (["--subject", "Müller"], "subject code"),
    (["--device", "replay:/nonexistent"], "capture.json"),
    (["--device", "/dev/ttyNONE", "--object", OBJECT], "--object only applies"),
    (["--device", "/dev/ttyNONE", "--sway", "patient"], "--sway only applies to --device sim"),
]


@pytest.mark.parametrize(("extra", "expected"), BAD_OPTIONS)
def test_bad_options_are_refused_before_anything_exists(capsys, tmp_path, extra, expected):
    path, out = tmp_path / "library.sqlite", tmp_path / "out"
    argv = ["scan", "--device", "sim", "--library", str(path), "-o", str(out), *extra]
    line = refused(capsys, *argv)
    assert expected in line
    assert "\x1b" not in line and "\n" not in line.rstrip("\n")
    assert scan_count(path) == 0
    assert not out.exists()


@pytest.mark.parametrize(
    "fields",
    [
        ("0", "2", "8"),
        ("-1", "2", "8"),
        ("4", "0", "8"),
        ("4", "nan", "8"),
        ("4", "inf", "8"),
        ("4", "-2", "8"),
        ("4", "2", "0"),
        ("4", "2", "-8"),
        ("501", "2", "8"),
    ],
)
def test_cli_and_tui_refuse_a_plan_with_the_same_words(capsys, tmp_path, fields):
    sections, pitch, views = fields
    with pytest.raises(UserError) as tui:
        parse_plan(sections, pitch, views)
    argv = [
        "scan",
        "--device",
        "sim",
        "--library",
        str(tmp_path / "l.sqlite"),
        "-o",
        str(tmp_path / "o"),
        "--sections",
        sections,
        "--pitch",
        pitch,
        "--views",
        views,
    ]
    line = refused(capsys, *argv)
    assert line == f"lamina: {tui.value}"


def test_scans_listing_escapes_whatever_an_older_library_holds(capsys, tmp_path):
    path = tmp_path / "library.sqlite"
    with Library(path) as library:
        library.create_scan("P-01", {"object": PLAN})
    with sqlite3.connect(path) as db:
        for code in ("evil\x1b[2J\x1b]0;owned\x07", "two\nlines", "rtl\u202egnp.exe"):
            db.execute("INSERT INTO subjects (code, created) VALUES (?, '2025')", (code,))
            db.execute(
                "INSERT INTO scans (subject_id, created, status, device, options, plans) "
                "VALUES (last_insert_rowid(), '2025\x1b[1m', 'acquiring', '{}', '{}', ?)",
                (json.dumps({"object": PLAN.to_dict()}),),
            )
    status, out, _ = run(capsys, "scans", "--library", str(path))
    assert status == 0
    assert len(out.splitlines()) == 5  # header and four scans, one line each
    assert "\x1b" not in out and "\x07" not in out and "\u202e" not in out
    assert "evil\\x1b[2J" in out and "two\\nlines" in out and "rtl\\u202egnp" in out
    assert printable("a\tb") == "a\\tb" == printable(printable("a\tb"))


# --- 4. files: one line, never outside the user's intent --------------------------------


def test_output_folders_that_cannot_be_used_are_refused_first(capsys, tmp_path):
    path = tmp_path / "library.sqlite"
    a_file = tmp_path / "a-file"
    a_file.write_text("keep")
    full = tmp_path / "full"
    full.mkdir()
    (full / "earlier.ply").write_text("keep")
    cases = [
        (a_file, "is a file"),
        (a_file / "sub", "cannot write into output folder"),
        (full, "is not empty"),
    ]
    if not os.access("/sys", os.W_OK) or _unwritable("/sys"):
        cases.append((Path("/sys/lamina-out"), "cannot write into output folder"))
    for out, expected in cases:
        line = refused(capsys, "scan", "--device", "sim", "--library", str(path), "-o", str(out))
        assert expected in line, line
    assert a_file.read_text() == "keep" and (full / "earlier.ply").read_text() == "keep"
    assert scan_count(path) == 0


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into any folder")
def test_an_unwritable_folder_is_refused_before_the_device_starts(capsys, tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    argv = ["scan", "--device", "sim", "--library", str(tmp_path / "l.sqlite")]
    line = refused(capsys, *argv, "-o", str(locked / "out"))
    assert "cannot write into output folder" in line


@pytest.fixture(scope="module")
def processed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with a library holding one processed 2 x 8 scan, and the scan's outputs."""
    folder = tmp_path_factory.mktemp("processed")
    status = cli.main(
        [
            "scan",
            "--device",
            "sim",
            "--object",
            OBJECT,
            "--sections",
            "2",
            "--views",
            "8",
            "--library",
            str(folder / "library.sqlite"),
            "-o",
            str(folder / "out"),
            "--subject",
            "P-01",
        ]
    )
    assert status == 0
    return folder


def test_outputs_exports_and_folders_are_owner_only(processed, tmp_path, capsys):
    out = processed / "out"
    assert stat.S_IMODE(out.stat().st_mode) == 0o700
    names = {p.name for p in out.iterdir()}
    assert names == {
        "calibration-grid.png",
        "cylinder-segments.npz",
        "segments.npz",
        "raw_points.ply",
        "points.ply",
        "mesh.ply",
        "report.json",
    }
    for path in out.iterdir():
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    for name in ("m.ply", "m.obj", "m.stl", "r.json"):
        status, _, err = run(
            capsys,
            "export",
            "1",
            "-o",
            str(tmp_path / name),
            "--library",
            str(processed / "library.sqlite"),
        )
        assert status == 0, err
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o600


def test_a_library_readable_by_others_is_tightened_once(processed, tmp_path, capsys):
    path = tmp_path / "library.sqlite"
    shutil.copy(processed / "library.sqlite", path)
    path.chmod(0o644)
    status, _, err = run(capsys, "scans", "--library", str(path))
    assert status == 0 and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert err.count("readable by its owner only") == 1
    status, _, err = run(capsys, "scans", "--library", str(path))
    assert status == 0 and err == ""


def test_export_refuses_every_path_it_must_not_write(processed, tmp_path, capsys):
    library = str(processed / "library.sqlite")
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (tmp_path / "link.ply").symlink_to(victim)
    (tmp_path / "dangling.ply").symlink_to(tmp_path / "nowhere.ply")
    (tmp_path / "exists.json").write_text("old")
    (tmp_path / "folder.ply").mkdir()
    (tmp_path / "link.dcm").symlink_to(victim)
    (tmp_path / "link.lrec").symlink_to(victim)
    cases = [
        (tmp_path / "link.dcm", "already exists"),
        (tmp_path / "link.lrec", "already exists"),
        (tmp_path / "no" / "x.dcm", "does not exist"),
        (tmp_path / "no" / "such" / "folder" / "x.ply", "does not exist"),
        (tmp_path / "victim.txt" / "x.ply", "does not exist"),
        (tmp_path / "link.ply", "already exists"),
        (tmp_path / "dangling.ply", "already exists"),
        (tmp_path / "exists.json", "already exists"),
        (tmp_path / "folder.ply", "already exists"),
        (tmp_path / "x.exe", "name the file .ply"),
    ]
    for path, expected in cases:
        line = refused(capsys, "export", "1", "-o", str(path), "--library", library)
        assert expected in line, line
    assert victim.read_text() == "precious" and (tmp_path / "exists.json").read_text() == "old"
    assert not (tmp_path / "nowhere.ply").exists() and not (tmp_path / "no").exists()


def test_resume_replaces_planted_links_and_never_writes_through_them(processed, tmp_path, capsys):
    path, out = tmp_path / "library.sqlite", tmp_path / "out"
    shutil.copy(processed / "library.sqlite", path)
    shutil.copytree(processed / "out", out)
    with sqlite3.connect(path) as db:
        options = json.loads(db.execute("SELECT options FROM scans").fetchone()[0])
        db.execute("UPDATE scans SET options = ?", (json.dumps({**options, "out": str(out)}),))
    victims = {}
    for file in out.iterdir():
        victim = tmp_path / f"victim-{file.name}"
        victim.write_bytes(b"precious")
        file.unlink()
        file.symlink_to(victim)
        victims[victim] = file
    resume = ["scan", "--device", "sim", "--library", str(path), "--resume", "1"]
    status, said, err = run(capsys, *resume)  # complete: nothing is written (issue #24)
    assert status == 0 and "is complete" in said, err
    assert all(file.is_symlink() for file in victims.values())
    status, _, err = run(capsys, *resume, "--reprocess")
    assert status == 0, err
    for victim, file in victims.items():
        assert victim.read_bytes() == b"precious"
        assert not file.is_symlink() and stat.S_IMODE(file.stat().st_mode) == 0o600
    assert len(load_segments(out / "segments.npz")) == 16


def test_a_damaged_library_is_one_line_for_every_command(processed, tmp_path, capsys):
    path = tmp_path / "library.sqlite"
    shutil.copy(processed / "library.sqlite", path)
    with open(path, "r+b") as db:
        page = 4096
        size = path.stat().st_size
        for offset in range(page, size, page):  # every page but the header's
            db.seek(offset)
            db.write(bytes(range(256)) * (page // 256))
    commands = [
        ["scans"],
        ["export", "1", "-o", str(tmp_path / "x.ply")],
        ["export", "1", "-o", str(tmp_path / "x.lrec")],
        ["batch", "--subjects", "*", "--measure", "-o", str(tmp_path / "t.csv")],
        ["scan", "--device", "sim", "-o", str(tmp_path / "new"), "--sections", "1"],
        ["scan", "--device", "sim", "--resume", "1"],
    ]
    for command in commands:
        line = refused(capsys, *command, "--library", str(path))
        assert "library" in line, line
    assert not (tmp_path / "x.ply").exists() and not (tmp_path / "t.csv").exists()


# --- 5. smaller ----------------------------------------------------------------------------


def _children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        text = (task / "children").read_text().split()
        found += [int(t) for t in text]
    return found


def _ctrl_c_as_in_a_terminal() -> None:
    # A shell starts background jobs (make test &, CI runners) with SIGINT ignored, and
    # Python then installs no KeyboardInterrupt handler: the host would rightly ignore the
    # signal. A user's Ctrl-C comes to a foreground program, whose SIGINT is the default.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_long_scan(tmp_path: Path) -> tuple[subprocess.Popen[str], Path, Path]:
    path, out = tmp_path / "library.sqlite", tmp_path / "out"
    argv = ["scan", "--device", "sim", "--library", str(path), "-o", str(out)]
    host = subprocess.Popen(
        host_command(*argv, "--sections", "10", "--views", "8"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_ctrl_c_as_in_a_terminal,
    )
    deadline = time.monotonic() + 120
    while held_segments(path) < 3 and host.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert host.poll() is None, host.communicate()
    return host, path, out


@pytest.mark.parametrize("how", ["device killed", "host interrupted"])
@pytest.mark.wall_clock
def test_a_stopped_scan_says_why_within_seconds_and_keeps_what_arrived(tmp_path, how):
    host, path, out = _start_long_scan(tmp_path)
    stopped = time.monotonic()
    if how == "device killed":
        (device,) = _children(host.pid)
        os.kill(device, signal.SIGKILL)
    else:
        os.kill(host.pid, signal.SIGINT)
    _, err = host.communicate(timeout=60)
    elapsed_s = time.monotonic() - stopped
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("lamina:")]
    assert len(lines) == 1, err
    if how == "device killed":
        assert host.returncode == 2 and elapsed_s < 8.0, (elapsed_s, err)
        assert "the device program was killed (signal 9)" in lines[0]
        assert "lamina scan --resume 1" in lines[0]
    else:
        assert host.returncode == 130, err
    held = held_segments(path)
    assert 3 <= held < 80
    kept = load_segments(out / "segments.npz")
    with Library(path) as library:
        stored = library.segments(1, "object")
    assert len(kept) == held and all(a.same_as(b) for a, b in zip(kept, stored, strict=True))


@pytest.fixture
def silent_device(tmp_path: Path) -> Iterator[tuple[PtyBridge, Path]]:
    bridge = PtyBridge()
    try:
        yield bridge, tmp_path
    finally:
        bridge.close()


def _client_for(bridge: PtyBridge, code: str) -> DeviceClient:
    process = subprocess.Popen(
        [sys.executable, "-c", code],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    port = serial.Serial(bridge.host_port, baudrate=115200, timeout=0.05)
    return DeviceClient(Channel(port), process)


@pytest.mark.wall_clock
def test_a_starting_device_is_waited_for_while_it_runs_then_named(silent_device, monkeypatch):
    bridge, _ = silent_device
    monkeypatch.setattr(link, "SPAWNED_STARTUP_S", 3.0)
    monkeypatch.setattr(link, "STARTUP_NOTICE_S", 0.5)
    client = _client_for(bridge, "import time; time.sleep(30)")
    notices: list[str] = []
    start = time.monotonic()
    try:
        with pytest.raises(DeviceError, match="has not answered in 3 s"):
            client.hello(timeout_s=0.5, on_notice=notices.append)
        assert time.monotonic() - start >= 2.9  # waited beyond the 0.5 s a cable gets
        assert notices == ["waiting for the device program to start (up to 3 s)"]
    finally:
        assert client.process is not None
        client.process.kill()
        client.process.wait()
    exited = _client_for(bridge, "import sys; sys.exit('replay: capture.json is damaged')")
    start = time.monotonic()
    with pytest.raises(DeviceError, match=r"exited \(status 1\): replay: capture.json is damaged"):
        exited.hello()
    assert time.monotonic() - start < 5.0


@pytest.mark.parametrize("failure", ["no pseudo-terminal", "unknown object", "damaged capture"])
def test_a_device_that_cannot_start_is_one_line_and_leaves_nothing(
    capsys, tmp_path, monkeypatch, failure
):
    path, out = tmp_path / "l.sqlite", tmp_path / "out"
    argv = ["scan", "--device", "sim", "--library", str(path), "-o", str(out)]
    if failure == "no pseudo-terminal":

        def no_pty() -> tuple[int, int]:
            raise FileNotFoundError(2, "No such file or directory", "/dev/ptmx")

        monkeypatch.setattr(os, "openpty", no_pty)
        expected = "cannot open a pseudo-terminal"
    elif failure == "unknown object":
        argv += ["--object", "blob:d=3"]
        expected = "the device program exited (status 2): lamina-device: object 'blob:d=3'"
    else:
        capture = tmp_path / "capture"
        capture.mkdir()
        (capture / "capture.json").write_text('{"format": ')
        argv[2] = f"replay:{capture}"
        expected = "the device program exited"
    line = refused(capsys, *argv)
    assert expected in line, line
    assert scan_count(path) == 0
    assert not out.exists()


def test_a_scan_stored_with_a_nan_cylinder_by_an_older_lamina_resumes(capsys, library_copy):
    path, out = library_copy
    with sqlite3.connect(path) as db:
        options = {"device": "sim", "out": str(out), "object": OBJECT, "cylinder_mm": math.nan}
        db.execute("UPDATE scans SET options = ?", (json.dumps(options),))
        db.execute("UPDATE calibrations SET cylinder_mm = NULL")
    status, _, err = run(capsys, "scan", "--device", "sim", "--library", str(path), "--resume", "1")
    assert status == 0, err
    with Library(path) as library:
        report = library.result(1)
        assert library.scans()[0].received == 16
    assert report is not None and report["calibration"]["n_corners"] == 143
    assert abs(report["correction_factor"] - 1.0) < 0.05  # the device's 19.05 mm was used


# --- helpers -------------------------------------------------------------------------------


def _unwritable(folder: str) -> bool:
    try:
        Path(folder, "lamina-probe").mkdir()
    except OSError:
        return True
    Path(folder, "lamina-probe").rmdir()
    return False


def _segment(plan: ScanPlan, seq: int) -> Segment:
    view = plan.views[seq]
    cols = np.arange(10, dtype=np.uint16)
    return Segment(
        "object",
        view.section,
        seq % 8,
        view.z_mm,
        view.angle_deg,
        cols,
        np.full(10, 5.0, np.float32),
        np.full(10, 200, np.uint8),
        np.full(10, 3, np.uint8),
    )


def _board() -> Any:
    from lamina_shared.types import BoardSpec

    return BoardSpec((9, 7), 3.0, (0.0, 0.0))


@contextmanager
def served(server_class: type[DeviceServer], settings: ServerSettings) -> Iterator[DeviceClient]:
    """A sim device served in this process over a real pty link, and a handshaken client."""
    with served_link(settings=settings, object_spec=OBJECT, server_class=server_class) as ends:
        yield ends.client


# --- issue 19: probes that need this module's scans -------------------------------------


def strict_json(text: str) -> Any:
    """Parse ``text`` as a strict JSON parser does: NaN and Infinity are not JSON."""

    def refuse(name: str) -> Any:
        raise ValueError(f"{name} is not JSON")

    return json.loads(text, parse_constant=refuse)


def test_resuming_a_tui_scan_without_an_output_folder_is_one_line(capsys, partial, tmp_path):
    """The TUI records no output folder: KeyError 'out' on lamina scan --resume."""
    path = tmp_path / "library.sqlite"
    path.write_bytes((partial / "library.sqlite").read_bytes())
    path.chmod(0o600)
    before = held_segments(path)
    argv = ["scan", "--device", "sim", "--library", str(path), "--resume", "1"]
    line = refused(capsys, *argv)
    assert "scan 1 has no output folder" in line and "-o NEW_FOLDER" in line
    assert held_segments(path) == before


def test_reports_are_strict_json(processed, capsys, tmp_path):
    """view_offset_sd_deg was written NaN, which strict parsers reject."""
    report = strict_json((processed / "out" / "report.json").read_text())
    assert report["axis"]["view_offset_sd_deg"] is None
    exported = tmp_path / "report.json"
    status, _, err = run(capsys, "export", "1", "-o", str(exported),
                         "--library", str(processed / "library.sqlite"))  # fmt: skip
    assert status == 0, err
    assert strict_json(exported.read_text())["axis"]["view_offset_sd_deg"] is None
