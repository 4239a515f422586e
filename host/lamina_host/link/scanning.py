"""The host's side of a scan request: store each segment, then acknowledge it.

A :class:`ScanReceiver` hears every message of one ``scan`` request. A new segment is
checked against the plan, handed to the caller (who stores it) and only then
acknowledged; a repeat is acknowledged again, not stored twice. Each ACK also names the
earlier plan indices still missing (segments come in plan order, so those were lost),
and a device heartbeat that reports unacknowledged segments gets the latest ones
acknowledged again (``shared/PROTOCOL.md``, *Segments*).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Collection

from lamina_host.link.errors import DeviceError
from lamina_shared.link import Channel
from lamina_shared.messages import Ack, DeviceHeartbeat, Event, MessageError, parse_event
from lamina_shared.protocol import Kind, Message, SegmentEvent, encode_json
from lamina_shared.types import ScanPlan, Segment

REACK_SEQS = 16
"""Segments acknowledged again when a heartbeat says the device still holds some (its
window)."""

IndexedSegmentHandler = Callable[[int, Segment], object]
"""Receives (seq, segment) for each new segment; it must have stored it when it returns."""
EventHandler = Callable[[Event], object]
"""Receives a scan's typed events: progress per view, status, log."""

log = logging.getLogger(__name__)


class ScanReceiver:
    """What the host does with each message of one scan request.

    Args:
        channel: the link, for the acknowledgements.
        target: what is scanned (``cylinder`` or ``object``), as the segments must say.
        plan: the whole plan; the segments' ``seq`` index it.
        held: plan indices the caller already holds (a resumed scan).
        image_size: the device's image (width, height): no point may lie outside it.
        on_segment: stores each new segment before it is acknowledged.
        on_event: hears the scan's events.
    """

    def __init__(
        self,
        channel: Channel,
        target: str,
        plan: ScanPlan,
        held: Collection[int],
        image_size: tuple[int, int],
        on_segment: IndexedSegmentHandler | None = None,
        on_event: EventHandler | None = None,
    ) -> None:
        self.channel, self.target, self.plan = channel, target, plan
        self.held = set(held)
        self.image_size = image_size
        self.on_segment, self.on_event = on_segment, on_event
        self.received: dict[int, Segment] = {}
        """New segments by plan index, in the order they arrived."""
        self.duplicates = 0
        """Segments that arrived again (held already or received before)."""
        self._expected = [s for s in range(len(plan.views)) if s not in self.held]

    def take(self, message: Message) -> None:
        """Handle one message of the scan request (the request's ``on_event``)."""
        if isinstance(message.body, SegmentEvent):
            self._segment(message.body)
        elif message.kind is Kind.HEARTBEAT:
            self._heartbeat(message)
        elif message.kind is Kind.EVENT and self.on_event is not None:
            try:
                event = parse_event(message.body)
            except MessageError as exc:
                log.warning("ignoring a malformed event from the device (%s)", exc)
                return
            self.on_event(event)

    def missing(self) -> set[int]:
        """Return the plan indices neither held before nor received."""
        return set(range(len(self.plan.views))) - self.held - set(self.received)

    def _segment(self, body: SegmentEvent) -> None:
        if body.seq not in self.held and body.seq not in self.received:
            check_segment(body, self.target, self.plan, self.image_size)
            if self.on_segment is not None:
                self.on_segment(body.seq, body.segment)
            self.received[body.seq] = body.segment
        else:
            self.duplicates += 1
        # Stored (or already held): acknowledge, also a repeat whose ack was lost.
        # Views come in plan order, so earlier ones still missing were lost.
        lost = [s for s in self._expected if s < body.seq and s not in self.received]
        self._send(Ack.stored(body.request_id, body.seq, lost))

    def _heartbeat(self, message: Message) -> None:
        # The device still holds segments: if it is one we stored, our ACK was lost;
        # acknowledging the latest again now beats the device's backoff.
        try:
            beat = DeviceHeartbeat.from_wire(message.body)
        except MessageError as exc:
            log.warning("ignoring a malformed heartbeat from the device (%s)", exc)
            return
        if beat.unacked > 0 and self.received and beat.request is not None:
            self._send(Ack(beat.request, tuple(self.received)[-REACK_SEQS:]))

    def _send(self, ack: Ack) -> None:
        self.channel.send(encode_json(Kind.ACK, ack.to_wire()))


def check_segment(
    event: SegmentEvent, target: str, plan: ScanPlan, image_size: tuple[int, int]
) -> None:
    """Refuse a segment that does not belong where it claims or lies outside the image."""
    segment, seq = event.segment, event.seq
    problem = None
    if seq >= len(plan.views):
        problem = f"view {seq} of a {len(plan.views)}-view plan"
    else:
        labels = (segment.section, segment.z_mm, segment.angle_deg)
        if segment.target != target or not plan.labels(seq, *labels):
            problem = f"view {seq} labelled differently from the plan"
        elif len(segment) and (
            int(segment.cols[-1]) >= image_size[0] or float(segment.rows.max()) >= image_size[1]
        ):
            problem = f"view {seq} has points outside the {image_size[0]}x{image_size[1]} image"
    if problem:
        raise DeviceError(f"the device sent a segment beyond this host's limits ({problem})")
