"""Test support, not used by the product: a faulty serial line for the link's tests.

:class:`LineFaults` is a ``transform`` for :class:`lamina_host.link.spawn.PtyBridge`: it
damages, drops, duplicates, delays and cuts bytes in flight, reproducibly (seeded), so
the fault-injection tests and ``tests/benchmarks/bench_link.py`` run the real link
(pyserial on real pseudo-terminals) over a bad cable.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np


@dataclass
class LineFaults:
    """A bad cable for ``PtyBridge``: flips, drops, duplicates, delays bytes, cuts.

    Each byte meets an error with probability ``error_rate``: half of them flip one bit,
    a quarter vanish, a quarter arrive twice. With probability ``delay_rate`` a burst
    of bytes is held for ``delay_s`` (order is kept, as on a real line). When the bytes
    relayed towards the host pass each of ``cut_after_bytes``, the line goes dead in
    both directions for ``cut_s``.
    """

    error_rate: float = 0.0
    delay_rate: float = 0.0
    delay_s: float = 0.02
    cut_after_bytes: tuple[int, ...] = ()
    cut_s: float = 1.0
    seed: int = 0
    counts: dict[str, int] = field(default_factory=dict)
    _to_host: int = 0
    _cut_until_s: float = 0.0
    _rng: np.random.Generator = field(init=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self._cuts = sorted(self.cut_after_bytes)
        for name in ("flipped", "dropped", "duplicated", "delayed", "cuts", "cut_bytes"):
            self.counts[name] = 0

    def __call__(self, data: bytes, direction: str) -> bytes:
        """Return what arrives at the other end of the line for ``data``."""
        now = time.monotonic()
        if direction == "to-host":
            self._to_host += len(data)
            if self._cuts and self._to_host >= self._cuts[0]:
                self._cuts.pop(0)
                self._cut_until_s = now + self.cut_s
                self.counts["cuts"] += 1
        if now < self._cut_until_s:
            self.counts["cut_bytes"] += len(data)
            return b""
        if self.delay_rate and self._rng.random() < self.delay_rate:
            self.counts["delayed"] += 1
            time.sleep(self.delay_s)
        if not self.error_rate:
            return data
        arr = np.frombuffer(data, np.uint8).copy()
        hit = np.flatnonzero(self._rng.random(len(arr)) < self.error_rate)
        what = self._rng.integers(0, 4, len(hit))
        flips = hit[what < 2]
        arr[flips] ^= (1 << self._rng.integers(0, 8, len(flips))).astype(np.uint8)
        repeat = np.ones(len(arr), np.int64)
        repeat[hit[what == 2]] = 0
        repeat[hit[what == 3]] = 2
        self.counts["flipped"] += len(flips)
        self.counts["dropped"] += int(np.sum(what == 2))
        self.counts["duplicated"] += int(np.sum(what == 3))
        return np.repeat(arr, repeat).tobytes()
