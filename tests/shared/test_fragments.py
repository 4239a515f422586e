"""Frames that adapt to the line: fragments, their reassembly and repair, the frame sizer."""

from __future__ import annotations

import json
import threading
import time
import zlib

import numpy as np
import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from lamina_host.link.spawn import PtyBridge
from lamina_host.testing import LineFaults
from lamina_shared.limits import DeviceLimits
from lamina_shared.link import (
    FRAGMENT_KIND,
    REPAIR_KIND,
    Channel,
    FrameSizer,
    Reassembly,
    SentMessages,
    decode_repair,
    fragment_frames,
    repair_frame,
)
from lamina_shared.protocol import (
    MAX_PAYLOAD_BYTES,
    PROTOCOL_VERSION,
    FrameDecoder,
    Kind,
    ProtocolError,
    decode_message,
    encode_json,
)


def payloads_of(frames: bytes) -> list[bytes]:
    """Split the bytes of concatenated frames into their payloads."""
    return FrameDecoder().feed(frames)


def message(n_bytes: int, seed: int = 0) -> bytes:
    """A payload of ``n_bytes`` with no structure a reassembly could lean on."""
    return bytes(np.random.default_rng(seed).integers(0, 256, n_bytes, dtype=np.uint8))


def test_fragments_respect_the_size_and_rebuild_the_message_in_any_order():
    whole = message(5000)
    pieces = payloads_of(fragment_frames(whole, 300))
    assert len(pieces) == 17 and all(p[0] == FRAGMENT_KIND for p in pieces)
    assert max(len(p) for p in pieces) == 300 + 13
    order = np.random.default_rng(1).permutation(len(pieces))
    reassembly = Reassembly(8, 100_000)
    got = [reassembly.take(pieces[i], 0.0) for i in order]
    assert got[-1] == whole and all(g is None for g in got[:-1])
    assert len(reassembly) == 0 and reassembly.held_bytes == 0


def test_copies_at_other_sizes_fill_the_gaps_and_duplicates_are_harmless():
    whole = message(4000, seed=2)
    first = payloads_of(fragment_frames(whole, 200))
    second = payloads_of(fragment_frames(whole, 96))  # the sender shrank its frames meanwhile
    reassembly = Reassembly(8, 100_000)
    # The first copy loses every third piece, each survivor arrives twice.
    for piece in [p for k, p in enumerate(first) if k % 3] * 2:
        assert reassembly.take(piece, 0.0) is None
    lost = [(k * 200, 200) for k in range(0, len(first), 3)]
    assert reassembly.repairs(1.0) == [((zlib.crc32(whole), 4000), lost)]
    results = [reassembly.take(p, 1.0) for p in second]
    assert results.count(whole) == 1
    # Asked for too often, the gaps of a message no longer are: it completed.
    assert reassembly.repairs(2.0) == []


def test_repairs_are_asked_once_the_fragments_stop_until_max_repairs_bring_nothing():
    whole = message(1000, seed=3)
    pieces = payloads_of(fragment_frames(whole, 100))
    reassembly = Reassembly(8, 100_000, idle_s=0.05, repeat_s=0.25, max_repairs=2)
    reassembly.take(pieces[0], 0.0)
    assert reassembly.repairs(0.01) == []  # more pieces may still be on their way
    reassembly.count_frame()  # a frame of another message came: the rest was lost
    assert reassembly.repairs(0.02) == [((zlib.crc32(whole), 1000), [(100, 900)])]
    assert reassembly.repairs(0.1) == []  # asked a moment ago
    assert len(reassembly.repairs(0.3)) == 1
    assert reassembly.repairs(1.0) == []  # asked twice for nothing: left to the layer above
    reassembly.take(pieces[5], 1.1)  # a repair came after all: the count starts again
    reassembly.count_frame()
    assert reassembly.repairs(1.2) == [((zlib.crc32(whole), 1000), [(100, 400), (600, 400)])]


def test_reassembly_memory_is_bounded_and_the_oldest_wait_is_dropped():
    limits = DeviceLimits()
    reassembly = Reassembly(limits.max_partial_messages, limits.max_reassembly_bytes)
    for seed in range(100):
        whole = message(MAX_PAYLOAD_BYTES, seed)
        reassembly.take(payloads_of(fragment_frames(whole, 4096))[0], float(seed))
        assert reassembly.held_bytes <= limits.max_reassembly_bytes
    assert len(reassembly) == limits.max_reassembly_bytes // MAX_PAYLOAD_BYTES
    many = Reassembly(4, 10**9)
    for seed in range(10):
        many.take(payloads_of(fragment_frames(message(500, seed), 100))[0], 0.0)
    assert len(many) == 4


def test_fragments_that_do_not_make_up_their_message_are_refused():
    whole = message(600, seed=4)
    pieces = payloads_of(fragment_frames(whole, 200))
    forged = bytearray(pieces[1])
    forged[-1] ^= 1  # a wrong byte under a valid frame CRC (a sender's bug, not the line)
    reassembly = Reassembly(8, 100_000)
    reassembly.take(pieces[0], 0.0)
    reassembly.take(bytes(forged), 0.0)
    with pytest.raises(ProtocolError, match="do not make up"):
        reassembly.take(pieces[2], 0.0)
    for bad in (pieces[0][:13], bytes([FRAGMENT_KIND]) + (1).to_bytes(4, "little") * 3 + b"xx"):
        with pytest.raises(ProtocolError):
            Reassembly(8, 100_000).take(bad, 0.0)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(min_size=0, max_size=80), max_size=40))
def test_any_received_fragment_or_repair_raises_only_protocol_error(blobs):
    reassembly = Reassembly(4, 4096)
    for blob in blobs:
        for kind in (FRAGMENT_KIND, REPAIR_KIND):
            payload = bytes([kind]) + blob
            try:
                if kind == FRAGMENT_KIND:
                    reassembly.take(payload, 0.0)
                else:
                    decode_repair(payload)
            except ProtocolError:
                pass
        assert reassembly.held_bytes <= 4096 and len(reassembly) <= 4


def test_repair_requests_round_trip_and_sent_messages_are_bounded():
    ranges = [(0, 10), (100, 50)]
    key, got = decode_repair(payloads_of(repair_frame(7, 200, ranges))[0])
    assert key == (7, 200) and got == ranges
    with pytest.raises(ProtocolError):
        decode_repair(payloads_of(repair_frame(7, 120, ranges))[0])  # past the message
    with pytest.raises(ProtocolError, match="longer than"):
        decode_repair(payloads_of(repair_frame(7, 200, [(0, 200), (0, 200)]))[0])
    sent = SentMessages(3, 2500)
    kept = [message(1000, seed) for seed in range(4)]
    for payload in kept:
        sent.keep(payload)
    assert sent.get((zlib.crc32(kept[0]), 1000)) is None  # beyond 2,500 bytes
    assert sent.get((zlib.crc32(kept[3]), 1000)) == kept[3]


def test_the_sizer_shrinks_on_errors_and_timeouts_and_grows_back_on_a_clean_line():
    sizer = FrameSizer()
    start = sizer.fragment_bytes
    assert start <= 200  # small until the line proves clean
    for _ in range(100):
        sizer.observe(10_000, 0)
    clean = sizer.fragment_bytes
    assert clean > 1000
    for _ in range(100):
        sizer.observe(1_000, 3)  # 3e-3
    noisy = sizer.fragment_bytes
    assert noisy == sizer.min_bytes
    for _ in range(300):
        sizer.observe(10_000, 0)
    assert sizer.fragment_bytes > 1000
    before = sizer.fragment_bytes
    for _ in range(20):
        sizer.penalise()
    assert sizer.fragment_bytes < before / 2
    # A frame of the chosen size survives a line at the measured rate most of the time.
    for rate in (1e-4, 1e-3, 3e-3):
        sizer = FrameSizer(errors=rate * 1e6, bytes_seen=1e6)
        assert (1 - rate) ** (sizer.fragment_bytes + 24) > 0.6


def test_a_long_message_sent_once_crosses_a_line_that_damages_three_bytes_in_a_thousand():
    """Over real ptys: a 20 kB message goes once; repairs fill whatever the line destroys."""
    faults = LineFaults(error_rate=3e-3, seed=11)
    bridge = PtyBridge(faults)
    ports = [serial.Serial(p, timeout=0.02) for p in (bridge.device_port, bridge.host_port)]
    device, host = (Channel(port) for port in ports)
    body = {"id": 1, "event": "log", "text": message(10_000, seed=5).hex()}
    stop = threading.Event()

    def device_reads() -> None:  # the sender must read to hear repair requests
        while not stop.is_set():
            device.receive(0.05)

    received: list = []

    def host_reads() -> None:  # from before the send: a loaded machine may fill the ptys
        deadline = time.monotonic() + 30
        while not received and time.monotonic() < deadline and not stop.is_set():
            if (message_in := host.receive(0.1)) is not None:
                received.append(message_in)

    reader = threading.Thread(target=device_reads, daemon=True)
    listener = threading.Thread(target=host_reads, daemon=True)
    reader.start()
    listener.start()
    try:
        device.sizer = FrameSizer(errors=3.0, bytes_seen=1000.0)  # as measured on this line
        device.send(encode_json(Kind.EVENT, body))
        listener.join(timeout=30)
    finally:
        stop.set()
        reader.join(timeout=2)
        listener.join(timeout=2)
        for port in ports:
            port.close()
        bridge.close()
    got = received[0] if received else None
    assert got is not None and got.kind is Kind.EVENT and got.body == body
    assert faults.counts["flipped"] + faults.counts["dropped"] + faults.counts["duplicated"] > 20
    assert host.repairs_asked > 0 and device.repairs_served > 0
    assert host.bad_frames > 0


def test_a_peer_of_another_version_gets_the_versions_in_one_whole_frame():
    """So an older host that cannot read fragments still names the mismatch."""
    from lamina_device.server import DeviceServer
    from lamina_device.sim import open_sim

    bridge = PtyBridge()
    hardware = open_sim("cylinder:d=19.05")
    device_port = serial.Serial(bridge.device_port, timeout=0.02)
    host_port = serial.Serial(bridge.host_port, timeout=0.02)
    server = DeviceServer(Channel(device_port), hardware)
    thread = threading.Thread(target=server.serve, daemon=True)
    thread.start()
    try:
        host_port.write(encode_json(Kind.HELLO, {"protocol": 3, "session": "old"}))
        decoder, payloads = FrameDecoder(), []
        deadline = time.monotonic() + 10
        while not payloads and time.monotonic() < deadline:
            payloads = decoder.feed(host_port.read(4096))
    finally:
        server.running = False
        thread.join(timeout=5)
        for port in (device_port, host_port):
            port.close()
        bridge.close()
        hardware.close()
    assert payloads, "no WELCOME"
    welcome = decode_message(payloads[0])
    assert welcome.kind is Kind.WELCOME
    assert json.loads(json.dumps(welcome.body))["protocol"] == PROTOCOL_VERSION
    assert set(welcome.body) == {"protocol", "software"}
