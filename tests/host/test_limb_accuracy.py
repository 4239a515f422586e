"""Limb-scale accuracy (issue #13): a residual limb's rounded end, scanned end to end.

The stump phantom at limb scale (``stump:scale=5``) moved down 50 mm so that six sections
10 mm apart cover the last straight centimetre and the whole rounded end, on the limb rig
with the harsh preset and 8 views: the same geometry as the top of ``bench_limb``'s full
stump, at half its size. The measurements are compared with the simulator's truth by the
bench's own functions (``tests/benchmarks/bench_limb.py``).
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from lamina_device.sim import parse_object
from lamina_host.reconstruct.axis import RADIUS_SPREAD_WARNING

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_limb.py"
SPEC, SECTIONS = "stump:scale=5,z=-50", 6
# The scan (a subprocess rendering 1536x864 frames) takes 1.5-2.5 minutes on two cores.
pytestmark = pytest.mark.timeout(600)


def bench_limb() -> ModuleType:
    """Load the limb bench module (its truths and measurements)."""
    spec = importlib.util.spec_from_file_location("bench_limb", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("bench_limb", module)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def stump(tmp_path_factory: pytest.TempPathFactory) -> tuple[ModuleType, dict, Path]:
    """Scan the stump's end once; return the bench module, the figures and the output."""
    bench = bench_limb()
    tmp = tmp_path_factory.mktemp("stump")
    _, error = bench._scan(SPEC, SECTIONS, tmp / "scan", tmp / "library.sqlite")
    assert error == ""
    report = json.loads((tmp / "scan" / "report.json").read_text())
    return bench, bench.measure(SPEC, report), tmp / "scan"


def test_the_stump_volume_and_surface_are_within_the_clinical_limits(stump) -> None:
    """Volume within 0.5 % of the truth over the scanned range; contours within 0.08 mm."""
    bench, figures, out = stump
    print({k: v for k, v in figures.items() if k != "levels"})
    assert abs(figures["volume_error_percent"]) <= 0.5
    # Straight lines between sections cut the dome's corners (about -0.8 % here).
    assert figures["linear_volume_error_percent"] < figures["volume_error_percent"]
    distance = bench.surface_distance(parse_object(SPEC), bench.points_ply(out))
    assert distance["aligned_mm"] <= 0.08 and distance["direct_mm"] <= 0.08


def test_every_level_circumference_is_within_1_mm(stump) -> None:
    """Every level within 1 mm, the distal one too (the top section, 5 mm below the apex).

    The distal level sits on the top section, where the sheet meets the dome at grazing
    incidence; it read 1.1 mm too large while the phantom's dome was faceted in 9 degree
    steps (README, Accuracy at limb scale).
    """
    _, figures, _ = stump
    levels = figures["levels"]
    scale = 1.0 + figures["lift_measured_percent"] / 100.0  # the lift as calibrated
    assert levels[0]["offset_mm"] == 0.0 and levels[0]["z_mm"] == pytest.approx(50.0 * scale)
    assert len(levels) == 3
    for level in levels:
        assert abs(level["error_mm"]) <= 1.0, level


def test_the_lift_is_calibrated_on_the_cylinders_grooves(stump) -> None:
    """The harsh preset's lift runs 0.2 % long: the host measures it on the two grooves of
    the limb rig's calibration cylinder (their sections among the cylinder's views) and
    report.json says so; the section heights it gives are then the true ones (the span
    within 0.05 %), so the volume error is the host's own, not the lift's."""
    _, figures, out = stump
    report = json.loads((out / "report.json").read_text())
    lift = report["lift"]
    print(lift)
    assert lift["calibrated"] and lift["applied"] and lift["warnings"] == []
    assert lift["error_percent"] == pytest.approx(0.2, abs=0.05)
    assert lift["reference"]["marks_mm"] == [22.5, 162.5] and lift["points"][0] > 200
    assert abs(figures["lift_span_error_percent"]) < 0.05
    assert abs(figures["volume_error_percent"]) < 0.2


def test_the_wide_lens_is_found_on_the_board_with_the_defaults(stump) -> None:
    """The harsh lens (barrel, ~4 px at the corners of the 1536x864 image), scanned with the
    default processing: the coefficient is kept, the corners' residual falls to their noise
    and the calibration cylinder's arcs agree between views within the axis warning's 2 %
    (issue 18 saw 5.7 % without it; ~1.4 % here is the harsh stripe noise on short arcs).
    The wide lens's figures are in ``bench_lens``."""
    _, _, out = stump
    report = json.loads((out / "report.json").read_text())
    lens = report["calibration"]["distortion"]
    assert lens["mode"] == "auto" and lens["applied"] and lens["division_k"] < 0.0
    assert lens["rms_px_with"] < 0.5 * lens["rms_px_without"]
    radii = np.asarray(report["axis"]["arc_radii_mm"])
    spread = (radii.max() - radii.min()) / radii.mean()
    print(f"lens k {lens['division_k']:.5f}, cylinder arc radii spread {spread:.2%}")
    assert spread < RADIUS_SPREAD_WARNING
    assert not any("radii vary" in w for w in report["warnings"])
