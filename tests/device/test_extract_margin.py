"""The centre weighing pixels beyond the run's ends (``margin_px``, issue 21)."""

from __future__ import annotations

import numpy as np
import pytest

from lamina_device.extract import ExtractSettings, extract


def stripe(centres, sigma_px=2.0, peak=180.0, ambient=40.0, height=120, noise=0.0, seed=0):
    """Return (on, off) frames with a Gaussian stripe at a known row per column."""
    rng = np.random.default_rng(seed)
    rows = np.arange(height, dtype=float)[:, None]
    laser = peak * np.exp(-0.5 * ((rows - np.asarray(centres)[None, :]) / sigma_px) ** 2)
    as8 = lambda a: np.clip(np.rint(a), 0, 255).astype(np.uint8)  # noqa: E731
    off = as8(ambient + rng.normal(0, noise, laser.shape))
    return as8(ambient + laser + rng.normal(0, noise, laser.shape)), off


def rms(points, truth):
    """Return the RMS row error of ``points`` against the true row per column."""
    return float(np.sqrt(np.mean((points.rows - truth[points.cols]) ** 2)))


@pytest.mark.parametrize("sigma_px", [1.0, 2.0, 3.5])
def test_margin_removes_the_threshold_cut_error_without_noise(sigma_px):
    truth = 60.0 + 0.013 * np.arange(300)  # the sub-pixel phase sweeps slowly
    on, off = stripe(truth, sigma_px=sigma_px)
    plain, margin = (extract(on, off, ExtractSettings(margin_px=k)) for k in (0, 3))
    assert np.array_equal(plain.cols, margin.cols)
    assert np.array_equal(plain.width, margin.width)  # the run itself is unchanged
    # Otsu's cut drops the profile's tails; weighing them back in removes most of
    # the phase-dependent error, and a symmetric margin adds no bias.
    assert rms(margin, truth) < 0.5 * rms(plain, truth)
    assert rms(margin, truth) < 0.03
    assert abs(np.mean(margin.rows - truth[margin.cols])) < 0.005


def test_margin_lowers_the_error_under_noise():
    truth = 50.0 + 8.0 * np.sin(np.arange(400) / 40.0)
    on, off = stripe(truth, sigma_px=2.5, peak=120.0, noise=2.5, seed=4)
    plain, margin = (extract(on, off, ExtractSettings(margin_px=k)) for k in (0, 3))
    assert rms(margin, truth) < rms(plain, truth)


def test_margin_leaves_out_a_neighbouring_run_and_the_frame_edges():
    truth = np.full(60, 30.0)
    on, off = stripe(truth, sigma_px=1.2, height=60)
    on[34:36, :] = 200  # a second run just below the stripe, within the margin
    points = extract(on, off, ExtractSettings(margin_px=4))
    assert np.allclose(points.rows, 30.0, atol=0.05)  # not pulled toward row 34.5
    edge = np.full(60, 1.0)  # the stripe touching the top row
    on, off = stripe(edge, sigma_px=1.2, height=40)
    points = extract(on, off, ExtractSettings(margin_px=4))
    assert points.cols.size == 60 and np.all(np.isfinite(points.rows))
    assert np.all(np.abs(points.rows - 1.0) < 0.3)


def test_margin_is_range_checked_and_off_in_the_thesis_method():
    with pytest.raises(ValueError, match="margin_px"):
        ExtractSettings(margin_px=-1)
    with pytest.raises(ValueError, match="margin_px"):
        ExtractSettings(margin_px=17)
    for other in ({"power": 2.0}, {"subtract_threshold": True}, {"method": "thinning"}):
        with pytest.raises(ValueError, match="margin_px > 0 needs"):
            ExtractSettings(margin_px=2, **other)
    assert ExtractSettings.thesis().margin_px == 0 and ExtractSettings().margin_px == 0
