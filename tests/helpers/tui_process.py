"""The terminal UI in a process of its own, for the library's concurrency tests.

``python tests/helpers/tui_process.py LIBRARY library`` shows the Library screen and
reloads it a few times; ``... LIBRARY scan SUBJECT OUT`` connects to the simulated
device, calibrates and scans 2 x 8 while the Library screen reloads in the same process,
then writes what the job holds (every view stored and acknowledged) to
``OUT/segments.npz`` and ``OUT/cylinder-segments.npz`` and prints ``scan N``. Exit 0 only
when it all worked; any error ends the process non-zero with the status line.
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "tui")]

from drive import connect_and_calibrate, fill_scan_form, wait_for  # noqa: E402
from textual.widgets import DataTable  # noqa: E402

from lamina_host.store.outputs import save_segments  # noqa: E402
from lamina_host.ui.tui.app import LaminaApp  # noqa: E402

RELOADS = 4


async def _reload_library(app: LaminaApp, pilot: object) -> None:
    """Show the Library screen and reload it, waiting until it lists at least one scan."""
    await pilot.press("f7")  # type: ignore[attr-defined]
    table = app.screen.query_one("#scans", DataTable)
    for _ in range(RELOADS):
        await pilot.press("u")  # type: ignore[attr-defined]
        await wait_for(pilot, lambda: table.row_count > 0, "the scan list")  # type: ignore[arg-type]
        await asyncio.sleep(0.2)


async def _run(library: Path, mode: str, subject: str, out: Path | None) -> int:
    app = LaminaApp("sim", library)
    async with app.run_test(size=(100, 30)) as pilot:
        if mode == "library":
            await _reload_library(app, pilot)
            return 0
        await connect_and_calibrate(pilot)
        await fill_scan_form(pilot, subject, "2", "2", "8")
        await pilot.press("s")
        while not app.job.acquisition.data.complete:
            status, is_error = app.status
            if is_error:
                raise SystemExit(f"the scan failed: {status}")
            await _reload_library(app, pilot)
            await pilot.press("f5")
        job = app.job
        assert out is not None and job.scan_id is not None
        out.mkdir(parents=True, exist_ok=True)
        save_segments(
            out / "segments.npz", [job.acquisition.held[k] for k in sorted(job.acquisition.held)]
        )
        cylinder = [job.acquisition.cylinder_held[k] for k in sorted(job.acquisition.cylinder_held)]
        save_segments(out / "cylinder-segments.npz", cylinder)
        print(f"scan {job.scan_id}", flush=True)
    return 0


def main(argv: list[str]) -> int:
    """Run the mode ``argv`` names; return the exit status."""
    library, mode = Path(argv[0]), argv[1]
    subject = argv[2] if len(argv) > 2 else ""
    out = Path(argv[3]) if len(argv) > 3 else None
    return asyncio.run(_run(library, mode, subject, out))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
