"""The lift is calibrated, not trusted (issue #23): two grooves on the calibration cylinder.

The arithmetic against exact arcs (a known scale comes back, biases common to both grooves
cancel, bad data are refused in one line and the lift is then trusted), the reference on
the wire and in the library, and the simulated limb rig's grooved cylinder. A rendered
scan's lift calibration (the harsh preset's lift, 0.2 % long) is checked end to end on
the limb-scale stump of ``test_limb_accuracy``; ``bench_lift`` scans the limb phantoms
with the lift 0.5 % short and long.
"""

from __future__ import annotations

import json
import math
import sqlite3
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from lamina_device.sim import Rig
from lamina_device.sim.objects import Cylinder, grooved_cylinder
from lamina_host.reconstruct.axis import fit_circle
from lamina_host.reconstruct.calibration import calibrate_lift
from lamina_host.reconstruct.pipeline import lift_sections
from lamina_host.store.library import SCHEMA_VERSION, Library
from lamina_shared.messages import Welcome
from lamina_shared.protocol import PROTOCOL_VERSION
from lamina_shared.types import BoardSpec, LiftReference, ScanPlan, Segment

REFERENCE = LiftReference((22.5, 162.5), 140.0, 1.0, 5.0)
RADIUS = 30.0
GROOVES = (25.0, 165.0)


def flank_radius(true_z: float, groove: float) -> float:
    """The radius of a 90 degree V-groove's lower flank at height ``true_z``."""
    return RADIUS - (true_z - (groove - 5.0))


def circle(points: np.ndarray) -> tuple[float, float]:
    """The pipeline's circle fit: radius and RMS residual."""
    fitted = fit_circle(points)
    return fitted.r, fitted.rms_mm


def arcs(radius: float, views: int = 4, bias: float = 0.0, centre=(10.0, -6.0)) -> list:
    """Four 100 degree arcs of a circle, as the views of one section give them."""
    out = []
    for k in range(views):
        t = np.radians(90.0 * k + np.linspace(-50.0, 50.0, 200))
        r = radius + bias
        out.append(np.column_stack([centre[0] + r * np.cos(t), centre[1] + r * np.sin(t)]))
    return out


@pytest.mark.parametrize("error", [-0.005, 0.0, 0.005])
def test_the_scale_comes_back_from_the_two_flank_radii(error: float) -> None:
    """Lifts 0.5 % short, exact and 0.5 % long: the scale within 1e-9, a common radial
    bias (the stripe's centre on a flank, the cylinder's diameter) cancelling."""
    scale = 1.0 + error
    radii = [flank_radius(scale * c, g) for c, g in zip(REFERENCE.marks_mm, GROOVES, strict=True)]
    for bias in (0.0, 0.08):
        lift = calibrate_lift([arcs(r, bias=bias) for r in radii], REFERENCE, RADIUS, circle)
        assert lift.applied and lift.warnings == ()
        assert lift.scale == pytest.approx(scale, abs=1e-9)
        assert lift.error_percent == pytest.approx(100 * error, abs=1e-7)
    report = lift.to_dict()
    assert report["applied"] and report["reference"]["spacing_mm"] == 140.0
    json.dumps(report, allow_nan=False)


def test_bad_lift_data_leave_the_lift_trusted_and_say_why() -> None:
    """A section off the flank's straight middle, a section without two views, and a
    reference that would mean a 10 % error: not applied, one line each."""
    good = flank_radius(22.5, 25.0)
    off = calibrate_lift([arcs(29.5), arcs(flank_radius(162.5, 165.0))], REFERENCE, RADIUS, circle)
    assert not off.applied and "off the straight middle" in off.warnings[0]
    blind = calibrate_lift([arcs(good, views=1), arcs(good)], REFERENCE, RADIUS, circle)
    assert not blind.applied and "1 view(s)" in blind.warnings[0]
    json.dumps(blind.to_dict(), allow_nan=False)  # NaN radii are written as null
    wrong = replace(REFERENCE, spacing_mm=154.0)
    far = calibrate_lift([arcs(good), arcs(flank_radius(162.5, 165.0))], wrong, RADIUS, circle)
    assert not far.applied and "+10.00 %" in far.warnings[0] and "trusted" in far.warnings[0]


def test_the_reference_travels_in_the_welcome_and_is_kept_with_the_calibration(
    tmp_path: Path,
) -> None:
    """WELCOME carries it (a malformed one is a listed problem); the library stores it
    with the scan's calibration, and a library of schema 5 gains the column, empty."""
    welcome = Welcome(PROTOCOL_VERSION, hardware="sim", image_size=(8, 8), lift_reference=REFERENCE)
    assert Welcome.from_wire(welcome.to_wire()).lift_reference == REFERENCE
    wire = welcome.to_wire() | {"lift_reference": {"marks_mm": [5, 1], "spacing_mm": 1}}
    with pytest.raises(ValueError, match=r"welcome\.lift_reference"):
        Welcome.from_wire(wire)
    path = tmp_path / "library.sqlite"
    plans = {"object": ScanPlan.regular(1, 1.0, 4)}
    board = BoardSpec((5, 4), 2.0, (0.0, 0.0))
    with Library(path) as library:
        old = library.create_scan("P1", plans)
        library.save_calibration(old, np.zeros((8, 8), np.uint8), board, 60.0)
    with sqlite3.connect(path) as db:  # back to schema 5: no lift reference column
        db.execute("ALTER TABLE calibrations DROP COLUMN lift_reference")
        db.execute("PRAGMA user_version=5")
    with Library(path) as library:
        assert library.calibration(old).lift_reference is None
        new = library.create_scan("P1", plans)
        library.save_calibration(new, np.zeros((8, 8), np.uint8), board, 60.0, None, REFERENCE)
        assert library.calibration(new).lift_reference == REFERENCE
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION


def test_the_cylinder_views_split_between_axis_and_marks() -> None:
    """Views at the marks' heights calibrate the lift; the others the axis."""
    plan = REFERENCE.plan(ScanPlan.regular(1, 2.0, 8))
    empty = np.zeros(0)
    views = [Segment("cylinder", v.section, k, v.z_mm, v.angle_deg, empty, empty, empty, empty)
             for k, v in enumerate(plan.views)]  # fmt: skip
    axis_views, marks = lift_sections(views, REFERENCE)
    assert [v.z_mm for v in axis_views] == [0.0] * 8
    assert [[v.z_mm for v in m] for m in marks] == [[22.5] * 8, [162.5] * 8]
    assert [v.angle_deg for v in marks[1]] == [45.0 * k for k in range(8)]
    assert lift_sections(views, None) == (views, [])


def test_the_grooved_cylinder_has_its_flanks_where_the_reference_says() -> None:
    """The simulated limb rig's cylinder: 60 mm, 45 degree flanks, grooves 140 mm apart; a
    ray meets the flank where the profile says, with the cone's normal, and the wall away
    from the grooves exactly as the plain cylinder does."""
    rig = Rig.limb()
    assert rig.lift_reference() == REFERENCE
    solid = grooved_cylinder(60.0, 185.0, 10.0, -6.0, -5.0, GROOVES, 5.0)
    for z, expected in ((0.0, 30.0), (22.5, 27.5), (25.0, 25.0), (163.0, 27.0)):
        (outline,) = solid.section_outline(z)
        radius = np.hypot(outline[:, 0] - 10.0, outline[:, 1] - -6.0)
        assert radius == pytest.approx(expected, abs=1e-9)
    assert solid.section_outline(181.0) == []
    origins = np.array([[10.0, -300.0, 22.5], [10.0, -300.0, 0.0], [10.0, -6.0, 400.0]])
    dirs = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    t, normal = solid.raycast(origins, dirs)
    assert t == pytest.approx([300.0 - 6.0 - 27.5, 300.0 - 6.0 - 30.0, 400.0 - 180.0])
    s2 = math.sqrt(0.5)
    assert normal == pytest.approx(np.array([[0.0, -s2, s2], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]))
    plain_t, plain_n = Cylinder(60.0, 185.0, 10.0, -6.0, -5.0).raycast(origins[1:2], dirs[1:2])
    assert t[1] == plain_t[0] and normal[1] == pytest.approx(plain_n[0])
