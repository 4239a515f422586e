"""Stripe extraction: difference image, Otsu threshold, centre of gravity (thesis 5.2)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lamina_device.extract import (
    FLAG_NOT_PEAK_RUN,
    FLAG_SATURATED,
    FLAG_SEVERAL_RUNS,
    ExtractSettings,
    StripePoints,
    centre_of_gravity,
    difference,
    extract,
    otsu_level,
    otsu_threshold,
    thin,
    to_segment,
)


def _load_bench(name):
    """Import a benchmark module (the sub-pixel table) so its numbers are tested too."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# --- The straightforward implementation the fast one must reproduce (pre-issue-3 code) ---


def reference_difference(on, off):
    """Return max(on - off, 0) as int32, in 8-bit units for 16-bit frames."""
    diff = on.astype(np.int32)
    if off is not None:
        diff -= off
        np.maximum(diff, 0, out=diff)
    if on.dtype == np.uint16:
        diff >>= 8
    return diff


def reference_otsu(image, floor=0):
    """Return Otsu's level from the image's own histogram, searched over floor..max."""
    top = int(image.max())
    if top <= floor:
        return float(floor)
    hist = np.bincount(image.ravel(), minlength=top + 1).astype(np.float64)
    levels = np.arange(top + 1, dtype=np.float64)
    weight0 = np.cumsum(hist)
    sum0 = np.cumsum(hist * levels)
    weight1 = weight0[-1] - weight0
    with np.errstate(divide="ignore", invalid="ignore"):
        between = weight0 * weight1 * (sum0 / weight0 - (sum0[-1] - sum0) / weight1) ** 2
    between[~np.isfinite(between)] = -1.0
    return float(floor + np.argmax(between[floor:]))


def reference_extract(on, off, threshold=None, power=1.0, min_peak=12.0, subtract=False):
    """Return (cols, rows, peak, width): eq. 5.1 over the run holding each column's peak."""
    diff = reference_difference(on, off)
    floor = int(np.ceil(min_peak - 1))
    t = reference_otsu(diff, floor) if threshold is None else max(threshold, floor)
    cols = np.arange(diff.shape[1])
    peak_row = np.argmax(diff, axis=0)
    peak = diff[peak_row, cols]
    above = diff > t
    run_id = np.cumsum(~above, axis=0)
    chosen = above & (run_id == run_id[peak_row, cols])
    weights = np.where(chosen, diff - t if subtract else diff, 0).astype(np.float64) ** power
    total = weights.sum(axis=0)
    keep = (peak > t) & (total > 0)
    rows = np.arange(diff.shape[0], dtype=np.float64)[:, None]
    centre = (weights[:, keep] * rows).sum(axis=0) / total[keep]
    return cols[keep], centre.astype(np.float32), peak[keep], chosen[:, keep].sum(axis=0)


def assert_matches_reference(on, off, **options):
    """Assert the fast extraction (the thesis's method alone) equals the reference."""
    names = {"subtract": "subtract_threshold"}
    settings = ExtractSettings.thesis(**{names.get(k, k): v for k, v in options.items()})
    fast = extract(on, off, settings)
    cols, rows, peak, width = reference_extract(on, off, **options)
    assert np.array_equal(fast.cols, cols)
    np.testing.assert_array_max_ulp(fast.rows, rows, maxulp=1)
    assert np.array_equal(fast.peak, np.minimum(peak, 255))
    assert np.array_equal(fast.width, np.minimum(width, 255))


def stripe_frames(centres, sigma_px=2.0, peak=180.0, ambient=40.0, height=120, noise=0.0, seed=0):
    """Return (on, off) frames with a Gaussian stripe at a known row per column."""
    rng = np.random.default_rng(seed)
    rows = np.arange(height, dtype=float)[:, None]
    ambient_field = ambient + 20.0 * np.linspace(0, 1, len(centres))[None, :]
    stripe = peak * np.exp(-0.5 * ((rows - np.asarray(centres)[None, :]) / sigma_px) ** 2)
    off = ambient_field + rng.normal(0, noise, (height, len(centres)))
    on = ambient_field + stripe + rng.normal(0, noise, (height, len(centres)))
    as8 = lambda a: np.clip(np.rint(a), 0, 255).astype(np.uint8)  # noqa: E731
    return as8(on), as8(off)


def test_difference_clips_at_zero_and_keeps_shape():
    on = np.array([[10, 5]], np.uint8)
    off = np.array([[4, 9]], np.uint8)
    assert difference(on, off).tolist() == [[6, 0]]
    assert difference(on, None).tolist() == [[10, 5]]
    with pytest.raises(ValueError):
        difference(on, np.zeros((2, 2), np.uint8))


def test_otsu_separates_two_populations():
    image = np.concatenate([np.full(900, 3), np.full(100, 150)]).astype(np.int32)
    threshold = otsu_threshold(image)
    assert 3 <= threshold < 150


def test_sub_pixel_centres_match_known_truth_without_noise():
    truth = 60.0 + 10.0 * np.sin(np.linspace(0, 3, 200))
    on, off = stripe_frames(truth)
    points = extract(on, off, ExtractSettings(margin_px=0))
    assert len(points.cols) == 200
    error = points.rows - truth[points.cols]
    # Eq. 5.1 with Otsu's cut keeps only the stripe's core, so its truncated tails
    # bias each centre by a few hundredths of a pixel, depending on sub-pixel phase.
    assert 0.02 < np.sqrt(np.mean(error**2)) < 0.1
    better = extract(on, off, ExtractSettings(subtract_threshold=True))
    error = better.rows - truth[better.cols]
    assert np.sqrt(np.mean(error**2)) < 0.03
    # The default weighs the tails back in (margin_px): the cut's error is gone.
    default = extract(on, off)
    assert np.sqrt(np.mean((default.rows - truth[default.cols]) ** 2)) < 0.015


def test_noisy_centres_stay_sub_pixel():
    truth = np.linspace(40.0, 80.0, 300)
    on, off = stripe_frames(truth, noise=2.0, seed=3)
    points = extract(on, off)
    error = points.rows - truth[points.cols]
    assert len(points.cols) >= 295
    assert np.sqrt(np.mean(error**2)) < 0.15


def test_only_the_run_holding_the_peak_is_used():
    truth = np.full(50, 30.0)
    on, off = stripe_frames(truth)
    on[90:95, :] = np.maximum(on[90:95, :], 150)  # a weaker reflection lower down
    points = extract(on, off)
    assert np.allclose(points.rows, 30.0, atol=0.05)
    assert np.all(points.width < 15)


def test_columns_without_stripe_are_skipped_and_quality_is_reported():
    truth = np.full(40, 50.0)
    on, off = stripe_frames(truth)
    on[:, 10:20] = off[:, 10:20]  # stripe hidden in these columns
    points = extract(on, off)
    assert set(range(10, 20)).isdisjoint(points.cols.tolist())
    assert points.peak.min() >= 150
    assert points.width.min() >= 3


def test_power_factor_weights_bright_pixels_more():
    diff = np.zeros((10, 1), np.int32)
    diff[4, 0], diff[5, 0] = 100, 50
    linear = centre_of_gravity(diff, 10, power=1.0).rows[0]
    squared = centre_of_gravity(diff, 10, power=2.0).rows[0]
    assert linear == pytest.approx(4 + 50 / 150)
    assert squared == pytest.approx(4 + 2500 / 12500)


def test_fixed_threshold_and_sixteen_bit_frames():
    truth = np.full(30, 20.0)
    on, off = stripe_frames(truth, height=40)
    points16 = extract(on.astype(np.uint16) << 8, off.astype(np.uint16) << 8)
    points8 = extract(on, off, ExtractSettings(threshold=None))
    assert np.array_equal(points16.cols, points8.cols)
    assert np.allclose(points16.rows, points8.rows, atol=1e-4)


def cluttered_frames(seed, height=90, width=160, bits=8):
    """Return a noisy stripe plus reflections, glare and saturated pixels: many runs per column."""
    rng = np.random.default_rng(seed)
    truth = 30 + 8 * np.sin(np.arange(width) / 9.0 + seed)
    on, off = stripe_frames(truth, sigma_px=1.5 + seed % 3, noise=3.0, height=height, seed=seed)
    on = on.astype(np.int32)
    for _ in range(4):
        r, c = rng.integers(0, height - 4), rng.integers(0, width - 20)
        on[r : r + rng.integers(1, 4), c : c + rng.integers(3, 20)] += rng.integers(40, 250)
    on = np.clip(on, 0, 255).astype(np.uint8)
    if bits == 16:
        noise = rng.integers(0, 256, on.shape)
        return (on.astype(np.uint16) << 8) | noise.astype(np.uint16), off.astype(np.uint16) << 8
    return on, off


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize(
    "options",
    [
        {},
        {"subtract": True},
        {"power": 2.0},
        {"power": 0.5, "subtract": True},
        {"threshold": 20.5},
        {"threshold": 5, "power": 2.0, "subtract": True},  # below min_peak: the floor rules
    ],
)
def test_default_and_options_match_the_reference_implementation(seed, options):
    on, off = cluttered_frames(seed)
    assert_matches_reference(on, off, **options)
    assert_matches_reference(on, None, **options)


@pytest.mark.parametrize("seed", range(3))
def test_sixteen_bit_frames_match_the_reference(seed):
    on, off = cluttered_frames(seed, bits=16)
    assert_matches_reference(on, off)


@settings(max_examples=60, deadline=None)
@given(
    st.integers(2, 24),
    st.integers(1, 24),
    st.integers(0, 2**32 - 1),
    st.sampled_from([None, 0.0, 30.0]),
    st.sampled_from([1.0, 12.0, 100.0]),
)
def test_any_frame_matches_the_reference(height, width, seed, threshold, min_peak):
    rng = np.random.default_rng(seed)
    on = rng.integers(0, 256, (height, width)).astype(np.uint8)
    off = (rng.integers(0, 256, (height, width)) // rng.integers(1, 8)).astype(np.uint8)
    assert_matches_reference(on, off, threshold=threshold, min_peak=min_peak)


def test_otsu_matches_the_reference_on_ties_and_wide_images():
    two_levels = np.concatenate([np.full(900, 3), np.full(100, 150)]).astype(np.uint8)
    assert otsu_threshold(two_levels) == reference_otsu(two_levels) == 3.0
    wide = np.random.default_rng(1).integers(0, 1000, (30, 40))
    assert otsu_threshold(wide) == reference_otsu(wide)


def reflected_frames():
    """Return frames where a brighter reflection sits 25 rows below the stripe in columns 60-79."""
    truth = 40.0 + 0.05 * np.arange(140)
    on, off = stripe_frames(truth, peak=150.0, height=100)
    on[64:68, 60:80] = 250  # brighter than the stripe, in its own run
    return truth, on, off


def test_brightest_run_default_keeps_the_reflection_but_flags_it():
    _, on, off = reflected_frames()
    points = extract(on, off)
    inside = (points.cols >= 60) & (points.cols < 80)
    assert np.allclose(points.rows[inside], 65.5, atol=0.01)  # the thesis's choice
    assert np.all(points.flags[inside] & FLAG_SEVERAL_RUNS)
    assert not np.any(points.flags[~inside] & FLAG_SEVERAL_RUNS)
    assert not np.any(points.flags & FLAG_NOT_PEAK_RUN)


def test_continuity_keeps_the_run_that_continues_the_stripe():
    truth, on, off = reflected_frames()
    points = extract(on, off, ExtractSettings(run_choice="continuity"))
    assert len(points.cols) == 140
    # The reflection is 25 rows away; what is left is eq. 5.1's truncation bias.
    assert np.abs(points.rows - truth[points.cols]).max() < 0.3
    inside = (points.cols >= 60) & (points.cols < 80)
    assert np.all(points.flags[inside] == FLAG_SEVERAL_RUNS | FLAG_NOT_PEAK_RUN)
    assert np.all(points.flags[~inside] == 0)
    assert np.all(points.peak[inside] < 250) and np.all(points.width[inside] >= 3)


def test_saturated_runs_are_flagged():
    on, off = stripe_frames(np.full(20, 30.0), peak=150.0, ambient=40.0)
    on[29:32, :10] = 255
    points = extract(on, np.zeros_like(off))  # difference reaches full scale in columns 0-9
    assert np.array_equal(points.cols, np.arange(20))
    assert np.all(points.flags[:10] == FLAG_SATURATED)
    assert np.all(points.flags[10:] == 0)


def test_thinning_leaves_one_pixel_lines_and_keeps_two_by_two_squares():
    square = np.zeros((6, 6), bool)
    square[2:4, 2:4] = True
    assert thin(square).sum() == 1  # a blob without holes shrinks to a point, never vanishes
    band = np.zeros((12, 30), bool)
    band[3:8, 2:28] = True  # five rows thick
    skeleton = thin(band)
    assert np.all(skeleton.sum(axis=0) <= 1)
    assert np.array_equal(np.flatnonzero(skeleton.any(axis=1)), [5])  # the middle row
    diagonal = np.eye(8, dtype=bool) | np.eye(8, k=1, dtype=bool)
    assert thin(diagonal).sum() == 8  # a two-pixel diagonal thins to one 8-connected line
    assert not thin(np.zeros((5, 5), bool)).any()


def test_thinning_picks_whole_pixels_and_the_upper_one_of_even_runs():
    centres = np.concatenate([np.full(40, 30.0), np.full(40, 30.5)])  # odd then even runs
    on, off = stripe_frames(centres, sigma_px=1.5, height=60)
    points = extract(on, off, ExtractSettings(method="thinning", threshold=60))
    assert np.array_equal(points.rows, np.rint(points.rows))
    inner = (points.cols > 3) & (points.cols < 76) & ((points.cols < 37) | (points.cols > 42))
    odd, even = inner & (points.cols < 40), inner & (points.cols >= 40)
    assert np.all(points.width[odd] % 2 == 1) and np.all(points.width[even] % 2 == 0)
    assert np.all(points.rows[odd] == 30.0)
    assert np.all(points.rows[even] == 30.0)  # 30 and 31 are equally central: the upper


def test_sub_pixel_table_ordering_matches_the_thesis():
    bench = _load_bench("bench_subpixel")
    for noise_dn, speckle in ((0.0, 0.0), (2.0, 0.0), (2.0, 0.5)):
        table = bench.accuracy(noise_dn, speckle, columns=400, seed=5)
        cog, thinning = table["cog"], table["thinning"]
        # Thinning is worse than the centre of gravity (thesis 5.2.3, fig. 5.6) ...
        assert thinning["rms_px"] > cog["rms_px"] + 0.05
        assert cog["found"] == 1.0 and thinning["found"] > 0.98
    for noise_dn in (0.0, 2.0):
        thinning = bench.accuracy(noise_dn, 0.0, columns=400, seed=5)["thinning"]
        # ... because it is biased toward the top of runs an even number of pixels thick.
        assert thinning["mean_even_width_px"] < -0.3
        assert abs(thinning["mean_odd_width_px"]) < 0.1
    clean = bench.accuracy(0.0, 0.0, columns=400, seed=5)
    assert clean["cog_minus_threshold"]["rms_px"] < clean["cog"]["rms_px"] < 0.15


def test_background_opening_removes_uneven_ambient_light():
    truth = 50.0 + 6.0 * np.sin(np.arange(200) / 20.0)
    on, _ = stripe_frames(truth, sigma_px=1.5, peak=120.0, ambient=0.0, height=120)
    rows = np.arange(120)[:, None]
    glare = 150.0 * np.exp(-0.5 * ((rows - 95.0) / 12.0) ** 2) * np.ones((1, 200))
    on = np.clip(on + glare + np.linspace(0, 60, 200)[None, :], 0, 255).astype(np.uint8)
    plain = extract(on, None)  # without a laser-off frame the glare wins Otsu and the peak
    assert np.median(np.abs(plain.rows - truth[plain.cols])) > 10
    opened = extract(on, None, ExtractSettings(background_opening_px=15))
    assert len(opened.cols) == 200
    assert np.sqrt(np.mean((opened.rows - truth[opened.cols]) ** 2)) < 0.2


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1.0, 12.0, 40.0]))
def test_default_threshold_is_the_whole_frame_otsu_wherever_that_can_be_a_stripe(seed, min_peak):
    on, off = cluttered_frames(seed % 1000, height=90, width=120)
    diff = difference(on, off)
    floor = int(np.ceil(min_peak - 1))
    thesis = otsu_threshold(diff)
    cols, rows, _, width = reference_extract(
        on, off, threshold=max(thesis, floor), min_peak=min_peak
    )
    points = extract(on, off, ExtractSettings.thesis(min_peak=min_peak))
    if thesis >= floor:  # the thesis's threshold, exactly
        assert np.array_equal(points.cols, cols)
        np.testing.assert_array_max_ulp(points.rows, rows, maxulp=1)
    else:  # it fell into the noise: the best level above the floor lets less noise in
        assert points.width.sum() <= width.sum()


def test_bad_settings_list_every_problem_at_once():
    with pytest.raises(ValueError) as error:
        ExtractSettings(threshold=-1, power=0, min_peak=0, method="skeleton", run_choice="x")
    message = str(error.value)
    for name in ("threshold", "power", "min_peak", "method", "run_choice"):
        assert name in message
    with pytest.raises(ValueError, match="background_opening_px"):
        ExtractSettings(background_opening_px=-3)


def test_frames_of_the_wrong_kind_are_refused_clearly():
    on = np.zeros((4, 4), np.uint8)
    with pytest.raises(ValueError, match="uint8 or uint16"):
        extract(on.astype(np.float32), None)
    with pytest.raises(ValueError, match="laser-off frame"):
        extract(on, on.astype(np.uint16))
    with pytest.raises(ValueError, match="2-D"):
        difference(np.zeros((4, 4, 3), np.uint8), None)


def test_flags_default_to_zero_and_stay_off_the_wire_segment():
    plain = StripePoints(
        np.arange(3, dtype=np.uint16), np.ones(3, np.float32), np.ones(3, np.uint8),
        np.ones(3, np.uint8),
    )  # fmt: skip
    assert plain.flags.tolist() == [0, 0, 0]
    with pytest.raises(ValueError):
        StripePoints(plain.cols, plain.rows, plain.peak, plain.width, np.zeros(2, np.uint8))
    _, on, off = reflected_frames()
    points = extract(on, off)
    segment = to_segment(points, "object", 2, 5, 4.0, 90.0)
    assert (segment.section, segment.view, segment.z_mm, segment.angle_deg) == (2, 5, 4.0, 90.0)
    assert np.array_equal(segment.rows, points.rows) and np.array_equal(segment.cols, points.cols)
    assert segment.peak.dtype == np.uint8 and segment.width.dtype == np.uint8


def test_blank_frames_give_no_points():
    blank = np.full((30, 40), 17, np.uint8)
    for method in ("cog", "thinning"):
        points = extract(blank, blank, ExtractSettings(method=method))
        assert len(points.cols) == 0 and points.rows.dtype == np.float32


def test_runs_never_continue_from_one_column_bottom_to_the_next_top():
    diff = np.zeros((5, 9), np.uint8)  # 9 columns: the padded word path as well
    diff[3:, 0] = 100  # column 0 reaches the bottom row ...
    diff[:2, 1] = 100  # ... column 1 starts at the top row
    points = centre_of_gravity(diff, 50)
    assert points.cols.tolist() == [0, 1]
    assert points.rows.tolist() == [3.5, 0.5]
    assert points.width.tolist() == [2, 2]


def test_otsu_level_needs_only_the_counts_above_its_floor():
    image = cluttered_frames(3)[0]
    full = np.bincount(image.ravel(), minlength=256)
    bright_only = np.where(np.arange(256) > 20, full, 0)
    total = float(image.sum())
    assert otsu_level(full, image.size, total, 20) == otsu_level(bright_only, image.size, total, 20)
    assert otsu_level(full, image.size, total) == otsu_threshold(image) == reference_otsu(image)


def test_opencv_inline_gives_the_same_points_on_the_calling_thread():
    import cv2

    from lamina_device.extract import run_opencv_inline

    on, off = stripe_frames(100.0 + 20.0 * np.sin(np.arange(640) / 40.0), height=480, noise=3.0)
    threaded = extract(on, off)
    try:
        run_opencv_inline()
        assert cv2.getNumThreads() == 1
        inline = extract(on, off)
    finally:
        cv2.setNumThreads(-1)
    assert inline.cols.size > 600
    for name in ("cols", "rows", "peak", "width", "flags", "confidence"):
        assert np.array_equal(getattr(inline, name), getattr(threaded, name)), name


def test_the_device_program_runs_opencv_inline_for_a_replay_not_for_the_simulator(
    monkeypatch, capsys, tmp_path
):
    import lamina_device.cli as cli

    calls: list[str] = []
    monkeypatch.setattr(cli, "run_opencv_inline", lambda: calls.append("inline"))
    capture = tmp_path / "capture"
    small = ["--sections", "1", "--views", "2", "--cylinder-views", "2"]
    record = ["record", "--noise", "none", *small]
    assert cli.main([*record, "--hardware", "sim", "--out", str(capture)]) == 0
    assert calls == []  # the simulator blurs its frames with OpenCV's threads
    again = tmp_path / "again"
    assert cli.main([*record, "--hardware", f"replay:{capture}", "--out", str(again)]) == 0
    assert calls == ["inline"]
    assert "Traceback" not in capsys.readouterr().err
