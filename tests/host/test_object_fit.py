"""Issue 24: an object too large for the rig is refused at its first view, in one line.

Before, a limb-sized object on the thesis rig acquired every view and failed only in
processing. The check (:func:`lamina_host.workflow.checks.check_object_fits`) is the
workflow's, so the command line and the terminal UI apply it alike; the plan presets are
cut to the lift's travel and refused before any view when their object is wider than the
camera's view.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lamina_host import cli
from lamina_host.store.library import Library
from lamina_host.workflow.checks import (
    FIT_OUTSIDE_SHARE,
    PLAN_PRESETS,
    ObjectTooLarge,
    check_object_fits,
    check_preset_fits,
    preset_plan,
)
from lamina_shared.messages import AxesInfo


def test_a_limb_on_the_thesis_rig_stops_after_its_first_view(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--object arm:scale=5` without `--rig limb`: one line, one object view, no traceback."""
    library = tmp_path / "library.sqlite"
    status = cli.main(
        ["scan", "--device", "sim", "--object", "arm:scale=5", "--sections", "2", "--pitch",
         "2", "--views", "4", "-o", str(tmp_path / "out"), "--library", str(library)]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert status == 2, err
    (line,) = [x for x in err.splitlines() if x.startswith("lamina: ")]
    assert "does not fit the camera's view" in line and "wider view" in line
    assert "Traceback" not in err
    with Library(library) as opened:
        (scan,) = opened.scans()
    assert (scan.received, scan.views, scan.status) == (1, 8, "acquiring")


@pytest.mark.parametrize("seed", range(20))
def test_the_fit_rule_on_random_views(seed: int) -> None:
    """Random views: refused exactly when more than half the points lie beyond the disc."""
    rng = np.random.default_rng(seed)
    field = float(rng.uniform(10.0, 120.0))
    n = int(rng.integers(1, 400))
    radii = rng.uniform(0.0, 2.0 * field, n)
    angles = rng.uniform(0.0, 2.0 * math.pi, n)
    points = np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)
    outside = int(np.count_nonzero(np.hypot(points[:, 0], points[:, 1]) > field))
    if outside > FIT_OUTSIDE_SHARE * n:
        with pytest.raises(ObjectTooLarge, match=f"{outside} of {n} points"):
            check_object_fits(points, field)
    else:
        check_object_fits(points, field)
    check_object_fits(points, None)  # no calibration: nothing to check against
    check_object_fits(np.empty((0, 2)), field)  # a view without stripe: nothing to judge


def test_presets_fit_the_lift_and_the_view() -> None:
    """A preset is cut to the lift's travel (saying so) and refused for a narrow rig."""
    arm = PLAN_PRESETS["arm"]
    free = preset_plan(arm)
    assert free.sections == int(arm.length_mm // arm.pitch_mm) + 1 and not free.note
    box = preset_plan(arm, AxesInfo(lift_min_mm=0.0, lift_max_mm=150.0))
    assert box.sections == 16 and (box.sections - 1) * box.pitch_mm <= 150.0
    assert box.note == "cut to the lift's 150 mm travel (an arm: 400 mm)"
    for preset in PLAN_PRESETS.values():
        # The thesis rig sees about 44 mm across; the limb rig about 210 mm.
        with pytest.raises(ObjectTooLarge, match=f"up to {preset.width_mm:g} mm across"):
            check_preset_fits(preset, 22.05)
        check_preset_fits(preset, 105.8)
        check_preset_fits(preset, None)
