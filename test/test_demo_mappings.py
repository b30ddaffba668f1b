"""Unit tests of the demo backend's subscriber mappings (demo_buffer_backend/mappings.py), fed
through its inbox (inbox.py) by the publisher's links (links.py), both ends in this process,
without DDS: handover, take and ack, stale and unknown descriptors, holds, retired and orphaned
segments, a refused connection; and two pools of one process, where the subscriber's inbox
thread screens connections and answers each handover (refusals, limits per process)."""
import gc
import os
import socket
import time

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


PUBLISHER_GID = b'\x01' * 16


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
        # discovery showed this process as a matched buffer-aware publisher
        self.inbox.expect(PUBLISHER_GID, os.getpid())

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
    # acknowledged once the view is let go, not between the take and the callback
    assert pin.slot.taken == {} and ends.publisher.counters.acks == 0
    del view, hold
    gc.collect()
    ends.links.drain(ends.links.get(ends.token))
    assert pin.slot.taken == {ends.token: 1} and ends.publisher.counters.acks == 1


def test_a_take_still_held_is_acknowledged_before_the_next_one_opens(ends):
    first_pin, first = ends.publish(b'first')
    held = ends.mappings.open(first)
    second_pin, second = ends.publish(b'second')
    assert second_pin.slot is not first_pin.slot
    view, hold = ends.mappings.open(second)
    ends.links.drain(ends.links.get(ends.token))
    assert first_pin.slot.taken == {ends.token: 1} and second_pin.slot.taken == {}
    del view, hold
    gc.collect()
    ends.links.drain(ends.links.get(ends.token))
    assert second_pin.slot.taken == {ends.token: 1} and ends.publisher.counters.acks == 2
    assert bytes(held[0]) == b'first'


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


# --- two pools of one process: a publisher's and a subscriber's, with the inbox's thread -------

@pytest.fixture
def pools():
    """A publisher's pool and a subscriber's pool (listening, its inbox thread running) in this
    process; the subscriber discovered this process as a matched publisher unless a test
    forgets it."""
    from demo_buffer_backend.pool import Pool
    subscriber, publisher = Pool(handover.new_token()), Pool(handover.new_token())
    assert subscriber.advertise() == subscriber.token
    subscriber.expect(PUBLISHER_GID, os.getpid())
    yield publisher, subscriber
    gc.collect()
    publisher.shutdown()
    subscriber.shutdown()


def _ledger(token):
    from demo_buffer_backend.ledgers import EndpointLedger
    return EndpointLedger(token, None, per_channel=False)


def test_a_refused_segment_goes_as_cpu_bytes_never_as_a_descriptor(pools, monkeypatch, caplog):
    """A subscriber that cannot map a segment (here: one per publisher process) says so before
    the frame's descriptor would leave: the publisher sends that frame as CPU bytes (describe
    gives None) instead of a descriptor the subscriber would reject; both sides count it."""
    monkeypatch.setattr(limits, 'MAX_MAPPINGS_PER_PROCESS', 1)
    publisher, subscriber = pools
    ledger = _ledger(subscriber.token)
    view, first = publisher.allocate(4096)
    view[:5] = b'first'
    packed = publisher.describe(first, ledger)
    assert packed is not None
    got, hold = subscriber.open_descriptor(packed)
    assert bytes(got[:5]) == b'first'
    view2, second = publisher.allocate(4096)  # the first slot is pinned: a second segment
    assert second.slot is not first.slot
    assert publisher.describe(second, ledger) is None  # refused: CPU bytes for this frame
    assert publisher.describe(second, ledger) is None  # and for every frame of that segment
    pub, sub = publisher.stats(), subscriber.stats()
    assert pub['handovers_refused'] == 1 and pub['descriptors_declined'] == 2, pub
    assert pub['verdicts_late'] == 0 and pub['descriptors_created'] == 1, pub
    assert sub['handovers_rejected'] == 1 and sub['rejected'] == 0 and sub['mappings'] == 1, sub


def test_a_connection_of_an_undiscovered_process_is_refused_then_the_publisher_relinks(
        pools, monkeypatch):
    """A process discovery never showed as a matched publisher is not read; after
    ``PENDING_SECONDS`` its connection is refused with the reason, and the publisher sends
    CPU bytes until ``RELINK_SECONDS`` have passed; once discovered, its new link serves."""
    monkeypatch.setattr(limits, 'PENDING_SECONDS', 0.2)
    monkeypatch.setattr(limits, 'RELINK_SECONDS', 0.3)
    publisher, subscriber = pools
    subscriber.forget(PUBLISHER_GID)
    ledger = _ledger(subscriber.token)
    view, pin = publisher.allocate(4096)
    assert publisher.describe(pin, ledger) is not None  # no verdict in time: sent, unanswered
    assert publisher.stats()['verdicts_late'] == 1
    deadline = time.monotonic() + 5
    while subscriber.stats()['connections_refused'] == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert subscriber.stats()['connections_refused'] == 1
    assert subscriber.stats()['handovers_received'] == 0  # never read
    assert publisher.describe(pin, ledger) is None  # refused link: CPU bytes
    assert publisher.stats()['links_refused'] == 1 and not publisher.stats()['peers_hung_up']
    subscriber.expect(PUBLISHER_GID, os.getpid())
    time.sleep(0.35)
    packed = publisher.describe(pin, ledger)  # a new link, its segment accepted
    assert packed is not None
    got, hold = subscriber.open_descriptor(packed)
    assert len(got) == 4096 and subscriber.stats()['handovers_received'] == 1


def test_the_inbox_thread_accepts_without_a_take_and_bounds_each_process(pools, monkeypatch):
    """Connections are accepted and screened by the inbox's thread with nobody taking: a full
    backlog of silent connections from one undiscovered process clears at once but for
    ``MAX_PENDING_PER_PROCESS``, which wait, unread, until ``PENDING_SECONDS``."""
    monkeypatch.setattr(limits, 'PENDING_SECONDS', 0.3)
    publisher, subscriber = pools
    subscriber.forget(PUBLISHER_GID)
    links = []
    while len(links) < 200:  # the attack: fill the listen backlog
        try:
            links.append(handover.Link(subscriber.token))
        except BlockingIOError:
            break
    deadline = time.monotonic() + 5
    while True:  # cleared by the thread, nobody taking
        try:
            links.append(handover.Link(subscriber.token))
            break
        except BlockingIOError:
            assert time.monotonic() < deadline, 'the backlog never cleared'
            time.sleep(0.01)
    while (subscriber.stats()['connections_refused'] < len(links) -
           limits.MAX_PENDING_PER_PROCESS and time.monotonic() < deadline):
        time.sleep(0.01)
    assert subscriber.stats()['connections_refused'] == len(links) - \
        limits.MAX_PENDING_PER_PROCESS
    assert len(subscriber.inbox.pending) == limits.MAX_PENDING_PER_PROCESS
    while subscriber.inbox.pending and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not subscriber.inbox.pending
    assert subscriber.stats()['connections_refused'] == len(links)
    for link in links:  # each was told, then closed
        replies, hung_up = link.replies()
        assert hung_up and [r.kind for r in replies] == [handover.ReplyKind.UNWANTED]
        link.close()


@pytest.fixture
def link_pair():
    """A Link's publisher end over a SOCK_SEQPACKET pair, and the subscriber's end; both
    closed at the end (closing twice is harmless: tests close them to hang up)."""
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ours.setblocking(False)
    link = handover.Link.__new__(handover.Link)
    link.sock = ours
    yield link, theirs
    ours.close()
    theirs.close()


def test_replies_returns_the_records_in_order_and_skips_ones_of_another_size(link_pair):
    link, theirs = link_pair
    assert link.replies() == ([], False)  # nothing queued: no exception, not hung up
    assert handover.send_reply(theirs, handover.ReplyKind.TAKEN, 3, 7)
    theirs.send(b'x' * (handover.REPLY.size + 1))  # not a reply: skipped
    theirs.send(b'x' * (handover.REPLY.size - 1))
    assert handover.send_reply(theirs, handover.ReplyKind.REFUSED, 4, 2)
    replies, hung_up = link.replies()
    assert not hung_up
    assert replies == [handover.Reply(3, handover.ReplyKind.TAKEN, 7),
                       handover.Reply(4, handover.ReplyKind.REFUSED, 2)]
    assert link.replies() == ([], False)


def test_replies_reads_a_burst_of_records_in_one_call(link_pair):
    link, theirs = link_pair
    for n in range(40):
        assert handover.send_reply(theirs, handover.ReplyKind.TAKEN, n, n + 1)
    replies, hung_up = link.replies()
    assert not hung_up
    assert replies == [handover.Reply(n, handover.ReplyKind.TAKEN, n + 1) for n in range(40)]
    for n in range(16):
        assert handover.send_reply(theirs, handover.ReplyKind.TAKEN, n, 0)
    assert len(link.replies()[0]) == 16
    assert link.replies() == ([], False)
    theirs.close()
    assert link.replies() == ([], True)


def test_a_link_says_accepted_only_for_a_segment_its_subscriber_mapped(link_pair):
    link, _ = link_pair
    link.verdicts = {3: handover.Reply(3, handover.ReplyKind.ACCEPTED, 0),
                     4: handover.Reply(4, handover.ReplyKind.REFUSED, 1)}
    assert link.accepted(3)
    assert not link.accepted(4) and not link.accepted(5)


def test_replies_of_a_peer_that_closed_come_with_the_hang_up(link_pair):
    link, theirs = link_pair
    assert handover.send_reply(theirs, handover.ReplyKind.TAKEN, 1, 2)
    theirs.close()
    assert link.replies() == ([handover.Reply(1, handover.ReplyKind.TAKEN, 2)], True)
    assert link.replies() == ([], True)


def test_replies_read_past_the_reset_of_a_peer_that_closed_with_records_of_ours_unread(
        link_pair):
    link, theirs = link_pair
    link.sock.send(b'unread by the peer')
    assert handover.send_reply(theirs, handover.ReplyKind.UNWANTED, 0, 1)
    theirs.close()  # with our record unread: the kernel reports ECONNRESET first
    replies, hung_up = link.replies()
    assert hung_up and replies == [handover.Reply(0, handover.ReplyKind.UNWANTED, 1)]


def test_replies_on_a_closed_link_say_hung_up(link_pair):
    link, theirs = link_pair
    link.sock.close()
    theirs.close()
    assert link.replies() == ([], True)


def _take_all(ends, raws):
    """What taking each of ``raws`` gives: the view's bytes and the hold's generation, or the
    error's text; the holds are kept."""
    outcomes, holds = [], []
    for raw in raws:
        try:
            view, hold = ends.mappings.take(raw)
        except ValueError as exc:
            outcomes.append(('refused', str(exc)))
            continue
        outcomes.append(('opened', bytes(view), view.readonly, hold.generation, hold.segment))
        holds.append((view, hold))
    return outcomes, holds


def _native_open_scenario(ends):
    """Good and bad descriptors of two segments, through every state the open checks."""
    pin, good = ends.publish(b'alpha' * 20)
    other_pin, other = ends.publish(b'beta' * 30)
    forged = [good._replace(**change) for change in (
        {'generation': good.generation + 1}, {'offset': 5}, {'offset': 5, 'size': good.size - 5},
        {'size': good.size - 1}, {'size': 1 << 30}, {'offset': 1 << 41}, {'pid': good.pid + 1},
        {'segment_id': good.segment_id + 100}, {'nonce': good.nonce ^ 1},
        {'generation': 0}, {'pid': 0})]
    packed = codec.pack(good)
    raws = [packed, packed, memoryview(packed), bytearray(packed), codec.pack(other)]
    raws += [codec.pack(d) for d in forged]
    raws += [b'XXXX' + packed[4:], packed[:4] + b'\x09' + packed[5:],
             packed[:6] + b'\x01' + packed[7:], packed[:24] + b'\x01' + packed[25:],
             packed[:-1], packed + b'\x00', b'', 12345, 'text']
    first, holds = _take_all(ends, raws)
    refs = sorted(m.refs for m in ends.mappings.by_key.values())
    del holds
    gc.collect()
    ends.links.drain(ends.links.get(ends.token))
    taken = (pin.slot.taken.get(ends.token), other_pin.slot.taken.get(ends.token))
    # its publisher holds the slot (renewing it): a take is refused as stale
    assert memory.try_lock(pin.slot.segment.fd, exclusive=True)
    held_out, _ = _take_all(ends, [packed])
    memory.unlock(pin.slot.segment.fd)
    # a reused slot, then a retired one
    assert ends.slots.renew(pin.slot, 10, gone=set())
    pin.follow_slot()
    reused, holds = _take_all(ends, [packed, codec.pack(good._replace(
        generation=pin.generation, size=10))])
    del holds
    gc.collect()
    ends.slots.remove(other_pin.slot)
    ends.mappings.receive()
    retired, _ = _take_all(ends, [codec.pack(other)])
    counters = ends.subscriber.counters.as_dict()
    return first, refs, taken, held_out, reused, retired, counters


def test_the_native_open_gives_what_the_python_open_gives():
    """The same descriptors, good and bad, through every state the open checks (mapped or not,
    current or stale, the range recorded or not, held by its publisher, retired), taken with
    the native open and with the Python open alone, each in a pair of ends of its own: the same
    views and errors, holds, acknowledgments and counters."""
    results = []
    for native in (True, False):
        made = Ends()
        try:
            if not native:
                made.mappings._open_mapped = lambda *args: None
            results.append(_native_open_scenario(made))
        finally:
            made.close()
    assert results[0] == results[1]
    first = results[0][0]
    assert [kind for kind, *_ in first[:5]] == ['opened'] * 5
    assert sum(kind == 'refused' for kind, *_ in first) == len(first) - 5


def test_a_mapped_current_segment_opens_natively(ends):
    """Only a take the native open cannot make goes through the Python open (the first of a
    segment not received yet, anything refused)."""
    pin, desc = ends.publish(b'n' * 64)
    opened_in_python = []
    python_open = ends.mappings.open

    def counting_open(d):
        opened_in_python.append(d)
        return python_open(d)
    ends.mappings.open = counting_open
    ends.mappings.last_sweep = 0.0  # the first take sweeps: the Python open receives it
    holds = [ends.mappings.take(codec.pack(desc)) for _ in range(3)]
    assert len(opened_in_python) == 1 and [bytes(v) for v, _ in holds] == [b'n' * 64] * 3
    with pytest.raises(ValueError, match='stale'):
        ends.mappings.take(codec.pack(desc._replace(generation=desc.generation + 1)))
    assert len(opened_in_python) == 2
