"""Backends in their places: Pi modules without the simulator, axis limits, shared presets."""

from __future__ import annotations

import argparse
import subprocess
import sys

import numpy as np
import pytest
from gpiozero.pins.mock import MockFactory

from lamina_device import cli as device_cli
from lamina_device.backends import open_hardware
from lamina_device.config import default_config_path
from lamina_device.hardware import HardwareError
from lamina_device.motion import MotionError, StepperLift, StepperTurntable
from lamina_device.operations import axes_of
from lamina_device.sim import SIM_LIFT_TRAVEL_MM, Mechanics, NoiseModel, Rig
from lamina_host import cli as host_cli
from lamina_shared.capture import CaptureWriter
from lamina_shared.errors import LaminaError
from lamina_shared.limits import DeviceLimits
from lamina_shared.messages import AxesInfo
from lamina_shared.presets import NOISE_PRESETS, RIG_PRESETS
from lamina_shared.types import BoardSpec, ScanPlan


def test_the_pi_modules_load_neither_the_simulator_nor_the_replay():
    code = (
        "import sys\n"
        "import lamina_device.camera, lamina_device.motion, lamina_device.hardware\n"
        "import lamina_device.server, lamina_device.acquisition\n"
        "print(sorted(m for m in sys.modules if m.startswith(('lamina_device.sim', "
        "'lamina_device.replay'))))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert result.stdout.strip() == "[]"


def test_the_simulated_axes_declare_their_limits_and_refuse_to_leave_them():
    hardware = open_hardware("sim", "cylinder:d=19.05", noise="none")
    try:
        assert axes_of(hardware) == AxesInfo(0.0, SIM_LIFT_TRAVEL_MM, None, None)
        assert axes_of(hardware).to_wire()["turntable"]["continuous"] is True
        hardware.lift.move_to(SIM_LIFT_TRAVEL_MM)
        with pytest.raises(MotionError, match=r"outside 0\.\.200 mm") as refused:
            hardware.lift.move_to(SIM_LIFT_TRAVEL_MM + 0.5)
        assert isinstance(refused.value, LaminaError)
        assert hardware.lift.z_mm == SIM_LIFT_TRAVEL_MM
        with pytest.raises(MotionError, match="finite"):
            hardware.turntable.move_to(float("nan"))
        hardware.turntable.move_to(725.0)  # continuous: any finite angle
        assert hardware.turntable.angle_deg == 725.0
    finally:
        hardware.close()


def test_the_stepper_axes_declare_the_configured_soft_limits(pi_kit):
    factory = MockFactory()
    config = pi_kit.config
    lift = StepperLift(config.lift, factory)
    turntable = StepperTurntable(config.turntable, factory)
    try:
        assert (lift.min_mm, lift.max_mm) == (config.lift.min_mm, config.lift.max_mm)
        assert (turntable.min_deg, turntable.max_deg) == (None, None)
        with pytest.raises(MotionError, match="soft limits"):
            lift.move_to(config.lift.max_mm + 1.0)
    finally:
        lift.close()
        turntable.close()


def test_the_replay_lift_reaches_every_height_a_capture_may_name(tmp_path):
    frame = np.zeros((48, 64), np.uint8)
    writer = CaptureWriter(tmp_path / "cap", (64, 48), {"object": "test"})
    writer.add_grid(frame, BoardSpec((5, 4), 2.0, (-5.0, -4.0)))
    for k, view in enumerate(ScanPlan.regular(2, 2.0, 2).views):
        writer.add_view("object", view, k % 2, frame, frame)
    writer.close()
    hardware = open_hardware(f"replay:{tmp_path / 'cap'}")
    try:
        limits = axes_of(hardware)
        assert limits == AxesInfo(0.0, DeviceLimits().max_z_mm, None, None)
    finally:
        hardware.close()


def _choices(parser: argparse.ArgumentParser, command: str, option: str) -> tuple[str, ...]:
    """Return the choices of ``option`` under the sub-command ``command``."""
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    sub = commands.choices[command]
    return tuple(next(a.choices for a in sub._actions if option in a.option_strings))


def test_both_command_lines_offer_the_shared_rig_and_noise_presets():
    device, host = device_cli.build_parser(), host_cli.build_parser()
    for command in ("serve", "record"):
        assert _choices(device, command, "--rig") == RIG_PRESETS
        assert _choices(device, command, "--noise") == NOISE_PRESETS
    assert _choices(host, "scan", "--rig") == RIG_PRESETS
    assert _choices(host, "scan", "--noise") == NOISE_PRESETS


def test_every_preset_name_builds_its_own_model():
    rigs = [Rig.preset(name) for name in RIG_PRESETS]
    assert len(set(rigs)) == len(RIG_PRESETS)
    assert rigs[0] == Rig() and rigs[1] == Rig.limb()
    models = [(NoiseModel.preset(name), Mechanics.preset(name)) for name in NOISE_PRESETS]
    assert len(set(models)) == len(NOISE_PRESETS)
    with pytest.raises(ValueError, match=", ".join(RIG_PRESETS)):
        Rig.preset("desk")


def test_the_simulator_runs_on_a_given_configuration_and_refuses_a_bad_one(tmp_path):
    """``--hardware sim --config FILE``: the simulated box takes its timing and continuous
    settings from the file (here laser-off frames a turn later); a file with a problem is
    refused by name, as the box's would be."""
    text = default_config_path().read_text()
    good = text.replace(
        'continuous_off_frames = "interleaved"', 'continuous_off_frames = "next-turn"'
    ).replace("frame_duration_us = 8333", "frame_duration_us = 8320")
    path = tmp_path / "box.toml"
    path.write_text(good)
    hardware = open_hardware("sim", config_path=path)
    try:
        assert hardware.turntable.off_frames == "next-turn"
        assert hardware.timing is not None and hardware.timing.camera.frame_duration_us == 8320
        assert hardware.camera.frame_timing.period_s == pytest.approx(8320e-6)
    finally:
        hardware.close()
    path.write_text(good.replace("frame_duration_us = 8320", "frame_duration_us = 8333"))
    with pytest.raises(HardwareError, match="set \\[camera\\] frame_duration_us = 8320"):
        open_hardware("sim", config_path=path)
    shipped = open_hardware("sim")
    try:
        assert shipped.turntable.off_frames == "interleaved"
    finally:
        shipped.close()
