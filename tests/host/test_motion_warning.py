"""A subject who moves during a scan is told, not hidden in a clean result (issue 22, part 3)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lamina_device.acquisition import acquire, grab_grid
from lamina_device.sim import open_sim
from lamina_device.sim.backend import DEFAULT_CYLINDER_PLAN
from lamina_host.reconstruct.pipeline import ProcessOptions, reconstruct
from lamina_host.reconstruct.precision import (
    MOTION_WARN_MM,
    TURN_TOLERANCE_DEG,
    ViewPair,
    disagreement_of,
    pair_differences,
    views_disagreement_mm,
)
from lamina_host.store.outputs import build_report
from lamina_shared.types import ScanPlan


def arc_views(shift_mm: tuple[float, float] = (0.0, 0.0), noise_mm: float = 0.02) -> list:
    """Return 8 views of a 10 mm circle, each 100 degrees of it, the fourth on shifted
    (the subject moved before the fourth view and stayed there)."""
    rng = np.random.default_rng(4)
    views = []
    for k in range(8):
        phi = np.radians(np.linspace(45 * k - 50, 45 * k + 50, 200))
        r = 10.0 + rng.normal(0.0, noise_mm, phi.size)
        points = np.column_stack([r * np.cos(phi), r * np.sin(phi)])
        views.append(points + (np.array(shift_mm) if k >= 3 else 0.0))
    return views


def test_noise_alone_stands_out_nowhere_and_a_shifted_view_does():
    assert views_disagreement_mm(arc_views()) < 0.02
    moved = views_disagreement_mm(arc_views((0.3, 0.3)))
    assert moved > MOTION_WARN_MM
    # The shift's radial part where the views before and after it overlap (the fourth
    # and third about 112 degrees, the first and last about 0): at most 0.42 mm.
    assert moved == pytest.approx(math.hypot(0.3, 0.3) * math.cos(math.radians(22.5)), rel=0.3)
    assert views_disagreement_mm([]) == 0.0 and views_disagreement_mm(arc_views()[:1]) == 0.0


def test_a_pair_laid_against_another_stretch_of_surface_shows_no_motion():
    """A view whose stripe runs off along another branch (a bent outline, a thin part's
    far face) differs from its neighbours by a ramp, not an offset: it is no motion (a
    still bent random limb shape reported its views 30 mm apart); a shifted view still is."""
    views = arc_views()
    phi = np.radians(np.linspace(45 * 5 - 50, 45 * 5 + 50, 200))
    r = 10.0 + np.linspace(0.0, 30.0, phi.size)  # from the circle out along another branch
    views[5] = np.column_stack([r * np.cos(phi), r * np.sin(phi)])
    assert views_disagreement_mm(views) < 0.02
    shifted = arc_views((0.3, 0.3))
    shifted[5] = views[5]
    assert views_disagreement_mm(shifted) == pytest.approx(
        views_disagreement_mm(arc_views((0.3, 0.3))), abs=0.01
    )


def test_one_pair_apart_is_the_shape_and_two_are_motion():
    """Round a closed outline a move shows where the views before and after it meet, in
    two pairs at least; one pair alone apart is the shape's (a thin part's edge, a shell's
    far face: of the 48 outlines of 30 still random limb shapes the largest offset warned
    of, 43 had one pair alone beyond 0.15 mm)."""
    rng = np.random.default_rng(7)
    noise = [rng.normal(0.0, 0.03, 110) for _ in range(8)]
    pairs = [ViewPair(d) for d in noise]
    one = [*pairs[:7], ViewPair(noise[7] - 0.3)]
    assert disagreement_of(pairs) == 0.0 and disagreement_of(one) == 0.0
    two = [*pairs[:6], ViewPair(noise[6] + 0.25), ViewPair(noise[7] - 0.3)]
    assert disagreement_of(two) == pytest.approx(0.25, abs=0.02)
    # A move before the fourth view, seen on whole views: still warned.
    assert views_disagreement_mm(arc_views((0.3, 0.3))) > MOTION_WARN_MM


def test_a_piece_of_a_dozen_points_is_no_measure_of_a_move():
    """A stretch the stripe grazed gives a view a piece of a dozen points standing off the
    surface by the grazing's bias; the earlier views compared with a curve through them
    stood 0.3-0.5 mm off on the still arm (continuous, limb rig) and warned. Such a piece
    is left out as the later view of a pair; a whole view shifted is still warned."""

    def grazed(views: list) -> list:
        for centre_deg in (80.0, 260.0):
            phi = np.radians(np.linspace(centre_deg - 20, centre_deg + 20, 12))
            r = 10.4  # the grazing bias: 0.4 mm out
            views.append(np.column_stack([r * np.cos(phi), r * np.sin(phi)]))
        return views

    assert views_disagreement_mm(grazed(arc_views())) < 0.02
    # Compared without the views' sizes, the same pieces stand apart as a move would.
    assert disagreement_of(pair_differences(grazed(arc_views()))) > MOTION_WARN_MM
    moved = views_disagreement_mm(grazed(arc_views((0.3, 0.3))))
    assert moved == pytest.approx(views_disagreement_mm(arc_views((0.3, 0.3))), abs=0.02)


def ellipse_views(turn_deg: float, shift_mm: tuple[float, float] = (0.0, 0.0)) -> list:
    """Return 8 views of a 120 x 40 mm ellipse off the axis (a slantwise outline in its
    polar frame), the fourth view on turned by ``turn_deg`` about the axis and shifted."""
    rng = np.random.default_rng(5)
    views = []
    turn = math.radians(turn_deg)
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    for k in range(8):
        phi = np.radians(np.linspace(45 * k - 50, 45 * k + 50, 600))
        points = np.column_stack([8.0 + 60.0 * np.cos(phi), 3.0 + 20.0 * np.sin(phi)])
        normal = np.column_stack([20.0 * np.cos(phi), 60.0 * np.sin(phi)])
        normal /= np.linalg.norm(normal, axis=1)[:, None]
        points += normal * rng.normal(0.0, 0.05, phi.size)[:, None]
        views.append(points @ rotation.T + np.array(shift_mm) if k >= 3 else points)
    return views


def test_the_turntables_own_angle_error_is_no_motion():
    """A gear's angle error turns the later views by a tenth of a degree or two; on an
    outline that runs slantwise to its frame that shifts overlapping views as a move
    would (the still random limb shapes' false alarms: 4 of 6 went with the gear error).
    Within :data:`TURN_TOLERANCE_DEG` it is not counted; a shift still is."""
    still = views_disagreement_mm(ellipse_views(0.0))
    turned = views_disagreement_mm(ellipse_views(TURN_TOLERANCE_DEG))
    assert still < 0.02 and turned < 0.02
    # Without the allowance the same turn stands apart (what the old rule warned of).
    assert disagreement_of(pair_differences(ellipse_views(TURN_TOLERANCE_DEG))) > 0.1
    moved = views_disagreement_mm(ellipse_views(TURN_TOLERANCE_DEG, (0.4, 0.4)))
    assert moved > MOTION_WARN_MM


def test_the_allowance_is_taken_wherever_it_could_change_the_warning(monkeypatch):
    """The turned comparison only lowers the figure, so it is made only where the figure
    would warn: on random turns and shifts the warning is the same as with it made
    everywhere, and so is the figure wherever it warns."""
    from lamina_host.reconstruct import precision

    rng = np.random.default_rng(22)
    cases = [
        ellipse_views(rng.uniform(-0.3, 0.3), tuple(rng.uniform(-0.25, 0.25, 2))) for _ in range(12)
    ]
    cases += [arc_views(tuple(rng.uniform(-0.15, 0.15, 2))) for _ in range(6)]
    # A gear's turn alone: apart beyond the warning until the allowance is taken off.
    cases += [ellipse_views(t) for t in (0.15, 0.2, -0.2)]
    quick = [views_disagreement_mm(v) for v in cases]
    monkeypatch.setattr(precision, "MOTION_WARN_MM", -1.0)  # the allowance everywhere
    full = [views_disagreement_mm(v) for v in cases]
    warned = [q > MOTION_WARN_MM for q in quick]
    assert warned == [f > MOTION_WARN_MM for f in full]
    assert 3 <= sum(warned) <= len(cases) - 3  # both outcomes are tried
    for q, f, w in zip(quick, full, warned, strict=True):
        assert f <= q + 1e-12 and (q == f if w else True)
    assert max(quick[-2:]) < 0.02  # the 0.2 degree turns stood apart until allowed for


@pytest.fixture(scope="module")
def calibration():
    """The board and the calibration cylinder, taken once with nothing moving."""
    hardware = open_sim("cylinder:d=19.05", seed=1)
    cylinder: list = []
    try:
        grid = grab_grid(hardware)
        acquire(hardware, "cylinder", DEFAULT_CYLINDER_PLAN, cylinder.append)
    finally:
        hardware.close()
    return grid, hardware.board, cylinder, hardware.cylinder_diameter_mm


def scan_report(calibration, sway: str):
    grid, board, cylinder, diameter = calibration
    hardware = open_sim("cylinder:d=19.05", seed=1, sway=sway)
    segments: list = []
    try:
        acquire(hardware, "object", ScanPlan.regular(1, 2.0, 8), segments.append)
    finally:
        hardware.close()
    recon = reconstruct(grid, board, cylinder, diameter, segments, ProcessOptions())
    return build_report(recon, {"kind": "sim"}, segments, None, {})


def test_a_breathing_subject_is_warned_of_and_a_still_one_is_not(calibration):
    still = scan_report(calibration, "none")
    assert not [w for w in still.warnings if "may have moved" in w]
    breathing = scan_report(calibration, "drift=0,breath=0.5,hz=0.25")
    moved = [w for w in breathing.warnings if "may have moved" in w]
    assert moved and moved[0].startswith("section 0: its overlapping views stand")
    # The line says what a repeat means: motion goes when the limb is held still, a fine
    # surface does not.
    assert "if a still limb is warned of again" in moved[0] and "\n" not in moved[0]
