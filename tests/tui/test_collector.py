"""The app sets what it has loaded aside from the garbage collector, and gives it back.

A full collection walks every object the process holds; with the host's libraries loaded
it stalled key presses during a scan (`make bench`, tui). The app freezes what exists at
mount and unfreezes it when it ends, so nothing set aside outlives it; while it runs, the
oldest generation is collected ten times less often (what a scan makes still brought eight
full collections a bench run), and Python's thresholds are restored when it ends.
"""

from __future__ import annotations

import gc
import weakref
from pathlib import Path

from lamina_host.ui.tui.app import FULL_COLLECTIONS_RARER, LaminaApp


class _Node:
    """An object that refers to itself: only the cyclic collector can free it."""

    def __init__(self) -> None:
        self.me = self


async def test_what_exists_at_mount_is_not_walked_until_the_app_ends(tmp_path: Path) -> None:
    """A cycle made before the app mounts survives collections while the app runs and is
    collected once it has ended; nothing stays frozen after it."""
    was_enabled = gc.isenabled()
    gc.disable()  # no automatic collection may free the cycle before the app freezes it
    try:
        gc.collect()
        thresholds = gc.get_threshold()
        node = _Node()
        alive = weakref.ref(node)
        del node
        app = LaminaApp("sim", tmp_path / "library.sqlite")
        async with app.run_test() as pilot:
            await pilot.pause()
            assert gc.get_freeze_count() > 10_000
            young, middle, old = thresholds
            assert gc.get_threshold() == (young, middle, old * FULL_COLLECTIONS_RARER)
            gc.collect()
            assert alive() is not None, "a collection walked what the app had set aside"
        assert gc.get_freeze_count() == 0
        assert gc.get_threshold() == thresholds
        gc.collect()
        assert alive() is None, "the cycle set aside at mount was never given back"
    finally:
        if was_enabled:
            gc.enable()
