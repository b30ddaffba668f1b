"""Unit tests of the demo backend's per-endpoint ledgers (demo_buffer_backend/ledgers.py): what
an endpoint gives up by its KEEP_LAST window (once newer messages reached its reader), by taking
in order and, when its history is not bounded or not known, past its share."""
import collections
import os
import random

import pytest

from demo_buffer_backend import limits, memory
from demo_buffer_backend.diagnostics import Counters
from demo_buffer_backend.ledgers import EndpointLedger, InFlight, keep_last_share
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


class _RuleModel:
    """The ledger's rules as plain Python (how EndpointLedger ran them before they moved to
    native code): the model the native rules must follow, operation by operation."""

    def __init__(self, token, depth, per_channel, delivered):
        self.token, self.depth, self.per_channel = token, depth, per_channel
        self.delivered, self.seq, self.inflight = delivered, 0, collections.deque()

    def record(self, slot):
        slot.sent[self.token] = slot.sent.get(self.token, 0) + 1
        self.inflight.append(InFlight(slot, slot.generation, self.seq))

    def settle(self, counters):
        token, kept = self.token, []
        for entry in self.inflight:
            slot = entry.slot
            if slot.closed or slot.generation != entry.generation:
                continue
            if slot.taken.get(token, 0) + slot.released.get(token, 0) >= slot.sent.get(token, 0):
                if self.per_channel:
                    for skipped in kept:
                        counters.released_skipped += self._give_up(skipped)
                    kept = []
                continue
            kept.append(entry)
        inflight = collections.deque(kept)
        depth = self.depth
        if depth and inflight:
            behind = depth if self.delivered is None else depth + 1
            if self.seq - inflight[0].seq >= behind and (
                    self.delivered is None or self.delivered()):
                while inflight and self.seq - inflight[0].seq >= behind:
                    counters.released_window += self._give_up(inflight.popleft())
        if depth is None:
            while inflight and self._past_share(inflight, False, 0):
                counters.released_share += self._give_up(inflight.popleft())
        self.inflight = inflight

    def full(self):
        return (self.depth is not None and bool(self.inflight) and
                self._past_share(self.inflight, True, self.depth))

    def _give_up(self, entry):
        slot = entry.slot
        if slot.closed or slot.generation != entry.generation:
            return False
        slot.released[self.token] = slot.released.get(self.token, 0) + 1
        return True

    @staticmethod
    def _past_share(inflight, history_known, depth):
        count, nbytes = EndpointLedger._share(history_known, depth)
        return len(inflight) >= count or sum(e.slot.capacity for e in inflight) >= nbytes


def test_the_native_rules_are_the_model_rules(new_slot):
    """Random runs of what the pool does (describe: seq, settle, full, record) and of what
    happens meanwhile (takes, acks lost, slots reused or removed, readers that stop receiving,
    limits changed) on the native ledger and on the plain-Python model, each on its own slots:
    the same in-flight lists, counters, slot counts and verdicts after every step."""
    rng = random.Random(30)
    for trial in range(300):
        depth = rng.choice((None, 0, 1, 2, 5))
        per_channel = rng.random() < 0.7
        reached = [True]
        delivered = (lambda: reached[0]) if rng.random() < 0.5 else None
        limits.configure(max_inflight_per_peer=rng.choice((0, 2, 4)),
                         max_slots=rng.choice((6, 64)),
                         max_pool_bytes=rng.choice((8, 64)) * memory.PAGE_SIZE)
        ours = EndpointLedger(TOKEN, depth=depth, per_channel=per_channel, delivered=delivered)
        model = _RuleModel(TOKEN, depth, per_channel, delivered)
        pairs = [(new_slot(), new_slot()) for _ in range(5)]
        index = {id(slot): n for n, pair in enumerate(pairs) for slot in pair}
        ours_counters, model_counters = Counters(), Counters()
        for step in range(rng.randrange(1, 25)):
            action = rng.random()
            if action < 0.5:  # describe one message
                native_slot, model_slot = rng.choice(pairs)
                for ledger, counters in ((ours, ours_counters), (model, model_counters)):
                    ledger.seq += 1
                    ledger.settle(counters)
                full = ours.full()
                assert full == model.full(), (trial, step)
                if not full:
                    ours.record(native_slot)
                    model.record(model_slot)
            elif action < 0.7:  # the endpoint takes what it was sent of a slot
                native_slot, model_slot = rng.choice(pairs)
                for slot in (native_slot, model_slot):
                    slot.taken[TOKEN] = slot.sent.get(TOKEN, 0)
            elif action < 0.8:  # a slot is reused, or removed
                reused = rng.random() < 0.8
                for slot in rng.choice(pairs):
                    if reused:
                        slot.start_generation(slot.generation + 1, 10)
                    else:
                        slot.closed = True
            elif action < 0.9:  # its reader stops or resumes receiving
                reached[0] = not reached[0]
            else:  # the limits change
                limits.configure(max_inflight_per_peer=rng.choice((0, 1, 3)))
            assert [(index[id(e.slot)], e.generation, e.seq) for e in ours.inflight] == \
                [(index[id(e.slot)], e.generation, e.seq) for e in model.inflight], (trial, step)
            assert ours_counters == model_counters, (trial, step)
            assert [(a.sent, a.taken, a.released) for a, _ in pairs] == \
                [(b.sent, b.taken, b.released) for _, b in pairs], (trial, step)
