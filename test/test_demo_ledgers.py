"""Unit tests of the demo backend's per-endpoint ledgers (demo_buffer_backend/ledgers.py): what
an endpoint gives up by its KEEP_LAST window (once newer messages reached its reader), by taking
in order and, when its history is not bounded or not known, past its share."""
import os

import pytest

from demo_buffer_backend import limits, memory
from demo_buffer_backend.diagnostics import Counters
from demo_buffer_backend.ledgers import EndpointLedger, keep_last_share
from demo_buffer_backend.slots import Slot

TOKEN = f'{os.getpid()}_00000000000000aa'


@pytest.fixture
def new_slot():
    """Makes slots (segments of one page, generation 1); closes them afterwards."""
    saved = limits.current.as_dict()
    made = []

    def make():
        slot = Slot(len(made) + 1, memory.Segment(memory.PAGE_SIZE))
        slot.start_generation(1, 10)
        made.append(slot)
        return slot

    yield make
    for slot in made:
        slot.segment.close()
    limits.configure(**saved)


def _send(ledger, slot, counters):
    """What the pool does to describe one message for the ledger's endpoint."""
    ledger.seq += 1
    ledger.settle(counters)
    ledger.record(slot)


def test_keep_last_depth_gives_up_what_left_the_readers_history(new_slot):
    ledger, counters = EndpointLedger(TOKEN, depth=2), Counters()
    slots = [new_slot() for _ in range(4)]
    for slot in slots:
        _send(ledger, slot, counters)
    assert [e.slot for e in ledger.inflight] == slots[2:]
    assert counters.released_window == 2
    assert [s.released.get(TOKEN, 0) for s in slots] == [1, 1, 0, 0]


def test_the_window_waits_until_newer_messages_reached_the_reader(new_slot):
    """With ``delivered`` (EndpointInfo.delivered), N newer messages must have *reached* the
    reader: a stopped reader's history still holds what it had, so nothing is given up, and
    the endpoint is full at its KEEP_LAST share (2 N + 4); once everything sent reached it,
    what is more than N behind is given up."""
    reached = [False]
    ledger, counters = EndpointLedger(TOKEN, depth=1, delivered=lambda: reached[0]), Counters()
    slots = [new_slot() for _ in range(6)]
    for slot in slots:
        _send(ledger, slot, counters)
    assert [e.slot for e in ledger.inflight] == slots and counters.released_window == 0
    assert ledger.full() and keep_last_share(1) == 6
    reached[0] = True  # it resumed and received everything sent (messages 1 to 6)
    ledger.seq += 1  # describing message 7: 6 stays (its reader may hold it), 1 to 5 go
    ledger.settle(counters)
    assert [e.slot for e in ledger.inflight] == slots[5:] and counters.released_window == 5
    assert not ledger.full()


def test_a_newer_take_gives_up_the_older_ones_on_one_channel_only(new_slot):
    for per_channel, skipped in ((True, 2), (False, 0)):
        ledger, counters = EndpointLedger(TOKEN, per_channel=per_channel), Counters()
        slots = [new_slot() for _ in range(3)]
        for slot in slots:
            _send(ledger, slot, counters)
        slots[2].taken[TOKEN] = 1
        _send(ledger, new_slot(), counters)
        assert counters.released_skipped == skipped
        assert len(ledger.inflight) == (1 if per_channel else 3)


def test_past_its_share_an_endpoint_gives_up_its_oldest(new_slot):
    limits.configure(max_inflight_per_peer=2)
    ledger, counters = EndpointLedger(TOKEN), Counters()
    slots = [new_slot() for _ in range(5)]
    for slot in slots:
        _send(ledger, slot, counters)
    assert [e.slot for e in ledger.inflight] == slots[3:]
    assert counters.released_share == 3
    assert ledger.summary() == {'token': TOKEN, 'depth': None, 'messages': 5, 'in_flight': 2}


def test_an_endpoint_whose_history_is_known_keeps_it_and_is_full_at_its_share(new_slot):
    """What a subscription whose history is known (KEEP_LAST N, KEEP_ALL) can still take is
    never given up: at its share it is *full* (its next messages go as CPU bytes) until it
    takes; its KEEP_LAST window still gives up what its reader can no longer hold."""
    limits.configure(max_inflight_per_peer=2)
    for depth in (4, 0):
        ledger, counters = EndpointLedger(TOKEN, depth=depth), Counters()
        slots = [new_slot() for _ in range(2)]
        for slot in slots:
            _send(ledger, slot, counters)
        ledger.seq += 1
        ledger.settle(counters)
        assert ledger.full() and [e.slot for e in ledger.inflight] == slots
        assert counters.released_share == 0
        slots[0].taken[TOKEN] = 1  # it took one: room for the next
        ledger.settle(counters)
        assert not ledger.full()
    ledger, counters = EndpointLedger(TOKEN, depth=2), Counters()
    limits.configure(max_inflight_per_peer=10)
    slots = [new_slot() for _ in range(4)]
    for slot in slots:
        _send(ledger, slot, counters)
    assert [e.slot for e in ledger.inflight] == slots[2:] and counters.released_window == 2


def test_reused_slots_leave_the_ledger_and_are_not_given_up(new_slot):
    ledger, counters = EndpointLedger(TOKEN, depth=1), Counters()
    slot = new_slot()
    _send(ledger, slot, counters)
    slot.start_generation(2, 10)  # reclaimed meanwhile
    _send(ledger, new_slot(), counters)
    assert counters.released_window == 0 and not slot.released
    assert [e.generation for e in ledger.inflight] == [1]


def _settled_by_the_rules(entries, token, per_channel):
    """The rule settle() follows for what leaves, as one plain walk: reclaimed entries and
    those the endpoint took or gave up leave; on one channel, a take gives up every older entry
    still kept (counted while its slot is current). Returns (kept entries, given up)."""
    kept, skipped = [], 0
    for entry in entries:
        slot = entry.slot
        if slot.closed or slot.generation != entry.generation:
            continue
        if slot.taken.get(token, 0) + slot.released.get(token, 0) >= slot.sent.get(token, 0):
            if per_channel:
                for older in kept:
                    if not older.slot.closed and older.slot.generation == older.generation:
                        older.slot.released[token] = older.slot.released.get(token, 0) + 1
                        skipped += 1
                kept = []
            continue
        kept.append(entry)
    return kept, skipped


def test_settle_follows_the_rules_for_random_takes_reclaims_and_closes(new_slot):
    """What settle() keeps and gives up (no window, no share) is what the rule gives, for
    random takes, reused and removed slots, on one channel and on several."""
    import random
    rng = random.Random(30)
    limits.configure(max_inflight_per_peer=1000)
    slots = [new_slot() for _ in range(6)]

    def counts():
        return [(dict(s.sent), dict(s.taken), dict(s.released)) for s in slots]

    def restore(saved):
        for slot, (sent, taken, released) in zip(slots, saved):
            slot.sent, slot.taken, slot.released = dict(sent), dict(taken), dict(released)

    for trial in range(400):
        per_channel = trial % 2 == 0
        ledger, counters = EndpointLedger(TOKEN, depth=0, per_channel=per_channel), Counters()
        for slot in slots:
            slot.start_generation(slot.generation + 1, 10)
            slot.closed = False
        for _ in range(rng.randrange(1, 8)):
            _send(ledger, rng.choice(slots), counters)
        for slot in slots:  # the endpoint takes some, a few slots are reused or removed
            if slot.sent and rng.random() < 0.4:
                slot.taken[TOKEN] = slot.sent[TOKEN] - rng.randrange(2)
            if rng.random() < 0.1:
                slot.start_generation(slot.generation + 1, 10)
            elif rng.random() < 0.05:
                slot.closed = True
        before, saved = list(ledger.inflight), counts()
        kept, skipped = _settled_by_the_rules(before, TOKEN, per_channel)
        expected = counts()
        restore(saved)
        ledger.seq += 1
        counters = Counters()
        ledger.settle(counters)
        assert list(ledger.inflight) == kept, (trial, before)
        assert counters.released_skipped == skipped and counts() == expected, trial
    for slot in slots:
        slot.closed = False
