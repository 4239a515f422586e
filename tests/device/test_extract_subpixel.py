"""The default stripe centre, device and host together, against known truth (issue 21).

Frames come from the sub-pixel bench's renderer (``tests/benchmarks/subpixel_cases.py``):
stripes whose centre line is known exactly in every column, pixel-integrated, with the
simulator's speckle and sensor noise. The default as the product runs it is the device's
centre (eq. 5.1 with margins and bridged runs) fitted along its chains by the host.
"""

from __future__ import annotations

import dataclasses
import sys
from functools import cache
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@cache
def cases():
    """Import the bench's case renderer and methods (they import their siblings by name)."""
    if str(BENCH) not in sys.path:
        sys.path.insert(0, str(BENCH))
    import subpixel_cases

    return subpixel_cases


def case(name: str):
    """Return the named case."""
    return next(c for c in cases().CASES if c.name == name)


def clean(name: str):
    """Return the case rendered without noise or speckle (the method's own bias shows)."""
    model = dataclasses.replace(
        cases().PRESETS["thesis"], read_noise_dn=0.0, shot_gain_dn=0.0, speckle_contrast=0.0
    )
    return cases().render(case(name), "thesis", model=model)


def scored(frames, method: str):
    """Return the named method's score on the frames."""
    found = cases().METHODS[method](frames.on, frames.off)
    return cases().score(frames, found)


@pytest.mark.parametrize("name", ["arcs r=20", "arcs r=50", "brightness steps 0.4"])
def test_the_default_is_not_pulled_on_curves_or_at_brightness_steps(name):
    frames = clean(name)
    default = scored(frames, cases().DEFAULT_AND_FIT)
    assert default.found > 0.95
    assert default.bias_px <= 0.02
    if name == "arcs r=20":
        # The fit alone keeps the centre of gravity's pull toward the centre of curvature,
        # the device's margins widen it; the host takes it off.
        assert scored(frames, "fit, no pull").bias_px > 3 * default.bias_px


def test_a_wide_stripe_on_a_tight_arc_is_pulled_less_than_by_the_column_centre_alone():
    # FWHM 6 px on a 20 px radius: the pull is beyond second order, so only partly
    # taken off (a known limit, README), yet less than eq. 5.1's over the run alone.
    frames = clean("arcs r=20, 6 px")
    default, alone = (scored(frames, m) for m in (cases().DEFAULT_AND_FIT, "COG p=1, run"))
    assert default.bias_px < 0.8 * alone.bias_px


def test_the_default_scatters_far_less_than_the_column_centre_and_the_horus_baseline():
    frames = cases().render(case("gaussian 3 px"), "thesis", 0)
    default, alone, horus = (
        scored(frames, m) for m in (cases().DEFAULT_AND_FIT, "COG p=1, run", "Horus-style")
    )
    assert default.found > 0.95 and default.beyond_1px < 0.002
    assert default.rms_px < 0.4 * alone.rms_px
    assert default.rms_px < 0.6 * horus.rms_px and horus.found > 0.9


def test_under_the_harsh_preset_the_default_finds_the_weak_stripe_and_halves_its_scatter():
    frames = cases().render(case("gaussian 3 px"), "harsh", 1)  # a red laser seen in luma
    default, alone, horus = (
        scored(frames, m) for m in (cases().DEFAULT_AND_FIT, "COG p=1, run", "Horus-style")
    )
    assert horus.found == 0.0  # its fixed 50 DN threshold misses the stripe
    assert default.found >= alone.found and default.found > 0.75
    assert default.beyond_1px < 0.02
    assert default.rms_px < 0.5 * alone.rms_px
