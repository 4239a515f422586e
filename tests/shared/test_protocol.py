"""Frames, COBS, CRC and message encodings of the link protocol."""

import numpy as np
import pytest

from lamina_shared.protocol import (
    MAX_PAYLOAD_BYTES,
    Chunk,
    FrameDecoder,
    Kind,
    ProtocolError,
    SegmentEvent,
    cobs_decode,
    cobs_encode,
    decode_frame,
    decode_message,
    encode_chunk,
    encode_frame,
    encode_json,
    encode_segment,
)
from lamina_shared.types import Segment


def make_segment(n: int = 640) -> Segment:
    rng = np.random.default_rng(1)
    return Segment(
        "object",
        3,
        5,
        6.0,
        225.0,
        np.arange(n, dtype=np.uint16),
        rng.uniform(0, 479, n).astype(np.float32),
        rng.integers(0, 256, n).astype(np.uint8),
        rng.integers(1, 20, n).astype(np.uint8),
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
    payloads = decoder.feed(b"\x00" + encode_json(Kind.HELLO, {"protocol": 1}))
    assert [decode_message(p).body for p in payloads] == [{"protocol": 1}]


def test_payload_limit_is_enforced_on_encode():
    with pytest.raises(ProtocolError):
        encode_frame(bytes(MAX_PAYLOAD_BYTES + 1))


def test_segment_round_trip_is_bit_exact():
    segment = make_segment()
    message = decode_message(decode_frame(encode_segment(42, segment)[1:-1]))
    assert message.kind is Kind.SEGMENT
    assert isinstance(message.body, SegmentEvent)
    assert message.body.request_id == 42
    assert message.body.segment.same_as(segment)


def test_segment_with_wrong_length_is_a_protocol_error():
    payload = decode_frame(encode_segment(1, make_segment(10))[1:-1])
    with pytest.raises(ProtocolError):
        decode_message(payload[:-1])


def test_chunk_round_trip_and_bounds():
    message = decode_message(decode_frame(encode_chunk(7, 4096, 5000, b"abc")[1:-1]))
    assert message.body == Chunk(7, 4096, 5000, b"abc")
    with pytest.raises(ProtocolError):
        decode_message(decode_frame(encode_chunk(7, 4999, 5000, b"abc")[1:-1]))


@pytest.mark.parametrize("payload", [b"", b"\x63{}", b"\x03not json", b"\x03[1, 2]"])
def test_bad_messages_raise_protocol_error(payload):
    with pytest.raises(ProtocolError):
        decode_message(payload)


def test_json_encoding_refuses_non_finite_numbers():
    with pytest.raises(ValueError):
        encode_json(Kind.EVENT, {"x": float("nan")})
