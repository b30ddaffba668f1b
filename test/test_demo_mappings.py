"""Unit tests of the demo backend's subscriber mappings (demo_buffer_backend/mappings.py), fed
through its inbox (inbox.py) by the publisher's links (links.py), both ends in this process,
without DDS: handover, take and ack, stale and unknown descriptors, holds, retired and orphaned
segments, a refused connection."""
import gc
import os

import pytest
from rosidl_buffer_py.backend import EndpointGone

from demo_buffer_backend import descriptor as codec
from demo_buffer_backend import handover, limits, memory
from demo_buffer_backend.diagnostics import Diagnostics
from demo_buffer_backend.guard import Guard
from demo_buffer_backend.inbox import Inbox
from demo_buffer_backend.links import Links
from demo_buffer_backend.mappings import Hold, Mappings
from demo_buffer_backend.slots import Slots


class Ends:
    """A publisher's slots and links and a subscriber's mappings, one process playing both."""

    def __init__(self) -> None:
        self.token = handover.new_token()
        nonce = int(self.token[-16:], 16)
        guard = Guard()
        self.publisher, self.subscriber = Diagnostics(), Diagnostics()
        self.slots = Slots(os.getpid(), nonce, guard, self.publisher,
                           lambda slot: self.links.retire(slot))
        self.links = Links(nonce, self.slots, self.publisher)
        self.inbox = Inbox(self.token, self.subscriber)
        self.mappings = Mappings(self.token, self.inbox, self.slots, guard, self.subscriber)
        assert self.inbox.listen()

    def publish(self, data: bytes):
        """A slot holding ``data`` handed over to the subscriber, and its descriptor."""
        view, pin = self.slots.allocate(len(data), gone=set())
        view[:] = data
        link = self.links.get(self.token)
        if pin.slot.id not in link.segments:
            assert self.links.hand_over(link, pin.slot)
        return pin, codec.Descriptor(os.getpid(), self.slots.nonce, pin.slot.id, pin.generation,
                                     0, len(data))

    def close(self) -> None:
        gc.collect()
        self.links.close()
        self.mappings.close()
        self.inbox.close()
        self.slots.close()


@pytest.fixture
def ends():
    made = Ends()
    yield made
    made.close()


def test_a_handed_over_segment_opens_read_only_and_the_take_is_acked(ends):
    pin, desc = ends.publish(b'frame')
    view, hold = ends.mappings.open(desc)
    assert bytes(view) == b'frame' and view.readonly and isinstance(hold, Hold)
    assert hold.segment == (os.getpid(), pin.slot.id) and hold.generation == desc.generation
    assert ends.subscriber.counters.handovers_received == 1
    ends.links.drain(ends.links.get(ends.token))
    assert pin.slot.taken == {ends.token: 1} and ends.publisher.counters.acks == 1


def test_a_hold_keeps_the_publisher_from_reusing_the_slot(ends):
    pin, desc = ends.publish(b'x' * 100)
    view, hold = ends.mappings.open(desc)
    fd = pin.slot.segment.fd
    assert not memory.try_lock(fd, exclusive=True)
    del view, hold
    gc.collect()
    assert memory.try_lock(fd, exclusive=True)
    memory.unlock(fd)


def test_stale_and_unknown_descriptors_are_refused(ends):
    pin, desc = ends.publish(b'old')
    pin.slot.start_generation(desc.generation + 1, 3)  # the publisher reused it
    with pytest.raises(ValueError, match='stale'):
        ends.mappings.open(desc)
    assert ends.subscriber.counters.stale == 1
    with pytest.raises(ValueError, match='did not hand to this one'):
        ends.mappings.open(desc._replace(segment_id=desc.segment_id + 100))
    with pytest.raises(ValueError, match='outside its segment'):
        ends.mappings.open(desc._replace(size=1 << 30))


def test_a_retired_segment_closes_once_no_view_holds_it(ends):
    pin, desc = ends.publish(b'r')
    view, hold = ends.mappings.open(desc)
    ends.slots.remove(pin.slot)  # retires it on the link
    ends.mappings.receive()
    assert len(ends.mappings) == 1  # still held
    del view, hold
    gc.collect()
    assert len(ends.mappings) == 0 and ends.subscriber.counters.mappings_closed == 1


def test_segments_of_a_publisher_that_hung_up_close_after_orphan_seconds(ends, monkeypatch):
    pin, desc = ends.publish(b'o')
    ends.mappings.receive()
    ends.links.close()
    monkeypatch.setattr(limits, 'ORPHAN_SECONDS', 3600)
    ends.mappings.receive()
    assert len(ends.mappings) == 1  # its frames may still be in the reader's history
    monkeypatch.setattr(limits, 'ORPHAN_SECONDS', 0)
    ends.mappings.receive()
    assert len(ends.mappings) == 0


def test_a_process_that_hung_up_is_gone_for_the_links(ends):
    ends.inbox.close()  # the subscriber process stops listening
    with pytest.raises(EndpointGone):
        ends.links.get(ends.token)
    assert ends.token in ends.links.gone and ends.publisher.counters.peers_gone == 1
    with pytest.raises(EndpointGone, match='its link hung up'):
        ends.links.get(ends.token)


def test_the_inbox_refuses_connections_past_max_inbound(ends, monkeypatch):
    monkeypatch.setattr(limits, 'MAX_INBOUND', 0)
    handover.Link(ends.token).close()
    assert ends.inbox.drain() == [] and not ends.inbox.inbound
    assert ends.subscriber.counters.connections_refused == 1
