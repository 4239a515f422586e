"""The terminal UI refuses what the command line refuses, with the same words (issue #11).

Values are put into the Scan screen's fields as a paste would (bypassing the fields'
own typing filters), so the refusal must come from the shared plan and subject rules.
"""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest
from drive import fill_scan_form, wait_for
from rich.text import Text
from textual.widgets import DataTable, Input

from lamina_host import cli
from lamina_host.store.library import Library
from lamina_host.ui.tui.app import LaminaApp
from lamina_shared.types import ScanPlan

BAD_FORMS = [
    (("P1", "0", "2", "8"), ["--sections", "0"]),
    (("P1", "-3", "2", "8"), ["--sections", "-3"]),
    (("P1", "2", "0", "8"), ["--pitch", "0"]),
    (("P1", "2", "nan", "8"), ["--pitch", "nan"]),
    (("P1", "2", "inf", "8"), ["--pitch", "inf"]),
    (("P1", "2", "-inf", "8"), ["--pitch=-inf"]),
    (("P1", "2", "1e-300", "8"), ["--pitch", "1e-300"]),  # rounds to 0 on the 1e-9 mm grid
    (("P1", "2", "0.0000000001", "8"), ["--pitch", "0.0000000001"]),
    (("P1", "2", "0.0004", "8"), ["--pitch", "0.0004"]),  # finer than any lift steps
    (("P1", "2", "2", "0"), ["--views", "0"]),
    (("Jane Doe", "2", "2", "8"), ["--subject", "Jane Doe"]),
    (("P1\x1b[2J", "2", "2", "8"), ["--subject", "P1\x1b[2J"]),
    (("x" * 33, "2", "2", "8"), ["--subject", "x" * 33]),
]


@pytest.mark.parametrize(("fields", "cli_args"), BAD_FORMS)
async def test_scan_form_refuses_what_the_cli_refuses_in_the_same_words(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], fields: tuple[str, ...], cli_args: list[str]
) -> None:
    """Nothing starts, no scan is recorded, and the status line says what the CLI says."""
    library = tmp_path / "library.sqlite"
    status = cli.main(
        ["scan", "--device", "sim", "--library", str(library), "-o", str(tmp_path / "o"), *cli_args]
    )
    cli_line = capsys.readouterr().err.strip()
    assert status == 2 and cli_line.startswith("lamina: ")
    app = LaminaApp("sim", library)
    async with app.run_test(size=(80, 24)) as pilot:
        await fill_scan_form(pilot, "P1", "2", "2", "8")
        for name, value in zip(("subject", "sections", "pitch", "views"), fields, strict=True):
            app.screen.query_one(f"#{name}", Input).value = value
        await pilot.press("s")
        await pilot.pause()
        message, is_error = app.status
        assert is_error and not app.screen.scanning
        assert message == cli_line.removeprefix("lamina: ")
    with Library(library) as opened:
        assert opened.scans() == []


async def test_library_screen_shows_stored_codes_as_plain_escaped_text(tmp_path: Path) -> None:
    """A code an older Lamina stored with escapes or markup is shown inert, on one line."""
    path = tmp_path / "library.sqlite"
    with Library(path) as library:
        library.create_scan("P-01", {"object": ScanPlan.regular(1, 2.0, 4)})
    evil = "[red]x[/]\x1b[2J\nname"
    with sqlite3.connect(path) as db:
        db.execute("UPDATE subjects SET code = ?", (evil,))
        db.execute("UPDATE scans SET options = ?", (json.dumps({}),))
    app = LaminaApp("sim", path)
    async with app.run_test(size=(100, 24)) as pilot:
        await pilot.press("f7")
        table = app.screen.query_one("#scans", DataTable)
        await wait_for(pilot, lambda: table.row_count == 1, "the library list")
        cell = table.get_row_at(0)[1]
        assert isinstance(cell, Text)
        assert cell.plain == "[red]x[/]\\x1b[2J\\nname" and not cell.spans
