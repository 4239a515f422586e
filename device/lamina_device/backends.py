"""The hardware factory: picks the backend the device program drives by name.

``pi`` is the scanner box (:func:`lamina_device.hardware.open_pi`); ``sim`` the virtual
rig (:mod:`lamina_device.sim.backend`); ``replay:DIR`` a recorded capture standing in for
the camera (:mod:`lamina_device.replay`). Every kind comes with its laser watchdog running.
"""

from __future__ import annotations

from pathlib import Path

from gpiozero.exc import GPIOZeroError
from gpiozero.pins import Factory

from lamina_device.camera import CameraError
from lamina_device.config import ConfigError, load_config
from lamina_device.hardware import Hardware, HardwareError, open_pi
from lamina_device.replay import open_replay
from lamina_device.sim.backend import open_sim
from lamina_shared.device_specs import SIM, replay_folder


def open_hardware(
    spec: str,
    object_spec: str | None = None,
    seed: int = 0,
    noise: str = "thesis",
    config_path: Path | str | None = None,
    pin_factory: Factory | None = None,
    rig: str = "thesis",
    sway: str = "none",
    lift_error_percent: float | None = None,
) -> Hardware:
    """Return the hardware named by ``spec``: ``sim``, ``replay:DIR`` or ``pi``.

    Args:
        spec: which hardware.
        object_spec: the simulated object (sim only).
        seed: simulation noise seed (sim only).
        noise: one of ``NOISE_PRESETS``: ``thesis``, ``harsh`` or ``none`` (sim only).
        config_path: the TOML configuration (the packaged default if None; the simulator
            takes its timing and continuous settings from it).
        pin_factory: gpiozero pin factory for ``pi`` (None: gpiozero's own choice).
        rig: the simulated rig's geometry, ``thesis`` or ``limb`` (sim only).
        sway: how the simulated object moves while scanned, e.g. ``patient`` (sim only).
        lift_error_percent: the simulated lift's scale error in % (sim only; None: the
            noise preset's).

    Raises:
        HardwareError: naming what is wrong and what to do.
    """
    if spec == SIM:
        try:
            config = load_config(config_path) if config_path is not None else None
        except ConfigError as exc:
            raise HardwareError(str(exc)) from None
        return open_sim(
            object_spec,
            seed,
            noise,
            rig,
            sway=sway,
            lift_error_percent=lift_error_percent,
            config=config,
        )
    if (folder := replay_folder(spec)) is not None:
        if not folder:
            raise HardwareError("replay needs a capture folder: --hardware replay:DIR")
        return open_replay(Path(folder))
    if spec == "pi":
        try:
            config = load_config(config_path)
            return open_pi(config, str(config_path or "(default)"), pin_factory)
        except (ConfigError, CameraError) as exc:
            raise HardwareError(str(exc)) from None
        except GPIOZeroError as exc:
            raise HardwareError(
                f"cannot drive the GPIO pins: {exc}; on the Pi install python3-lgpio "
                "(GPIOZERO_PIN_FACTORY=lgpio), off the Pi use GPIOZERO_PIN_FACTORY=mock"
            ) from None
    raise HardwareError(
        f"unknown hardware {spec!r}: use 'sim', 'replay:DIR' (a recorded capture folder) or 'pi'"
    )
