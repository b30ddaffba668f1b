"""Unit tests of the demo backend's publisher slots (demo_buffer_backend/slots.py), in one
process, without DDS: reuse, pins, what pins a generation, growth and removal at the limits."""
import gc
import os

import pytest

from demo_buffer_backend import limits, memory
from demo_buffer_backend.diagnostics import Diagnostics
from demo_buffer_backend.guard import Guard
from demo_buffer_backend.slots import Pin, Slots

PAGE = memory.PAGE_SIZE


@pytest.fixture
def slots():
    """Slots of their own (limits restored afterwards); ``retired`` lists the removed ids."""
    saved = limits.current.as_dict()
    retired = []
    own = Slots(os.getpid(), 7, Guard(), Diagnostics(), lambda slot: retired.append(slot.id))
    own.retired = retired
    yield own
    gc.collect()
    own.close()
    limits.configure(**saved)


def test_a_freed_slot_is_reused_with_the_next_generation(slots):
    view, pin = slots.allocate(100, gone=set())
    assert isinstance(pin, Pin) and len(view) == 100 and not view.readonly
    assert pin.segment == (os.getpid(), pin.slot.id) and pin.generation == 1
    slot = pin.slot
    assert slots.allocate(100, gone=set())[1].slot is not slot  # pinned: a second slot
    del view, pin
    gc.collect()  # the pin's release runs through the guard
    assert slot.pins == 0
    again = slots.allocate(200, gone=set())[1]
    assert again.slot is slot and again.generation == 2
    _, _, generation, _, size = memory.HEADER.unpack_from(slot.segment.map)
    assert generation == 2
    assert size == 200


def test_descriptors_pin_a_generation_until_taken_given_up_or_gone(slots):
    slot = slots.allocate(100, gone=set())[1].slot
    gc.collect()
    slot.sent.update(a=2, b=1)
    assert slot.pinning(gone=set()) == 3
    assert slots.acknowledge(slot.id, slot.generation, 'a')
    assert not slots.acknowledge(slot.id, slot.generation + 1, 'a')  # another generation
    slot.released['a'] = 1
    assert slot.pinning(gone=set()) == 1
    assert slot.pinning(gone={'b'}) == 0
    assert slots.allocate(100, gone=set())[1].slot is not slot  # b's descriptor pins it
    assert slots.allocate(100, gone={'b'})[1].slot is slot


def test_reclaim_timeout_frees_what_descriptors_still_pin(slots):
    limits.configure(max_slots=1, reclaim_timeout=0)
    first = slots.allocate(100, gone=set())[1].slot
    first.sent['a'] = 1
    gc.collect()
    assert slots.allocate(100, gone=set())[1].slot is first
    assert slots.counters.reclaimed == 1


def test_at_the_limits_free_slots_of_another_size_are_removed(slots):
    limits.configure(max_slots=1)
    small = slots.allocate(100, gone=set())[1].slot
    gc.collect()
    big = slots.allocate(4 * PAGE, gone=set())[1].slot
    assert big is not small and small.closed and slots.retired == [small.id]
    assert len(slots) == 1 and slots.bytes == 4 * PAGE
    assert slots.counters.segments_removed == 1


def test_fallbacks_are_counted_by_cause(slots):
    limits.configure(max_pool_bytes=PAGE, max_slots=1)
    assert slots.allocate(2 * PAGE, gone=set()) is None
    held = slots.allocate(PAGE, gone=set())
    assert slots.allocate(PAGE, gone=set()) is None
    counters = slots.counters
    assert (counters.fallbacks, counters.fallbacks_too_large, counters.fallbacks_held) == (2, 1, 1)
    assert slots.pinned() == 1
    del held


def test_a_removed_slot_is_retired_and_no_longer_current(slots):
    pin = slots.allocate(100, gone=set())[1]
    slots.remove(pin.slot)
    assert slots.retired == [pin.slot.id] and not pin.slot.current(pin.generation)
    assert slots.get(pin.slot.id) is None and slots.bytes == 0
