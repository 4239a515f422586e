"""Terminal UI responsiveness: key-to-screen latency while a scan and processing run.

The app runs headless under Textual's test driver with the simulated device on a
pseudo-terminal. F1 goes into the driver's input queue, as a terminal's key would, and
the time until the help screen is the app's current screen is one sample; Escape, and
the time until the screen below is back, is another. Samples are taken only while the
scan worker, then the processing worker, is still running, keys 50 ms after the
previous key's answer (a key sent sooner queues behind the previous screen's layout).
"""

from __future__ import annotations

import asyncio
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from textual import events
from textual.widgets import Input
from textual.worker import Worker

from lamina_host.ui.tui.app import LaminaApp
from tests.tui.drive import help_key_latencies_s

PAUSE_S = 0.05
"""Time between one key's answer and the next key, about a fast typist's."""

TITLE = "terminal UI key latency during a 4 x 8 scan and its processing (simulated device)"


def _running(app: LaminaApp, group: str) -> bool:
    workers: list[Worker[Any]] = [w for w in app.screen.workers if w.group == group]
    return any(w.is_running for w in workers)


async def _until(condition: Any, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError("the simulated workflow did not finish")
        await asyncio.sleep(0.05)


async def _measure(library: Path) -> dict[str, list[float]]:
    app = LaminaApp("sim", library)
    samples: dict[str, list[float]] = {"scan": [], "processing": []}
    async with app.run_test(size=(80, 24)) as pilot:
        assert app._driver is not None
        await pilot.press("c")
        await _until(lambda: app.job.device.connected)
        await pilot.press("f4", "g")
        await _until(lambda: app.job.acquisition.grid is not None)
        await pilot.press("a", "y")
        await _until(lambda: app.job.acquisition.axis is not None)
        await pilot.press("f5")
        for field, value in (("subject", "BENCH"), ("sections", "4"), ("views", "8")):
            app.screen.query_one(f"#{field}", Input).value = value
        await pilot.press("escape")
        app._driver.send_message(events.Key("s", "s"))
        await _until(lambda: _running(app, "scan"))
        while _running(app, "scan"):
            samples["scan"] += list(await help_key_latencies_s(app, 0.0005, PAUSE_S))
            await asyncio.sleep(0.02)
        await _until(lambda: app.job.acquisition.data.complete)
        await pilot.press("f6")
        # Straight into the driver: Pilot's press would wait for the processing to end.
        app._driver.send_message(events.Key("p", "p"))
        await _until(lambda: _running(app, "process") or app.job.processing.results is not None)
        while _running(app, "process"):
            samples["processing"] += list(await help_key_latencies_s(app, 0.0005, PAUSE_S))
            await asyncio.sleep(0.01)
        await _until(lambda: app.job.processing.results is not None)
    return samples


def run() -> dict[str, Any]:
    """Scan and process through the UI, sampling key latency throughout."""
    with tempfile.TemporaryDirectory() as tmp:
        samples = asyncio.run(_measure(Path(tmp) / "library.sqlite"))
    out: dict[str, Any] = {}
    for phase, values in samples.items():
        ms = sorted(v * 1000.0 for v in values)
        out[phase] = {
            "samples": len(ms),
            "median_ms": statistics.median(ms) if ms else None,
            "p90_ms": ms[int(0.9 * (len(ms) - 1))] if ms else None,
            "max_ms": ms[-1] if ms else None,
        }
    return out


def report(results: dict[str, Any]) -> list[str]:
    """Return one line per phase."""
    lines = []
    for phase in ("scan", "processing"):
        r = results[phase]
        if not r["samples"]:
            lines.append(f"  during {phase}: no sample (it finished before a key could be sent)")
            continue
        lines.append(
            f"  during {phase}: {r['samples']} key presses, median {r['median_ms']:.1f} ms, "
            f"p90 {r['p90_ms']:.1f} ms, max {r['max_ms']:.1f} ms (requirement: 100 ms)"
        )
    return lines
