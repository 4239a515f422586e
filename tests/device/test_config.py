"""The TOML configuration: the packaged default is valid; every problem is listed at once."""

from __future__ import annotations

import subprocess
import sys
import tomllib

import pytest

from lamina_device.config import ConfigError, default_config_path, load_config, parse_config


def default_data() -> dict:
    return tomllib.loads(default_config_path().read_text())


def test_packaged_default_loads_with_the_documented_values():
    config = load_config()
    assert config.laser.pin == 17 and config.laser.active_high
    # 8 microsteps (wiring.md): a continuous turn at 360 deg/s is 6400 steps/s, within lgpio's PWM.
    assert config.turntable.full_steps_per_rev * config.turntable.microsteps == 1600
    assert config.turntable.continuous_speed_deg_s == 360.0
    assert config.camera.readout_us == 7957
    assert config.lift.limit_pin == 6 and config.lift.home_mm <= config.lift.min_mm
    assert (config.camera.width, config.camera.height) == (1536, 864)
    assert config.safety.laser_max_on_s == 2.0
    assert config.board.inner_corners == (13, 11) and config.board.origin_mm == (-12.0, -10.0)
    # The cylinder at three heights 3 mm apart: a steadier turntable axis (calibration-cylinder.md).
    assert (config.plan.cylinder_sections, config.plan.cylinder_pitch_mm) == (3, 3.0)


def test_every_problem_is_listed_at_once():
    data = default_data()
    data["lift"]["enable_pin"] = 16  # the turntable's enable pin
    data["lift"]["speed"] = 3  # unknown key
    del data["camera"]["gain"]  # missing value
    data["turntable"]["microsteps"] = 3  # not a microstep setting
    data["lift"]["lead_mm"] = "two"  # wrong type
    data["safety"]["laser_max_on_s"] = 600.0  # out of range
    data["board"]["inner_corners"] = [9]  # wrong shape
    data["laser"]["pin"] = 40  # not a GPIO
    data["extra"] = {}
    with pytest.raises(ConfigError) as info:
        parse_config(data, "box.toml")
    assert sorted(info.value.problems) == sorted(
        [
            "[extra]: unknown section",
            "[laser] pin: 40 is not a GPIO pin number (BCM 0..27)",
            "[turntable] microsteps: 3 is not one of 1, 2, 4, 8, 16, 32, 64, 128, 256",
            "[lift] speed: unknown key",
            "[lift] lead_mm: expected a number, got 'two'",
            "[camera] gain: missing value (a number)",
            "[safety] laser_max_on_s: 600.0 is outside 0.01..60",
            "[board] inner_corners: expected a list of 2 integers, got [9]",
            "GPIO16 is used twice: by [turntable] enable_pin and [lift] enable_pin",
        ]
    )
    assert str(info.value).startswith("config box.toml: 9 problems: ")


def test_values_that_disagree_are_reported():
    data = default_data()
    data["lift"]["min_mm"], data["lift"]["max_mm"] = 50.0, 40.0
    data["camera"]["exposure_us"] = 20000
    with pytest.raises(ConfigError) as info:
        parse_config(data)
    problems = " | ".join(info.value.problems)
    assert "min_mm 50.0 must be below max_mm 40.0" in problems
    assert "exposure_us 20000 must fit in frame_duration_us 8333" in problems
    assert "outside the lift's 50..40 mm" in problems


def check_config(path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "lamina_device", "check-config", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_check_config_command(tmp_path):
    good = check_config(default_config_path())
    assert good.returncode == 0 and good.stdout.strip().endswith(": OK"), good.stderr
    bad_file = tmp_path / "box.toml"
    bad_file.write_text(
        default_config_path().read_text().replace("pin = 17", "pin = 19").replace("gain = 2.0", "")
    )
    bad = check_config(bad_file)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.splitlines() == [
        f"lamina-device: config {bad_file} has 2 problems:",
        "  - [camera] gain: missing value (a number)",
        "  - GPIO19 is used twice: by [laser] pin and [lift] step_pin",
    ]
    broken = tmp_path / "broken.toml"
    broken.write_text("[laser\npin = 17\n")
    result = check_config(broken)
    assert result.returncode == 2 and "not valid TOML" in result.stderr
    missing = check_config(tmp_path / "nope.toml")
    assert missing.returncode == 2 and "cannot read it" in missing.stderr


def test_extraction_settings_come_from_the_extract_table():
    from lamina_device.extract import ExtractSettings

    assert load_config().extract == ExtractSettings()  # the packaged table states the defaults
    data = default_data()
    data["extract"] = {"method": "thinning", "threshold": 40, "min_chain_px": 3}
    config = parse_config(data, "box.toml")
    assert config.extract == ExtractSettings(method="thinning", threshold=40.0, min_chain_px=3)
    del data["extract"]
    assert parse_config(data, "box.toml").extract == ExtractSettings()  # the table is optional


def test_every_extraction_problem_is_listed():
    data = default_data()
    data["extract"] = {"method": "sobel", "noise_gate": 1, "speed": 2}
    with pytest.raises(ConfigError) as info:
        parse_config(data, "box.toml")
    assert info.value.problems == [
        "[extract]: takes no argument 'speed'",
        "[extract].method: one of cog, thinning is required, found 'sobel'",
        "[extract].noise_gate: true or false is required, found 1",
    ]
    data["extract"] = {"power": 0, "min_width_px": 9, "max_width_px": 4}
    with pytest.raises(ConfigError) as info:
        parse_config(data, "box.toml")
    assert info.value.problems == [
        "[extract] power 0.0 is not in (0, 8]",
        "[extract] min_width_px 9 and max_width_px 4 do not satisfy "
        "1 <= min_width_px <= max_width_px <= 255",
    ]


def test_keys_added_later_may_be_left_out_and_keep_the_older_behaviour():
    """A box's configuration from before continuous scans and the three-height cylinder stays
    valid: stop-and-go only, the cylinder at one height."""
    data = default_data()
    del data["turntable"]["continuous_speed_deg_s"]
    del data["camera"]["readout_us"]
    del data["plan"]["cylinder_sections"], data["plan"]["cylinder_pitch_mm"]
    config = parse_config(data)
    assert config.turntable.continuous_speed_deg_s == 0.0
    assert config.plan.cylinder_sections == 1  # the cylinder at one height, as before
    assert config.camera.readout_s == config.camera.frame_duration_us * 1e-6


def test_a_continuous_speed_beyond_the_pulse_timer_or_a_readout_beyond_the_frame_is_refused():
    data = default_data()
    data["turntable"]["continuous_speed_deg_s"] = 600.0  # 10,667 steps/s at 8 microsteps
    data["camera"]["readout_us"] = 9000
    with pytest.raises(ConfigError) as caught:
        parse_config(data)
    text = str(caught.value)
    assert "continuous_speed_deg_s 600 asks for 10667 steps/s" in text
    assert "readout_us 9000 must fit in frame_duration_us 8333" in text


def test_laser_off_frames_a_turn_later_need_a_frame_period_that_divides_the_turn():
    """The shipped table turns in 6400 steps of 156 us (998.4 ms): at 8333 us a frame a
    turn later misses the angle by 0.56 degrees, and the message names the period that
    meets it; with that period the configuration loads."""
    data = default_data()
    assert load_config().turntable.continuous_off_frames == "interleaved"
    data["turntable"]["continuous_off_frames"] = "next-turn"
    with pytest.raises(ConfigError) as caught:
        parse_config(data)
    text = str(caught.value)
    assert "a turn of the table takes 998.4 ms, 119.81 frames of 8333 us" in text
    assert "misses the angle by 0.56 degrees" in text
    assert "set [camera] frame_duration_us = 8320 (120 frames a turn)" in text
    data["camera"]["frame_duration_us"] = 8320
    assert parse_config(data).turntable.continuous_off_frames == "next-turn"
    data["turntable"]["continuous_off_frames"] = "later"
    with pytest.raises(ConfigError, match="'later' is not one of 'interleaved', 'next-turn'"):
        parse_config(data)


def test_the_lift_reference_is_an_optional_table_checked_whole():
    """``[lift_reference]`` (the calibration cylinder's grooves): left out, none; given, the
    four keys, its marks in order and inside the lift's travel, else one line each."""
    from lamina_shared.types import LiftReference

    data = tomllib.loads(default_config_path().read_text())
    assert parse_config(data).lift_reference is None
    reference = {"marks_mm": [22.5, 122.5], "spacing_mm": 100.0, "flank_slope": 1.0,
                 "depth_mm": 5.0}  # fmt: skip
    data["lift_reference"] = reference
    assert parse_config(data).lift_reference == LiftReference((22.5, 122.5), 100.0, 1.0, 5.0)
    for wrong, says in (
        ({"marks_mm": [22.5], "spacing_mm": 100.0}, "the keys marks_mm, spacing_mm"),
        (reference | {"marks_mm": [122.5, 22.5]}, "upper mark above the lower one"),
        (reference | {"marks_mm": [22.5, 222.5]}, "must lie within the lift's 0..150 mm"),
    ):
        data["lift_reference"] = wrong
        with pytest.raises(ConfigError, match=says):
            parse_config(data)
