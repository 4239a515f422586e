"""The probes of issue #19 that still got a traceback, a crash, a hang or a wrong message.

Each test reproduces one probe as a careless user or an attacker ran it (and failed on
the code before the fix), then tries its class on random values: plans no lift can make,
captures with thousands of problems, paths that are not text, stop signals, huge numbers
on the wire, a port closing under its reader, NaN in a report, a full disk, a second host.
The real CLI runs through ``main()`` (or as a process where it must be signalled), with a
real SQLite library and simulated devices on real pseudo-terminals or sockets.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import logging
import math
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import serial

from lamina_device.motion import StepperLift
from lamina_device.sim.backend import DEFAULT_CYLINDER_PLAN
from lamina_device.sim.specs import MAX_OBJECT_MM, parse_object
from lamina_host import cli
from lamina_host.link import client as link
from lamina_host.link.client import DeviceClient
from lamina_host.link.connect import open_device
from lamina_host.link.errors import DeviceError, RequestRefused
from lamina_host.link.spawn import PtyBridge
from lamina_host.store.library import Library
from lamina_host.store.outputs import load_segments
from lamina_host.workflow import check_plan, check_plan_limits
from lamina_host.workflow.job import ScanRequest
from lamina_shared.errors import InputError
from lamina_shared.link import Channel
from lamina_shared.messages import AxesInfo
from lamina_shared.types import ScanPlan
from tests.helpers.cli import device_command
from tests.helpers.library import held_segments
from tests.test_hostile_device import _refused, device
from tests.test_hostile_host import (
    OBJECT,
    _start_long_scan,
    one_line,
    refused,
    run,
    scan_count,
    strict_json,
)

SIM_AXES = AxesInfo(0.0, 200.0)
"""The simulated device's WELCOME ``axes`` (a continuous turntable)."""


def lamina_line(status: int, err: str) -> str:
    """Assert a refusal during a scan: status 2, no traceback, one ``lamina:`` line (the
    progress lines aside); return it."""
    assert status == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("lamina")]
    assert len(lines) == 1, err
    return lines[0]


# --- pitches and plans a lift cannot make ----------------------------------------------


def test_every_pitch_is_a_plan_or_one_refusal_never_a_value_error():
    """1e-300 rounded to 0 inside ScanPlan and escaped both front ends as a ValueError."""
    rng = np.random.default_rng(19)
    pitches = [1e-300, 5e-324, 1e-10, 4e-10, 5e-10, 1e-9, 4e-4, 1e-3, 2.0, 50.0]
    pitches += list(10.0 ** rng.uniform(-320, 2, 200))
    for pitch in pitches:
        try:
            plan = check_plan(3, float(pitch), 8)
        except InputError as exc:
            assert "pitch" in str(exc) and "\n" not in str(exc)
            assert pitch < 1e-3 or pitch > 50.0, pitch
            continue
        heights = sorted({v.z_mm for v in plan.views})
        assert heights[1] == round(pitch, 9) > 0 and 1e-3 <= pitch <= 50.0


@pytest.mark.parametrize("pitch", ["1e-300", "0.0000000001", "0.0004"])
def test_a_pitch_finer_than_any_lift_is_one_line_before_anything_exists(capsys, tmp_path, pitch):
    path, out = tmp_path / "library.sqlite", tmp_path / "out"
    argv = ["scan", "--device", "sim", "--library", str(path), "-o", str(out)]
    line = refused(capsys, *argv, "--sections", "2", "--pitch", pitch)
    assert "pitch" in line and "0.001 mm" in line
    assert scan_count(path) == 0 and not out.exists()


def test_plans_are_checked_against_the_advertised_axes():
    """Random regular plans: refused exactly when they leave the lift's travel or step."""
    stepper = dataclasses.replace(SIM_AXES, lift_step_mm=0.0025)
    with pytest.raises(InputError, match=r"reaches 202 mm, beyond the lift's travel of 0\.\.200"):
        check_plan_limits("object", ScanPlan.regular(102, 2.0, 8), None, SIM_AXES)
    check_plan_limits("object", ScanPlan.regular(101, 2.0, 8), None, SIM_AXES)  # top at 200
    with pytest.raises(InputError, match=r"finer than the lift's step of 0\.0025 mm"):
        check_plan_limits("object", ScanPlan.regular(3, 0.002, 8), None, stepper)
    check_plan_limits("object", ScanPlan.regular(3, 0.0025, 8), None, stepper)
    bounded = dataclasses.replace(SIM_AXES, turntable_min_deg=0.0, turntable_max_deg=180.0)
    with pytest.raises(InputError, match=r"beyond the turntable's travel of 0\.\.180 deg"):
        check_plan_limits("object", ScanPlan.regular(1, 2.0, 4), None, bounded)  # 270 deg
    # No axes reported: the travel is not checked.
    check_plan_limits("object", ScanPlan.regular(500, 2.0, 8), None, AxesInfo())
    rng = np.random.default_rng(7)
    for _ in range(300):
        sections, pitch = int(rng.integers(1, 400)), float(rng.uniform(0.001, 5.0))
        plan = ScanPlan.regular(sections, pitch, 4)
        top = max(v.z_mm for v in plan.views)
        gaps = np.diff(sorted({v.z_mm for v in plan.views}))
        beyond = top > 200.0 or (len(gaps) > 0 and gaps.min() < 0.0025 * (1 - 1e-9))
        try:
            check_plan_limits("object", plan, None, stepper)
        except InputError:
            assert beyond, (sections, pitch)
        else:
            assert not beyond, (sections, pitch)


def test_a_stepper_lift_advertises_its_step():
    from gpiozero.pins.mock import MockFactory

    from lamina_device.config import load_config
    from lamina_device.operations import check_section_gaps
    from lamina_device.server import RequestError

    config = load_config()
    lift = StepperLift(config.lift, MockFactory())
    try:
        step = 1.0 / lift.steps_per_mm
        assert lift.step_mm == step
        limits = AxesInfo(lift.min_mm, lift.max_mm, None, None, lift.step_mm)
        assert limits.to_wire()["lift"]["step"] == step
        assert "step" not in AxesInfo(0.0, 200.0).to_wire()["lift"]  # a lift without steps
        check_section_gaps(limits, [0.0, step, 2 * step, 40.0])
        with pytest.raises(RequestError, match="finer than the lift's step"):
            check_section_gaps(limits, [0.0, step / 2])  # the device refuses it too
        check_section_gaps(AxesInfo(0.0, 200.0), [0.0, 1e-9])  # no step: not checked
    finally:
        lift.close()


def test_a_plan_beyond_the_lift_is_refused_before_the_scan_exists(capsys, tmp_path):
    """The probe: created, calibrated and half acquired, then refused at 202 mm."""
    path, out = tmp_path / "library.sqlite", tmp_path / "out"
    argv = ["scan", "--device", "sim", "--library", str(path), "-o", str(out)]
    line = refused(capsys, *argv, "--sections", "102", "--pitch", "2")
    assert "202 mm, beyond the lift's travel of 0..200 mm" in line
    assert scan_count(path) == 0 and not out.exists()


def test_a_stored_plan_beyond_the_lift_is_not_advised_to_be_resumed(capsys, tmp_path):
    """A scan an older Lamina created beyond the lift: one line, and no resume advice."""
    path, out = tmp_path / "library.sqlite", tmp_path / "out"
    with open_device("sim") as client, Library(path) as library:
        plans = {"cylinder": client.plan_for("cylinder", None)}
        plans["object"] = ScanPlan.regular(102, 2.0, 8)
        library.create_scan("P-01", plans, {"device": "sim", "out": str(out)}, {},
                            client.identity())  # fmt: skip
    line = refused(capsys, "scan", "--device", "sim", "--library", str(path), "--resume", "1")
    assert "scan 1 cannot be finished on this device" in line and "--resume" not in line


def test_a_device_refusing_the_plan_mid_scan_is_not_advised_to_be_resumed(monkeypatch, tmp_path):
    """The device's own limit refusal repeats on every resume: the advice must not loop."""

    class Device:
        def set_extract(self, changes: Any) -> None: ...
        def set_colour(self, colour: bool) -> None: ...

    class Job:
        scan_id, library_path = 3, tmp_path / "library.sqlite"
        device = Device()

        def connect(self, on_notice: Any = None) -> None: ...

    def refuse(*args: Any, **kwargs: Any) -> None:
        message = "the device refused scan: lift position 202.0 mm is outside 0..200"
        raise RequestRefused("limit", message)

    monkeypatch.setattr(cli, "acquire", refuse)
    args = cli.build_parser().parse_args(["scan", "--device", "sim", "-o", str(tmp_path / "o")])
    request = ScanRequest("P-01")
    with pytest.raises(DeviceError) as caught:
        cli._acquire_scan(Job(), args, request)  # type: ignore[arg-type]
    assert "cannot finish its plan" in str(caught.value) and "--resume" not in str(caught.value)
    for code, resumable in (("timeout", True), ("busy", True), ("bad-args", False)):
        monkeypatch.setattr(cli, "acquire", lambda *a, c=code, **k: (_ for _ in ()).throw(
            RequestRefused(c, "the device refused scan: ...")))  # fmt: skip
        with pytest.raises(DeviceError) as caught:
            cli._acquire_scan(Job(), args, request)  # type: ignore[arg-type]
        assert ("--resume 3" in str(caught.value)) is resumable, code


# --- a capture with thousands of problems ----------------------------------------------


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("capture") / "rod"
    plan = ["--sections", "1", "--views", "3", "--cylinder-views", "3"]
    subprocess.run(
        device_command("record", "--hardware", "sim", "--out", str(out), *plan),
        check=True,
        capture_output=True,
        timeout=300,
    )
    return out


@pytest.mark.wall_clock
def test_a_capture_with_thousands_of_problems_is_one_line_within_seconds(small_capture, tmp_path):
    """The device wrote 107 KB of problems to a pipe read only after exit: a 120 s hang."""
    capture = tmp_path / "capture"
    subprocess.run(["cp", "-r", str(small_capture), str(capture)], check=True)
    manifest = json.loads((capture / "capture.json").read_text())
    view = manifest["scan"]["views"][0]
    manifest["scan"]["views"] = [{**view, "angle_deg": True} for _ in range(2000)]
    (capture / "capture.json").write_text(json.dumps(manifest))
    start = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "lamina_host", "scan", "--device", f"replay:{capture}",
         "--library", str(tmp_path / "l.sqlite"), "-o", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=100,
    )  # fmt: skip
    elapsed_s = time.monotonic() - start
    line = one_line(done.returncode, done.stderr)
    found = re.search(r"\((\d+) problem\(s\)\)", line)
    assert found and int(found.group(1)) >= 2000, line
    assert "the device program exited (status 2)" in line and "more" in line
    assert elapsed_s < 60, elapsed_s
    assert len(line) < 8000


def test_the_device_lists_the_first_problems_and_counts_the_rest(small_capture, tmp_path):
    capture = tmp_path / "capture"
    subprocess.run(["cp", "-r", str(small_capture), str(capture)], check=True)
    manifest = json.loads((capture / "capture.json").read_text())
    view = manifest["scan"]["views"][0]
    manifest["scan"]["views"] = [{**view, "z_mm": "x"} for _ in range(500)]
    (capture / "capture.json").write_text(json.dumps(manifest))
    done = subprocess.run(
        device_command("serve", "--port", "/dev/null", "--hardware", f"replay:{capture}"),
        capture_output=True,
        text=True,
        timeout=60,
    )
    lines = done.stderr.splitlines()
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert lines[-1].startswith(f"lamina-device: capture {capture} is not usable")
    assert len(lines) == 12 and lines[-2].startswith("  - ... and ") and "more" in lines[-2]
    assert len(done.stderr) < 16_000


@pytest.mark.wall_clock
def test_the_host_reads_a_device_programs_stderr_while_it_runs(monkeypatch):
    """A child that writes far more than a pipe holds, then exits, is named at once."""
    monkeypatch.setattr(link, "SPAWNED_STARTUP_S", 20.0)
    code = (
        "import sys\n"
        "for k in range(5000): print(f'  - problem {k}: ' + 'x' * 60, file=sys.stderr)\n"
        "sys.exit('lamina-device: capture is not usable (5000 problem(s))')\n"
    )
    bridge = PtyBridge()
    process = subprocess.Popen(
        [sys.executable, "-c", code],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        port = serial.Serial(bridge.host_port, baudrate=115200, timeout=0.05)
        client = DeviceClient(Channel(port), process)
        start = time.monotonic()
        with pytest.raises(DeviceError, match=r"exited \(status 1\): lamina-device: capture"):
            client.hello()
        assert time.monotonic() - start < 15
        port.close()
    finally:
        process.kill()
        process.wait()
        bridge.close()


# --- paths that are not text -------------------------------------------------------------


def test_an_output_path_that_is_not_utf8_is_refused_before_anything_exists(capsys, tmp_path):
    """cv2.imwrite segfaulted on the surrogate-escaped name, after the scan was created."""
    path = tmp_path / "library.sqlite"
    bad = tmp_path / os.fsdecode(b"out-\xff\xfe")
    line = refused(capsys, "scan", "--device", "sim", "--library", str(path), "-o", str(bad))
    assert "-o" in line and "not UTF-8" in line and "\\udcff" in line
    assert scan_count(path) == 0 and not bad.exists()
    for argv in (
        ["export", "1", "-o", str(tmp_path / os.fsdecode(b"m\xff.stl"))],
        ["report", "1", "-o", str(tmp_path / os.fsdecode(b"r\xff.pdf"))],
        ["scans", "--library", str(tmp_path / os.fsdecode(b"l\xff.sqlite"))],
    ):
        assert "not UTF-8" in refused(capsys, *argv)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_the_calibration_image_is_written_to_any_path_the_file_system_takes(tmp_path):
    """Written through Python's file API: a name of any bytes gets the PNG (no crash)."""
    code = (
        "import os, sys, numpy as np\n"
        "from pathlib import Path\n"
        "from lamina_host.workflow.job import _write_image\n"
        "from lamina_host.workflow.results import ScanData\n"
        "image = (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64)\n"
        "_write_image(Path(sys.argv[1]) / os.fsdecode(b'grid-\\xff.png'), ScanData(image))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, (done.returncode, done.stderr)
    import cv2

    written = (tmp_path / os.fsdecode(b"grid-\xff.png")).read_bytes()
    image = cv2.imdecode(np.frombuffer(written, np.uint8), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(image, (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64))


def test_capture_frames_are_written_and_read_under_any_file_name(tmp_path):
    """The capture format's PNGs go through Python's file API too (OpenCV took text)."""
    code = (
        "import os, sys, numpy as np\n"
        "from pathlib import Path\n"
        "from lamina_shared.capture import CaptureWriter, read_frame\n"
        "image = (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64)\n"
        "folder = Path(sys.argv[1]) / os.fsdecode(b'capture-\\xff')\n"
        "writer = CaptureWriter(folder, (64, 48))\n"
        "rel = writer._write_png('calib/grid.png', image)\n"
        "assert np.array_equal(read_frame(folder / rel), image)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, (done.returncode, done.stderr)


# --- SIGTERM and SIGHUP -------------------------------------------------------------------


def test_sigterm_stops_a_scan_as_ctrl_c_does(tmp_path):
    """An SSH session dropping ended the scan silently, nothing in the output folder."""
    host, path, out = _start_long_scan(tmp_path)
    os.kill(host.pid, signal.SIGTERM)
    _, err = host.communicate(timeout=60)
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("lamina:")]
    assert host.returncode == 130 and len(lines) == 1, err
    assert "interrupted" in lines[0] and "lamina scan --resume 1 --device sim" in lines[0]
    held = held_segments(path)
    kept = load_segments(out / "segments.npz")
    with Library(path) as library:
        stored = library.segments(1, "object")
    assert 3 <= held == len(kept) and all(a.same_as(b) for a, b in zip(kept, stored, strict=True))
    assert (out / "cylinder-segments.npz").exists()


@pytest.mark.parametrize("number", cli.STOP_SIGNALS)
def test_every_stop_signal_interrupts_as_ctrl_c(number):
    """SIGHUP (a terminal closed) and SIGTERM arrive as the interrupt Ctrl+C gives."""
    assert set(cli.STOP_SIGNALS) == {signal.SIGTERM, signal.SIGHUP}
    with pytest.raises(KeyboardInterrupt), cli._stop_signals_interrupt():
        os.kill(os.getpid(), number)
        time.sleep(5)  # the handler raises here, at once
    assert signal.getsignal(number) is not cli._interrupt


def test_the_stop_signals_are_given_back_after_a_scan(capsys, tmp_path):
    before = {n: signal.getsignal(n) for n in cli.STOP_SIGNALS}
    refused(capsys, "scan", "--device", "sim", "--pitch", "0", "-o", str(tmp_path / "o"))
    assert {n: signal.getsignal(n) for n in cli.STOP_SIGNALS} == before


# --- huge numbers in a plan on the wire ------------------------------------------------


def test_huge_integers_anywhere_in_a_plan_are_refused_not_internal():
    """A 401-digit z_mm reached float() and the device answered 'internal'."""
    huge = [10**400, -(10**400), 2**1024, -(2**1024), 10**309]
    with device() as ends:
        for value in huge:
            for key in ("z_mm", "angle_deg"):
                view = {"section": 0, "z_mm": 0.0, "angle_deg": 0.0, key: value}
                reply = ends.request("scan", {"target": "object", "plan": {"views": [view]}})
                assert key in _refused(reply, "bad-args", "limit")
            regular = {"sections": 2, "pitch_mm": value, "views": 2}
            reply = ends.request("scan", {"target": "object", "plan": {"regular": regular}})
            assert "pitch_mm" in _refused(reply, "bad-args", "limit")
        assert ends.hardware.camera.frames_taken == 0
        ends.assert_up()


# --- the end of a scan over socket:// ---------------------------------------------------


def test_the_link_reader_stops_before_its_socket_closes(device_service, caplog):
    """1 of 6 runs ended with 'the link reader met an error' (AttributeError)."""
    with caplog.at_level(logging.ERROR, logger="lamina_shared.endpoint"):
        for _ in range(3):
            with open_device(device_service) as client:
                assert client.exposure()[0] > 0
                reader = client.dispatcher._thread
            assert reader is not None and not reader.is_alive()
        time.sleep(0.3)  # a reader left running would meet the closed port by now
    assert not [r for r in caplog.records if "link reader" in r.getMessage()]
    assert not [t for t in threading.enumerate() if t.name == "link-reader"]


# --- a second host on a device service ------------------------------------------------------


def test_a_second_host_is_told_the_device_is_in_use(device_service, capsys, tmp_path):
    """It was told the link broke and to check the cable."""
    path = tmp_path / "library.sqlite"
    with open_device(device_service) as first:
        for _ in range(2):
            with (
                pytest.raises(DeviceError, match="in use by another host") as caught,
                open_device(device_service),
            ):
                pass
            assert "cable" not in str(caught.value)
        argv = ["scan", "--device", device_service, "--library", str(path)]
        line = refused(capsys, *argv, "-o", str(tmp_path / "out"))
        assert "the device is in use by another host" in line and "cable" not in line
        assert first.exposure()[0] > 0  # the first host is undisturbed
    assert scan_count(path) == 0
    with open_device(device_service) as again:  # once the first is gone, the next connects
        assert again.info is not None


# --- report.json --------------------------------------------------------------------------


def test_finite_json_replaces_every_non_finite_number_only():
    from lamina_host.store.files import finite_json, json_text

    rng = np.random.default_rng(3)
    values = [math.nan, math.inf, -math.inf, 0.0, -1.5, 1e308, 3]
    data = {
        f"k{i}": [float(rng.choice(values[:6])), {"x": values[i % 7]}, (values[i % 7], "s")]
        for i in range(50)
    }
    parsed = strict_json(json_text(data))
    for key, (a, b, c) in data.items():
        got = parsed[key]
        for want, have in ((a, got[0]), (b["x"], got[1]["x"]), (c[0], got[2][0])):
            assert have == (want if math.isfinite(want) else None)
    assert finite_json({"a": "NaN"}) == {"a": "NaN"}


# --- simulated objects beyond any rig ----------------------------------------------------


@pytest.mark.wall_clock
def test_simulated_objects_beyond_the_rig_are_one_line(capsys, tmp_path):
    """hand:scale=1e9 span the device at full CPU and 600 MB, the host silent."""
    beyond = ["hand:scale=1e9", "hand:scale=50", "cylinder:d=1e9", "sphere:d=25,x=1e7"]
    beyond += ["ellipsoid:a=1e-9,b=1,c=1", "bone:scale=1e-9", "cylinder:d=19.05,h=1e6"]
    for spec in beyond:
        start = time.monotonic()
        with pytest.raises(ValueError, match="simulated rig can hold") as caught:
            parse_object(spec)
        assert time.monotonic() - start < 5 and "\n" not in str(caught.value)
    rng = np.random.default_rng(5)
    for _ in range(40):
        d, scale = float(rng.uniform(0.01, MAX_OBJECT_MM)), float(10 ** rng.uniform(-3, 1.5))
        parse_object(f"cylinder:d={d},h={float(rng.uniform(0.01, MAX_OBJECT_MM))}")
        parse_object(f"foot:scale={scale}")
    path, out = tmp_path / "l.sqlite", tmp_path / "out"
    argv = ["scan", "--device", "sim", "--library", str(path), "-o", str(out)]
    line = refused(capsys, *argv, "--object", "hand:scale=1e9")
    assert "the device program exited (status 2)" in line and "scale=1e9" in line
    assert scan_count(path) == 0 and not out.exists()


# --- a full disk ---------------------------------------------------------------------------


def _fill_disk_after(monkeypatch: pytest.MonkeyPatch, stored: int, outputs: bool) -> None:
    """Make the library's disk full after ``stored`` segments, and the outputs' if asked."""
    add = Library.add_segment
    count = {"n": 0}

    def add_segment(self: Library, *args: Any, **kwargs: Any) -> Any:
        count["n"] += 1
        if count["n"] > stored:
            raise sqlite3.OperationalError("database or disk is full")
        return add(self, *args, **kwargs)

    monkeypatch.setattr(Library, "add_segment", add_segment)
    if outputs:

        def savez(*args: Any, **kwargs: Any) -> None:
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(np, "savez_compressed", savez)


@pytest.mark.parametrize(
    ("full", "names"),
    [("both", "library.sqlite"), ("outputs", "cylinder-segments.npz")],
)
def test_a_full_disk_names_what_filled_and_how_to_finish(capsys, monkeypatch, tmp_path, full,
                                                          names):  # fmt: skip
    """The first error was replaced in a finally by cylinder-segments.npz, or 'restore it'."""
    path, out = tmp_path / "library.sqlite", tmp_path / "out"
    cylinder_views = len(DEFAULT_CYLINDER_PLAN.views)
    _fill_disk_after(monkeypatch, 10**9 if full == "outputs" else cylinder_views + 2, outputs=True)
    argv = ["scan", "--device", "sim", "--object", OBJECT, "--library", str(path), "-o", str(out)]
    line = lamina_line(*run(capsys, *argv, "--sections", "1", "--views", "4")[::2])
    assert names in line and "disk is full" in line, line
    assert "lamina scan --resume 1 --device sim" in line and "backup" not in line
    monkeypatch.undo()
    with Library(path) as library:
        assert library.scans()[0].id == 1
    assert held_segments(path) == (4 if full == "outputs" else 2)  # the cylinder's, then 2


def test_the_terminal_ui_says_a_full_disk_is_full_not_damaged():
    from lamina_host.store.files import OutputError, disk_full
    from lamina_host.ui.tui.adapter import user_message

    full = sqlite3.OperationalError("database or disk is full")
    assert disk_full(full) and disk_full(OSError(errno.ENOSPC, "No space left on device"))
    assert disk_full(OutputError("cannot write x.npz (No space left on device)", errno.ENOSPC))
    assert not disk_full(sqlite3.DatabaseError("database disk image is malformed"))
    assert not disk_full(OSError(errno.EACCES, "Permission denied"))
    message = user_message(full)
    assert "disk holding the scan library is full" in message and "backup" not in message
    assert "restore a backup" in user_message(sqlite3.DatabaseError("malformed"))
