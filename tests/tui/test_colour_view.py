"""Colour in the terminal UI: the Scan screen's Colour box and the Results colour strips."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from textual.widgets import Checkbox, Input, Static

from lamina_device.sim.texture import Texture, colour_errors
from lamina_host.ui.tui.app import LaminaApp
from lamina_host.ui.tui.screens.results import COLOUR_SECTORS, colour_strip
from lamina_host.workflow.results import colour_bins

from .drive import calibrate, connect, fill_scan_form, wait_for


async def test_a_colour_scan_shows_the_patches_round_each_section(tmp_path: Path) -> None:
    app = LaminaApp("sim", tmp_path / "tui.sqlite", "patches:d=30", noise="harsh")
    async with app.run_test(size=(100, 30)) as pilot:
        await connect(pilot)
        await calibrate(pilot)
        await fill_scan_form(pilot, "P002", "1", "2", "8")
        app.screen.query_one("#colour", Checkbox).value = True
        await pilot.press("s")
        await wait_for(pilot, lambda: app.job.acquisition.data.complete, "the scan")
        assert all(s.has_colour for s in app.job.acquisition.data.segments)
        await pilot.press("f6")
        app.screen.query_one("#harmonics", Input).focus()
        await pilot.press("enter")
        await wait_for(pilot, lambda: app.job.processing.results is not None, "processing")
        summary = app.screen.query_one("#summary", Static)
        shown = str(summary.render())
        results = app.job.processing.results
    assert results is not None
    assert re.search(r"colour 0\.0 z +0\.00 ", shown), shown
    section = results.reconstruction.sections[0]
    bins = colour_bins(section, COLOUR_SECTORS)
    assert bins is not None and np.all(bins >= 0)  # seen all round: no blank sector
    strip = colour_strip(results)
    assert strip is not None
    styles = [str(span.style) for span in strip.spans]
    assert len(styles) == COLOUR_SECTORS
    # Each sector whose middle lies well inside a patch shows that patch's colour: of the
    # patches and the skin (white-balanced on the skin), its block is nearest that patch.
    texture = Texture()
    gain, _ = colour_errors(section.colour_points, section.colours)  # type: ignore[arg-type]
    reflectances = [p.reflectance for p in texture.patches] + [texture.base]
    truths = gain * np.array(reflectances)
    middles = (np.arange(COLOUR_SECTORS) + 0.5) * 360.0 / COLOUR_SECTORS
    centre = section.colour_points.mean(axis=0)  # type: ignore[union-attr]
    on = texture.patch_index(
        centre + 15.0 * np.stack([np.cos(np.radians(middles)), np.sin(np.radians(middles))], 1),
        margin_deg=8.0,
    )
    checked = 0
    for k, style in zip(on, styles, strict=True):
        if k < 0:
            continue
        rgb = np.array([int(v) for v in re.findall(r"\d+", style)], float)
        assert int(np.argmin(np.linalg.norm(truths - rgb, axis=1))) == k, (k, style)
        checked += 1
    assert checked >= 8
