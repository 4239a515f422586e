"""Each rule a front end applies is defined once; the lists that mirror another must match.

The command line and the terminal UI refuse exactly what the pipeline refuses (harmonics,
trim, methods and their combinations); the command line offers exactly the pipeline's
method choices; the host spawns a device for exactly the strings the device opens as a
simulator or a replay; the files the terminal UI exports are the library's formats.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import fields
from pathlib import Path

import pytest

from lamina_device.backends import open_hardware
from lamina_host import cli
from lamina_host.link.identity import spawned_source
from lamina_host.reconstruct.assembly import TRIM_RANGE, trim
from lamina_host.reconstruct.efd import HARMONICS_RANGE
from lamina_host.reconstruct.pipeline import OPTION_CHOICES, ProcessOptions
from lamina_host.store.files import OutputError, new_file_problem, write_new_file
from lamina_host.store.library import EXPORT_FORMATS, StoreError, check_new_file
from lamina_host.ui.tui.adapter import UserError, process
from lamina_host.workflow.exports import ALL_FORMATS, EXPORTERS
from lamina_host.workflow.job import EXPORT_NAMES, DeviceTarget, ScanJob
from lamina_shared.device_specs import spawns_device
from lamina_shared.errors import InputError, LaminaError


def _subparser(name: str) -> argparse.ArgumentParser:
    """Return the ``lamina NAME`` parser."""
    sub = next(a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def _cli_refusal(*options: str) -> str | None:
    """Return the command line's refusal of ``lamina scan`` processing options, or None."""
    args = _subparser("scan").parse_args(["--device", "sim", "-o", "out", *options])
    cli._apply_defaults(args)
    try:
        cli._process_options(args)
    except InputError as exc:
        return str(exc)
    return None


def _tui_refusal(harmonics: int | None = None, mesh: str = "contours") -> str | None:
    """Return the terminal UI's refusal of the Results screen's choices, or None.

    A choice it accepts goes on to process, which a session without a scan refuses:
    that refusal means the choices passed.
    """
    with pytest.raises(UserError) as refused:
        job = ScanJob(DeviceTarget(), Path("/nonexistent/never-opened.sqlite"))
        process(job, harmonics, mesh)
    text = str(refused.value)
    return None if text.startswith("nothing to process") else text


@pytest.mark.parametrize("harmonics", [-1, 0, 1, 50, 100, 101])
def test_both_front_ends_refuse_the_harmonics_the_pipeline_refuses(harmonics: int) -> None:
    low, high = HARMONICS_RANGE
    allowed = low <= harmonics <= high
    cli_refusal = _cli_refusal("--harmonics", str(harmonics))
    tui_refusal = _tui_refusal(harmonics)
    pipeline_refusal = ProcessOptions(harmonics=harmonics).problem()
    assert (cli_refusal is None, tui_refusal is None, pipeline_refusal is None) == (allowed,) * 3
    if not allowed:
        assert cli_refusal == f"--harmonics {harmonics} must be between 1 and 100"
        assert tui_refusal == f"harmonics {harmonics} must be between 1 and 100, or blank for auto"


@pytest.mark.parametrize("fraction", [-0.1, 0.0, 0.1, 0.49, 0.5, 0.7, math.nan])
def test_the_command_line_refuses_the_trim_the_assembly_refuses(fraction: float) -> None:
    low, high = TRIM_RANGE
    allowed = low <= fraction < high
    cli_refusal = _cli_refusal("--trim", str(fraction))
    assert (
        (cli_refusal is None)
        == allowed
        == (ProcessOptions(trim_fraction=fraction).problem() is None)
    )
    if allowed:
        assert len(trim([[0.0, 0.0]] * 10, fraction)) == 10 - 2 * math.floor(10 * fraction)
    else:
        assert cli_refusal == f"--trim {fraction} must be at least 0 and below 0.5"
        with pytest.raises(ValueError, match=r"must be at least 0 and below 0\.5"):
            trim([[0.0, 0.0]] * 10, fraction)


def test_the_tui_refuses_a_mesh_method_the_pipeline_has_not() -> None:
    refusal = _tui_refusal(mesh="marching-cubes")
    assert refusal is not None and refusal.startswith("mesh method 'marching-cubes' is not one of")
    assert _tui_refusal(mesh=OPTION_CHOICES["mesh"][-1]) is None


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (("--axis", "centroid", "--angle-correction"), "--angle-correction needs --axis joint"),
        (("--calibration", "dlt", "--distortion", "on"), "--distortion on needs --calibration ml"),
        (("--axis", "centroid"), None),  # the angle correction follows the axis off
        (("--pipeline", "thesis", "--axis", "joint", "--angle-correction"), None),
    ],
)
def test_method_combinations_are_the_pipelines_rule(options: tuple[str, ...], message) -> None:
    assert _cli_refusal(*options) == message


@pytest.mark.parametrize("command", ["scan", "process"])
def test_the_command_line_offers_exactly_the_pipelines_methods(command: str) -> None:
    parser = _subparser(command)
    offered = {a.dest: tuple(a.choices) for a in parser._actions if a.dest in OPTION_CHOICES}
    assert offered, "no method option found"
    assert all(offered[name] == OPTION_CHOICES[name] for name in offered)
    names = {f.name for f in fields(ProcessOptions)}
    assert set(OPTION_CHOICES) <= names and set(cli.OPTION_FLAGS) <= names
    flags = {flag for a in parser._actions for flag in a.option_strings}
    assert set(cli.OPTION_FLAGS.values()) <= flags
    defaults = ProcessOptions()
    assert all(getattr(defaults, name) in allowed for name, allowed in OPTION_CHOICES.items())
    assert ProcessOptions().problem() is None and ProcessOptions.thesis().problem() is None


@pytest.mark.parametrize(
    "spec",
    ["sim", "replay:/no/such/capture", "replay:", "/dev/ttyACM0", "local", "socket://h:1",
     "simulator", "replay", "SIM", "pi"],
)  # fmt: skip
def test_the_host_spawns_a_device_for_exactly_what_the_device_simulates_or_replays(
    spec: str,
) -> None:
    spawned = spawns_device(spec)
    assert (spawned_source(spec, None, 0, None, None) is not None) == spawned
    if spec == "sim" or spec == "pi":
        assert spawned == (spec == "sim")
        return  # opening them starts a simulator or needs the Pi's pins
    with pytest.raises(LaminaError) as refused:  # a bad capture folder, or unknown hardware
        open_hardware(spec)
    assert ("unknown hardware" in str(refused.value)) == (not spawned)


def test_the_tuis_exports_are_the_librarys_formats() -> None:
    assert tuple(Path(name).suffix for name in EXPORT_NAMES) == tuple(EXPORT_FORMATS)
    assert not set(EXPORT_FORMATS) & set(EXPORTERS)
    assert tuple(ALL_FORMATS) == (*EXPORT_FORMATS, *EXPORTERS)


def test_an_export_and_a_new_file_refuse_the_same_paths(tmp_path: Path) -> None:
    (tmp_path / "taken.ply").write_bytes(b"")
    (tmp_path / "dangling.ply").symlink_to(tmp_path / "nowhere")
    for name in ("taken.ply", "dangling.ply", "no/such/folder.ply", "new.ply"):
        path = tmp_path / name
        problem = new_file_problem(path)
        assert (problem is None) == (name == "new.ply")
        if problem is None:
            check_new_file(path)
            write_new_file(path, b"x")
            assert path.read_bytes() == b"x"
            continue
        with pytest.raises(StoreError) as store:
            check_new_file(path)
        with pytest.raises(OutputError) as written:
            write_new_file(path, b"x")
        assert str(store.value) == str(written.value) == problem


@pytest.mark.parametrize("name", ["taken.pdf", "no/such/folder/report.pdf"])
def test_lamina_report_refuses_what_an_export_refuses_before_measuring(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    (tmp_path / "taken.pdf").write_bytes(b"")
    path = tmp_path / name
    library = tmp_path / "never-opened.sqlite"  # the refusal comes before the library
    assert cli.main(["report", "1", "-o", str(path), "--library", str(library)]) == 2
    assert capsys.readouterr().err == f"lamina: {new_file_problem(path)}\n"
    assert not library.exists()
