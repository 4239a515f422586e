"""The link: bytes per point, throughput over a pseudo-terminal, cost of a bad line."""

from __future__ import annotations

import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import serial

from lamina_device.acquisition import acquire
from lamina_device.sim import open_sim
from lamina_host.link.client import DeviceClient
from lamina_host.link.connect import open_device
from lamina_host.link.spawn import PtyBridge
from lamina_host.store.library import Library
from lamina_host.testing import LineFaults
from lamina_host.workflow.job import DeviceTarget, ScanJob, ScanRequest
from lamina_host.workflow.job import acquire as acquire_scan
from lamina_shared.link import Channel
from lamina_shared.protocol import Kind, SegmentEvent, encode_json, encode_segment, quantise_segment
from lamina_shared.types import ScanPlan, Segment

TITLE = "link protocol v4: segment encoding, pty throughput, fault-injection overhead"
UART_BYTES_PER_S = 115_200 / 10  # 8N1: ten bit times per byte
LINK_SEGMENTS = 3000


def _acquire(client: DeviceClient, library: Library, out: Path) -> int:
    """Run the workflow's acquisition (create, calibration, cylinder, object) on ``client``."""
    job = ScanJob(DeviceTarget("sim"), library=library)
    job.attach_for_testing(client)
    return acquire_scan(job, ScanRequest("B-01"), out=out).scan_id


def _sim_segments(object_spec: str, plan: ScanPlan) -> list[Segment]:
    hardware = open_sim(object_spec)
    segments: list[Segment] = []
    try:
        acquire(hardware, "object", plan, segments.append)
    finally:
        hardware.close()
    return [quantise_segment(s) for s in segments]


def encoding() -> dict[str, Any]:
    """Bytes per point of the default cylinder scan and of a full-width stripe."""
    typical = _sim_segments("cylinder:d=19.05", ScanPlan.regular(2, 2.0, 8))
    wide = _sim_segments("ellipsoid:a=30,b=20,c=40", ScanPlan.regular(1, 2.0, 2))
    frames = [len(encode_segment(1, k, s)) for k, s in enumerate(typical)]
    points = sum(len(s) for s in typical)
    widest = max(wide, key=len)
    return {
        "bytes_per_point": sum(frames) / points,
        "v1_bytes_per_point": (sum(29 + 8 * len(s) for s in typical) + 16 * len(typical)) / points,
        "typical_points": points / len(typical),
        "full_width_points": len(widest),
        "full_width_frame_bytes": len(encode_segment(1, 0, widest)),
        "uart_segments_per_s": UART_BYTES_PER_S / (sum(frames) / len(frames)),
    }


def pty_throughput() -> dict[str, Any]:
    """Segments per second through Channel + codec + a pty bridge, each one acknowledged."""
    segment = _sim_segments("ellipsoid:a=30,b=20,c=40", ScanPlan.regular(1, 2.0, 1))[0]
    frame = encode_segment(1, 0, segment)
    bridge = PtyBridge()
    device_port = serial.Serial(bridge.device_port, timeout=0.01)
    host_port = serial.Serial(bridge.host_port, timeout=0.01)
    device, host = Channel(device_port), Channel(host_port)
    acks = [0]

    def count_acks() -> None:
        while acks[0] < LINK_SEGMENTS:
            message = device.receive(0.5)
            if message is None:
                return
            if message.kind is Kind.ACK:
                acks[0] += 1

    counter = threading.Thread(target=count_acks, daemon=True)
    counter.start()
    start = time.perf_counter()
    sender = threading.Thread(
        target=lambda: [device.send(frame) for _ in range(LINK_SEGMENTS)], daemon=True
    )
    sender.start()
    received = 0
    while received < LINK_SEGMENTS:
        message = host.receive(2.0)
        if message is None:
            break
        if isinstance(message.body, SegmentEvent):
            received += 1
            host.send(encode_json(Kind.ACK, {"id": 1, "seqs": [message.body.seq]}))
    counter.join(timeout=5)
    elapsed = time.perf_counter() - start
    for port in (device_port, host_port):
        port.close()
    bridge.close()
    return {
        "segments": received,
        "acknowledged": acks[0],
        "segment_points": len(segment),
        "segments_per_s": received / elapsed,
        "bytes_per_s": received * len(frame) / elapsed,
        "points_per_s": received * len(segment) / elapsed,
    }


@dataclass(frozen=True)
class BadLine:
    """One bad cable of the fault-injection figures."""

    name: str
    error_rate: float
    cuts: int = 0
    cut_s: float = 2.0

    def faults(self) -> LineFaults:
        """Return the line's fault injector (seeded: every run meets the same faults)."""
        cut_after = (50_000, 175_000, 190_000)[: self.cuts]
        return LineFaults(error_rate=self.error_rate, cut_after_bytes=cut_after, cut_s=self.cut_s)


BAD_LINES = (
    BadLine("ber_1e-3", 1e-3),
    BadLine("ber_1e-3_cuts", 1e-3, cuts=3),
    BadLine("ber_3e-3_cuts", 3e-3, cuts=3),
)
"""Issue 14's lines: a total byte error rate (flip, drop, duplicate in 2:1:1), 2 s cuts."""


def _full_scan(faults: LineFaults | None) -> dict[str, Any]:
    """Time a full simulated acquisition (grid, cylinder, object) into a library."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        start = time.perf_counter()
        with Library(out / "library.sqlite") as library, open_device("sim", transform=faults) as c:
            scan_id = _acquire(c, library, out)
            assert library.missing(scan_id, "object") == []
            channel = c.channel
            stats = {
                "request_retries": c.stats.request_retries,
                "fetch_rounds": c.stats.fetch_rounds,
                "repairs_asked": channel.repairs_asked,
                "bad_frames": channel.bad_frames,
                "fragment_bytes": channel.sizer.fragment_bytes,
                "measured_error_rate": channel.sizer.error_rate,
            }
        return {"s": time.perf_counter() - start, "host": stats}


def fault_overhead() -> dict[str, Any]:
    """Full-scan time on a clean line and on the bad lines, measured in the same run."""
    result: dict[str, Any] = {"clean": _full_scan(None)}
    for line in BAD_LINES:
        faults = line.faults()
        result[line.name] = {**_full_scan(faults), "counts": dict(faults.counts)}
    return result


def run() -> dict[str, Any]:
    """Measure everything."""
    return {"encoding": encoding(), "pty": pty_throughput(), "faults": fault_overhead()}


def report(results: dict[str, Any]) -> list[str]:
    """Return the summary lines."""
    enc, pty, faults = results["encoding"], results["pty"], results["faults"]
    clean = faults["clean"]["s"]
    lines = [
        f"  segment encoding: {enc['bytes_per_point']:.2f} bytes/point framed "
        f"(v1: {enc['v1_bytes_per_point']:.2f}); a {enc['full_width_points']}-column segment "
        f"is {enc['full_width_frame_bytes']} bytes; at 115200 baud "
        f"{enc['uart_segments_per_s']:.1f} typical segments/s "
        f"({enc['typical_points']:.0f} points each)",
        f"  pty link: {pty['segments_per_s']:.0f} segments/s, {pty['bytes_per_s'] / 1e3:.0f} kB/s, "
        f"{pty['points_per_s'] / 1e3:.0f} k points/s ({pty['segment_points']}-point segments, "
        "each acknowledged)",
        f"  full simulated scan (grid + 8 cylinder + 32 object views): clean {clean:.1f} s",
    ]
    for line in BAD_LINES:
        got = faults[line.name]
        cuts = f" + {line.cuts} cuts of {line.cut_s:g} s" if line.cuts else ""
        host = got["host"]
        lines.append(
            f"    byte error rate {line.error_rate:g}{cuts}: {got['s']:.1f} s "
            f"({got['s'] / clean:.2f}x clean; host measured {host['measured_error_rate']:.1e}, "
            f"frames of {host['fragment_bytes']} bytes, {host['repairs_asked']} repairs asked, "
            f"{host['request_retries']} requests repeated)"
        )
    return lines
