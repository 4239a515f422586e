"""A section that stands off the line of its neighbours is warned of (issue 22, part 3)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lamina_host.reconstruct.continuity import (
    JUMP_WARN_MM,
    OutlineShape,
    outline_jumps,
    outline_shape,
    section_jumps,
)
from lamina_host.reconstruct.efd import efd_fit
from lamina_host.reconstruct.pipeline import Section
from lamina_host.reconstruct.status import OutlineStatus
from lamina_host.store.outputs import _jump_warnings

PITCH_MM = 10.0


def ellipse(centre: tuple[float, float], radius_mm: float, points: int = 360) -> np.ndarray:
    """Return an ellipse (axes radius x 1.2 and x 0.8) about ``centre``."""
    phi = np.linspace(0.0, 2.0 * math.pi, points, endpoint=False)
    return np.column_stack(
        [centre[0] + 1.2 * radius_mm * np.cos(phi), centre[1] + 0.8 * radius_mm * np.sin(phi)]
    )


def limb(
    count: int = 7,
    tilt_deg: float = 3.0,
    bend_mm: float = 0.0,
    moved: dict[int, tuple[float, float, float]] | None = None,
) -> list[Section]:
    """Return a tapering limb leant by ``tilt_deg``, its centre line bent by ``bend_mm`` at
    mid height; ``moved`` shifts sections by (dx, dy, dr) mm, a subject's sway."""
    sections = []
    slope = math.tan(math.radians(tilt_deg))
    for k in range(count):
        z = k * PITCH_MM
        u = k / max(count - 1, 1)
        dx, dy, dr = (moved or {}).get(k, (0.0, 0.0, 0.0))
        centre = (slope * z + bend_mm * 4 * u * (1 - u) + dx, 0.3 * slope * z + dy)
        contour = ellipse(centre, 40.0 - 0.08 * z + dr)  # 8 mm of taper over 100 mm
        sections.append(Section(k, z, 8, contour, efd_fit(contour, 8), contour))
    return sections


def test_a_still_limb_leant_tapered_and_bent_is_not_flagged():
    for tilt, bend in ((0.0, 0.0), (3.0, 0.0), (3.0, 2.0)):
        jumps = outline_jumps(limb(tilt_deg=tilt, bend_mm=bend))
        assert [j.index for j in jumps] == [1, 2, 3, 4, 5]
        assert not any(j.flagged for j in jumps), (tilt, bend)
        assert _jump_warnings(jumps) == []


@pytest.mark.parametrize("shift", [(2.5, 0.0, 0.0), (0.0, -2.2, 0.0), (0.0, 0.0, 2.3)])
def test_a_shifted_or_grown_section_is_flagged_with_its_size(shift):
    jumps = outline_jumps(limb(moved={3: shift}))
    worst = max(jumps, key=lambda j: j.jump_mm)
    assert worst.index == 3 and worst.flagged
    dx, dy, dr = shift
    assert worst.centre_mm == pytest.approx(math.hypot(dx, dy), abs=0.02)
    # The ellipse's axes grow by 1.2 dr and 0.8 dr: its equivalent radius by 0.98 dr.
    assert worst.size_mm == pytest.approx(dr * math.sqrt(1.2 * 0.8), abs=0.02)
    warnings = _jump_warnings(jumps)
    assert any(w.startswith(f"section 3: it stands {worst.jump_mm:.2f} mm") for w in warnings)
    assert all("scan again with the limb supported and still" in w for w in warnings)


def test_a_jump_within_the_limit_is_not_flagged():
    jumps = outline_jumps(limb(moved={3: (0.0, 0.0, 0.3)}))
    assert 0.25 < max(j.jump_mm for j in jumps) < JUMP_WARN_MM
    assert not any(j.flagged for j in jumps)


def test_estimated_and_open_outlines_neither_judge_nor_are_judged():
    sections = limb(moved={3: (2.0, 0.0, 0.0)})
    for status in (OutlineStatus.INTERPOLATED, OutlineStatus.OPEN):
        marked = [s if s.index != 3 else _with_status(s, status) for s in sections]
        jumps = outline_jumps(marked)
        assert 3 not in [j.index for j in jumps]
        assert not any(j.flagged for j in jumps)  # 2 and 4 judged across the gap


def _with_status(s: Section, status: OutlineStatus) -> Section:
    from dataclasses import replace

    return replace(s, status=status)


def test_a_rounded_end_is_not_judged():
    # A dome: the radius falls by more than half a millimetre per millimetre of height.
    shapes = [OutlineShape(k, 0, 2.0 * k, (0.0, 0.0), r, 0.0) for k, r in enumerate((10, 8, 3))]
    assert section_jumps(shapes) == []


def test_degenerate_input_gives_no_jump():
    assert outline_jumps([]) == []
    assert outline_jumps(limb(1)) == [] and outline_jumps(limb(2)) == []
    assert outline_shape(0, 0, 0.0, np.zeros((5, 2))) is None  # no area
    assert outline_shape(0, 0, 0.0, np.zeros((0, 2))) is None
    same_height = [OutlineShape(k, 0, 0.0, (0.0, 0.0), 10.0, 0.0) for k in range(3)]
    assert section_jumps(same_height) == []


def test_a_flat_outline_in_the_stack_is_passed_over_not_raised():
    """A section whose stripe was seen edge-on (its contour encloses no area) neither
    breaks the chains nor is judged; its neighbours still are."""
    sections = limb(5)
    flat = np.column_stack([np.linspace(-30.0, 30.0, 360), np.zeros(360)])
    sections[2] = replace(sections[2], contour=flat, raw=flat)
    jumps = outline_jumps(sections)
    assert [j.index for j in jumps] == [1, 3]
    sections = limb(7)
    sections[0] = replace(sections[0], contour=flat, raw=flat)
    assert [j.index for j in outline_jumps(sections)] == [2, 3, 4, 5]


def test_the_noise_of_a_poor_outline_raises_its_limit():
    quiet = outline_shape(0, 0, 0.0, ellipse((0, 0), 10.0), precision_mm=0.05, points=2000)
    noisy = outline_shape(0, 0, 0.0, ellipse((0, 0), 10.0), precision_mm=0.5, points=20)
    assert quiet is not None and noisy is not None
    assert quiet.error_mm == pytest.approx(0.05 * math.sqrt(2 / 2000))
    chain = [OutlineShape(k, 0, 10.0 * k, (0, 0), 40.0, noisy.error_mm) for k in range(3)]
    calm = [OutlineShape(k, 0, 10.0 * k, (0, 0), 40.0, quiet.error_mm) for k in range(3)]
    assert section_jumps(chain)[0].limit_mm > section_jumps(calm)[0].limit_mm + 0.4


@settings(max_examples=40, deadline=None, derandomize=True)
@given(
    tilt_deg=st.floats(0.0, 3.0),
    bend_mm=st.floats(-2.0, 2.0),
    count=st.integers(0, 9),
    jump=st.tuples(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0)),
    at=st.integers(1, 7),
)
def test_only_a_jump_beyond_the_limit_is_flagged(tilt_deg, bend_mm, count, jump, at):
    jumps = outline_jumps(limb(count, tilt_deg, bend_mm, {at: jump}))
    assert [j.index for j in jumps] == list(range(1, count - 1))
    size = max(math.hypot(jump[0], jump[1]), abs(jump[2]))
    flagged = [j.index for j in jumps if j.flagged]
    # A smooth limb's own curvature stays far below the limit, so only the moved
    # section (at its full jump) or its neighbours (at half of it) can be flagged.
    assert set(flagged) <= {at - 1, at, at + 1}
    if 0 < at < count - 1 and size > 1.2 * max(j.limit_mm for j in jumps):
        assert at in flagged
    if size < 0.8 * JUMP_WARN_MM:
        assert flagged == []
