"""Binary transfers (a calibration image, a preview frame) put together from CHUNKs.

The device pushes a transfer once in pieces; the host keeps each piece by offset, then
asks ``fetch`` for the pieces it lacks until it holds all of them, and checks the whole
against the reply's byte count and CRC32 (``shared/PROTOCOL.md``, *CHUNK body*).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from lamina_host.link.errors import DeviceError
from lamina_shared.ops import FetchArgs
from lamina_shared.protocol import CHUNK_BYTES, MAX_TRANSFER_BYTES, Chunk, Message
from lamina_shared.replies import FetchReply, GridReply, PreviewReply

MAX_FETCH_ROUNDS = 1000
"""Fetch rounds after which a transfer that no longer grows is given up."""

Offering = TypeVar("Offering", GridReply, PreviewReply)
"""A reply that offers a binary transfer (its ``offer``)."""
Requester = Callable[[str, Any, Any, Callable[[Message], None] | None], Any]
"""Sends one request (op, reply class, arguments, message handler) until answered;
returns the typed reply (``DeviceClient.call``)."""


class Transfer:
    """One binary transfer being put together from pieces that arrive in any order."""

    def __init__(self, total: int) -> None:
        if total > MAX_TRANSFER_BYTES:
            raise DeviceError(f"the device offered {total} bytes, beyond this host's limit")
        self.total = total
        self.data = bytearray(total)
        self.have = np.zeros(-(-total // CHUNK_BYTES), bool)

    def take(self, chunk: Chunk) -> None:
        """Keep a piece if it is one this transfer expects."""
        index, expected = divmod(chunk.offset, CHUNK_BYTES)
        size = min(CHUNK_BYTES, self.total - chunk.offset)
        if chunk.total == self.total and expected == 0 and len(chunk.data) == size:
            self.data[chunk.offset : chunk.offset + size] = chunk.data
            self.have[index] = True

    def missing(self, max_bytes: int) -> list[list[int]]:
        """Return up to ``max_bytes`` of missing pieces as merged [offset, length] ranges."""
        ranges: list[list[int]] = []
        budget = max_bytes
        for index in np.flatnonzero(~self.have).tolist():
            offset = index * CHUNK_BYTES
            size = min(CHUNK_BYTES, self.total - offset)
            if size > budget:
                break
            budget -= size
            if ranges and ranges[-1][0] + ranges[-1][1] == offset:
                ranges[-1][1] += size
            else:
                ranges.append([offset, size])
        return ranges


class Transfers:
    """The transfers one request's CHUNKs belong to, by transfer number."""

    def __init__(self) -> None:
        self.by_number: dict[int, Transfer] = {}

    def take(self, message: Message) -> None:
        """Keep the piece a CHUNK carries (the request's other messages are not ours)."""
        chunk = message.body
        if isinstance(chunk, Chunk):
            if chunk.transfer not in self.by_number:
                self.by_number[chunk.transfer] = Transfer(chunk.total)
            self.by_number[chunk.transfer].take(chunk)


def fetch_transfer(
    call: Requester, op: str, reply_type: type[Offering], args: Any, max_fetch_bytes: int
) -> tuple[bytes, Offering, int]:
    """Run a request that offers a binary transfer; fetch what did not arrive.

    Args:
        call: sends a request until answered and reads its reply (``DeviceClient.call``).
        op: the operation that offers the transfer (``grab_grid``, ``preview``).
        reply_type: its reply class.
        args: its typed arguments.
        max_fetch_bytes: the most one ``fetch`` may ask for (the device's limits).

    Returns:
        The transfer's bytes, the typed reply and the number of fetch rounds.

    Raises:
        DeviceError: the reply is malformed, the transfer stopped growing or arrived damaged.
    """
    transfers = Transfers()
    reply: Offering = call(op, reply_type, args, transfers.take)
    number, total = reply.offer.transfer, reply.offer.size_bytes
    transfer = transfers.by_number.get(number) or Transfer(total)
    transfers.by_number = {number: transfer}
    rounds = 0
    while not transfer.have.all():
        before = int(transfer.have.sum())
        ranges = tuple((offset, length) for offset, length in transfer.missing(max_fetch_bytes))
        call("fetch", FetchReply, FetchArgs(number, ranges), transfers.take)
        rounds += 1
        if int(transfer.have.sum()) == before and rounds > MAX_FETCH_ROUNDS:
            raise DeviceError(f"the {op} transfer makes no progress: check the cable")
    data = bytes(transfer.data)
    if len(data) != total or zlib.crc32(data) != reply.offer.crc32:
        raise DeviceError(f"the {op} transfer arrived damaged: try again")
    return data, reply, rounds
