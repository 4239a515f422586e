"""hardware/ stays true to the device: wiring table vs default config, BOM budget, service unit."""

import configparser
import csv
import re
import shlex
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HARDWARE = ROOT / "hardware"
CONFIG = ROOT / "device" / "lamina_device" / "default_config.toml"


def wiring_pins():
    """Return {config key: BCM number} from the signal table in wiring.md."""
    pins = {}
    for line in (HARDWARE / "wiring.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) > 3 and cells[1].startswith("`") and cells[2].startswith("GPIO"):
            pins[cells[1].strip("`")] = int(cells[2].removeprefix("GPIO"))
    return pins


def test_wiring_table_matches_the_default_config():
    config = tomllib.loads(CONFIG.read_text())
    expected = {
        f"{section}.{key}": value
        for section, table in config.items()
        if isinstance(table, dict)
        for key, value in table.items()
        if key == "pin" or key.endswith("_pin")
    }
    assert expected, "no pins found in the default config"
    assert wiring_pins() == expected


def test_every_active_low_enable_has_a_pull_up_and_the_laser_a_pull_down():
    config = tomllib.loads(CONFIG.read_text())
    text = (HARDWARE / "wiring.md").read_text()
    for axis in ("turntable", "lift"):
        assert config[axis]["enable_active_high"] is False
        pin = config[axis]["enable_pin"]
        assert re.search(rf"\| {axis} EN \(GPIO{pin}\) \| 4\.7 kΩ \| 3\.3 V \|", text)
    assert config["laser"]["active_high"] is True
    assert re.search(rf"\| laser \(GPIO{config['laser']['pin']}\) \| 10 kΩ \| GND", text)


def test_bill_of_materials_stays_below_150_usd_without_the_pi():
    rows = list(csv.DictReader((HARDWARE / "bom.csv").open()))
    assert all(r["part_number"] and r["description"] for r in rows)
    assert not any("raspberry pi 4" in r["description"].lower() for r in rows)
    total = sum(float(r["unit_usd"]) * int(r["qty"]) for r in rows)
    assert 50 < total < 150
    assert f"{total:.0f}" in (HARDWARE / "README.md").read_text()


def test_service_starts_the_device_on_the_gadget_port_and_restarts_it():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str
    unit.read(HARDWARE / "systemd" / "lamina-device.service")
    command = shlex.split(unit["Service"]["ExecStart"])
    assert command[0].endswith("/lamina-device")
    assert command[1:] == ["serve", "--port", "/dev/ttyGS0", "--hardware", "pi"]
    # A shutdown request ends the program with status 0: it must come back all the same.
    assert unit["Service"]["Restart"] == "always"
    assert unit["Service"]["KillSignal"] == "SIGTERM"
    assert unit["Install"]["WantedBy"] == "multi-user.target"


def read_unit(name: str) -> configparser.ConfigParser:
    """Return a systemd unit of hardware/systemd/ as sections of keys."""
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str
    unit.read(HARDWARE / "systemd" / name)
    return unit


def test_box_alone_units_run_commands_the_programs_accept():
    """The local device service and the browser UI: their command lines parse as written."""
    from lamina_device.cli import build_parser as device_parser
    from lamina_host.cli import build_parser as host_parser

    device = read_unit("lamina-device-local.service")
    command = shlex.split(device["Service"]["ExecStart"])
    assert command[0].endswith("/lamina-device")
    args = device_parser().parse_args(command[1:])
    assert (args.command, args.listen, args.port, args.hardware) == ("serve", "local", None, "pi")
    assert device["Unit"]["Conflicts"] == "lamina-device.service"
    assert device["Service"]["Restart"] == "always"

    ui = read_unit("lamina-ui.service")
    command = shlex.split(ui["Service"]["ExecStart"])
    assert command[0].endswith("/lamina")
    args = host_parser().parse_args(command[1:])
    assert (args.command, args.device, args.host) == ("serve-ui", "local", "127.0.0.1")
    assert not args.allow_remote
    assert ui["Unit"]["After"] == "lamina-device-local.service"
