"""Frames, COBS, CRC and message encodings of the link protocol."""

import json
import struct
from dataclasses import replace

import numpy as np
import pytest

from lamina_shared.protocol import (
    MAX_PAYLOAD_BYTES,
    ROW_SCALE,
    Chunk,
    FrameDecoder,
    Kind,
    ProtocolError,
    SegmentEvent,
    cobs_decode,
    cobs_encode,
    confidence_bytes,
    decode_frame,
    decode_message,
    encode_chunk,
    encode_frame,
    encode_json,
    encode_segment,
    quantise_segment,
)
from lamina_shared.types import CONFIDENCE_SCALE, Segment


def make_segment(n: int = 640, noise_px: float = 0.15) -> Segment:
    """A stripe across ``n`` columns: a smooth curve, speckle-like scatter, varying peaks."""
    rng = np.random.default_rng(1)
    cols = np.arange(n)
    rows = 240 + 60 * np.sin(cols / 150) + rng.normal(0, noise_px, n)
    peak = np.clip(150 + 40 * np.sin(cols / 40) + rng.normal(0, 20, n), 0, 255)
    width = np.clip(5 + rng.normal(0, 1.2, n), 1, 20)
    return quantise_segment(
        Segment(
            "object",
            3,
            5,
            6.0,
            225.0,
            cols.astype(np.uint16),
            rows.astype(np.float32),
            peak.astype(np.uint8),
            width.astype(np.uint8),
        )
    )


@pytest.mark.parametrize("size", [0, 1, 253, 254, 255, 508, 509, 3000])
def test_cobs_round_trip_has_no_zero(size):
    rng = np.random.default_rng(size)
    data = rng.integers(0, 4, size).astype(np.uint8).tobytes()  # many zeros
    encoded = cobs_encode(data)
    assert 0 not in encoded
    assert cobs_decode(encoded) == data


def test_cobs_known_vectors():
    # Vectors from the COBS paper / Wikipedia examples.
    assert cobs_encode(b"\x00") == b"\x01\x01"
    assert cobs_encode(b"\x00\x00") == b"\x01\x01\x01"
    assert cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    assert cobs_encode(b"\x11\x00\x00\x00") == b"\x02\x11\x01\x01\x01"
    assert cobs_encode(bytes(range(1, 255))) == b"\xff" + bytes(range(1, 255)) + b"\x01"


def test_crc_mismatch_is_rejected():
    frame = bytearray(encode_frame(b"\x03hello"))
    frame[2] ^= 0x01
    with pytest.raises(ProtocolError):
        decode_frame(bytes(frame[1:-1]))


def test_decoder_resynchronises_after_garbage_and_damage():
    good = [encode_json(Kind.EVENT, {"id": k, "event": "progress"}) for k in range(3)]
    damaged = bytearray(good[1])
    damaged[5] ^= 0xFF
    stream = b"\x17\x99garbage" + good[0] + bytes(damaged) + good[2]
    decoder = FrameDecoder()
    payloads = []
    for k in range(0, len(stream), 7):  # arrive in small pieces
        payloads += decoder.feed(stream[k : k + 7])
    ids = [decode_message(p).body["id"] for p in payloads]
    assert ids == [0, 2]
    assert decoder.errors == 2


def test_decoder_drops_oversized_runs_without_growing():
    decoder = FrameDecoder()
    for _ in range(40):
        assert decoder.feed(b"\x01" * 4096) == []
    assert len(decoder._buffer) <= FrameDecoder._MAX_ENCODED
    payloads = decoder.feed(b"\x00" + encode_json(Kind.HELLO, {"protocol": 2}))
    assert [decode_message(p).body for p in payloads] == [{"protocol": 2}]


def test_payload_limit_is_enforced_on_encode():
    with pytest.raises(ProtocolError):
        encode_frame(bytes(MAX_PAYLOAD_BYTES + 1))


def decode(frame: bytes):
    return decode_message(decode_frame(frame[1:-1]))


def test_segment_round_trip_is_bit_exact():
    segment = make_segment()
    message = decode(encode_segment(42, 17, segment))
    assert message.kind is Kind.SEGMENT
    assert isinstance(message.body, SegmentEvent)
    assert (message.body.request_id, message.body.seq) == (42, 17)
    assert message.body.segment.same_as(segment)


@pytest.mark.parametrize("n", [0, 1, 2, 31, 32, 33, 500])
def test_segments_of_any_length_and_gappy_columns_round_trip(n):
    full = make_segment(3 * n + 3)
    keep = np.sort(np.random.default_rng(n).choice(len(full), n, replace=False))
    segment = Segment("cylinder", 0, 1, 0.5, -45.0, *(getattr(full, f)[keep] for f in SEG_FIELDS))
    assert decode(encode_segment(1, 2, segment)).body.segment.same_as(segment)


SEG_FIELDS = ("cols", "rows", "peak", "width")


@pytest.mark.parametrize("turns", [0, 1, -1, 41, 2**31 - 1, -(2**31)])
def test_a_segments_whole_turns_travel_exactly(turns):
    """The step count's whole turns (negative after turning back past power-up's 0) go
    over the wire as sent; a count beyond 32 bits cannot be encoded at all."""
    segment = replace(make_segment(50), turns=turns)
    got = decode(encode_segment(3, 4, segment)).body.segment
    assert got.turns == turns and got.same_as(segment)
    assert got.count_deg == segment.angle_deg + 360.0 * turns
    with pytest.raises(struct.error):
        encode_segment(3, 4, replace(segment, turns=2**31))


def test_full_width_segment_fits_in_one_and_a_half_kilobytes():
    # 0.15 px scatter is what the simulated rig's speckle gives (see bench_link).
    frame = encode_segment(1, 0, make_segment(640))
    assert len(frame) <= 1536, len(frame)


def test_rows_are_fixed_point_at_one_sixty_fourth_pixel():
    raw = make_segment(8)
    rows = raw.rows + np.float32(0.3 / ROW_SCALE)  # off the grid
    off_grid = Segment("object", 0, 0, 0.0, 0.0, raw.cols, rows, raw.peak, raw.width)
    with pytest.raises(ProtocolError, match="quantise"):
        encode_segment(1, 0, off_grid)
    on_grid = quantise_segment(off_grid)
    assert np.max(np.abs(on_grid.rows - rows)) <= 0.5 / ROW_SCALE
    assert np.array_equal(on_grid.rows * ROW_SCALE, np.rint(on_grid.rows * ROW_SCALE))


def test_segment_with_wrong_length_is_a_protocol_error():
    payload = decode_frame(encode_segment(1, 0, make_segment(10))[1:-1])
    for cut in (1, 5, len(payload) - 40):
        with pytest.raises(ProtocolError):
            decode_message(payload[:-cut])
    with pytest.raises(ProtocolError):
        decode_message(payload + b"\x00")


def test_chunk_round_trip_and_bounds():
    message = decode(encode_chunk(7, 2, 4096, 5000, b"abc"))
    assert message.body == Chunk(7, 2, 4096, 5000, b"abc")
    with pytest.raises(ProtocolError):
        decode(encode_chunk(7, 2, 4999, 5000, b"abc"))
    with pytest.raises(ProtocolError):
        decode(encode_chunk(7, 2, 0, 2**32 - 1, b"abc"))  # beyond the transfer limit


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        b"\x63{}",
        b"\x03not json",
        b"\x03[1, 2]",
        b'\x03{"x": NaN}',
        b"\x03" + b"[" * 100_000,
        b'\x03{"x": ' + b"9" * 5000 + b"}",
    ],
)
def test_bad_messages_raise_protocol_error(payload):
    with pytest.raises(ProtocolError):
        decode_message(payload)


def test_json_encoding_refuses_non_finite_numbers():
    with pytest.raises(ValueError):
        encode_json(Kind.EVENT, {"x": float("nan")})


def test_json_kinds_round_trip():
    for kind in (Kind.ACK, Kind.HEARTBEAT, Kind.REQUEST):
        body = {"id": 3, "seqs": [1, 2], "note": "é"}
        assert decode(encode_json(kind, body)) == decode_message(
            bytes([kind]) + json.dumps(body).encode()
        )


def with_confidence(segment: Segment, confidence: np.ndarray) -> Segment:
    """Return ``segment`` carrying ``confidence`` (uint8 per point)."""
    fields = (getattr(segment, f) for f in SEG_FIELDS)
    head = (segment.target, segment.section, segment.view, segment.z_mm, segment.angle_deg)
    return Segment(*head, *fields, confidence.astype(np.uint8))


@pytest.mark.parametrize("n", [1, 2, 33, 640])
def test_any_confidence_bytes_round_trip(n):
    segment = make_segment(n)
    rng = np.random.default_rng(n)
    confidence = rng.integers(0, 256, n)
    confidence[:3] = 255  # saturated
    peak = segment.peak.copy()
    peak[-1] = 0  # a point without a peak can only have confidence 0
    confidence[-1] = 0
    segment = with_confidence(replace(segment, peak=peak), confidence)
    assert decode(encode_segment(1, 2, segment)).body.segment.same_as(segment)


@pytest.mark.parametrize("noise_dn", [1e-4, 0.37, 1.0, 2.9, 6.3, 17.0, 255.0, 1e6])
def test_confidence_of_8_bit_peaks_is_the_same_by_table(noise_dn):
    """The device's 8-bit peaks are looked up in a table: the bytes of the general path."""
    peak = np.arange(256, dtype=np.uint8)
    assert np.array_equal(
        confidence_bytes(peak, noise_dn), confidence_bytes(peak.astype(np.int64), noise_dn)
    )


def test_confidence_of_one_noise_costs_a_few_bytes_a_segment():
    segment = make_segment(640)
    plain = len(encode_segment(1, 0, segment))
    device = with_confidence(segment, confidence_bytes(segment.peak, 6.3))
    assert device.confidence.min() > 0
    got = decode(encode_segment(1, 0, device)).body.segment
    assert got.same_as(device)
    assert len(encode_segment(1, 0, device)) - plain <= 4  # one scale run
    expected = np.minimum(segment.peak / 6.3 * CONFIDENCE_SCALE, 255)
    # The scale travels in 1/256: rounding it moves a confidence byte by at most one.
    assert np.abs(device.confidence - expected).max() <= 1.0


def test_confidence_without_a_peak_is_refused():
    segment = make_segment(4)
    segment = with_confidence(replace(segment, peak=np.zeros(4, np.uint8)), np.full(4, 9))
    with pytest.raises(ProtocolError, match="peak 0"):
        encode_segment(1, 0, segment)
