"""Per-endpoint ledgers: which descriptors a subscriber endpoint may still take (fairness).

What one subscriber does costs only that subscriber. Each subscriber endpoint (per local
publisher when ``EndpointInfo.local_gid`` names it) has an :class:`EndpointLedger` of its
descriptors in flight, in send order. A descriptor stops pinning its slot (:mod:`.slots`) when
the endpoint cannot take it any more or has used up its share, never by sending it CPU bytes:

- *KEEP_LAST depth N* (``EndpointInfo.history_depth``): N newer messages on the channel
  reached the endpoint's reader and pushed it out of its history (``released_window``). That
  they reached it, ``EndpointInfo.delivered`` tells (DDS acknowledged every sample the channel
  holds, and the channel holds at least N: the caller says False otherwise); without it, N
  newer messages sent count. A reader whose process is stopped receives nothing: what its
  history held stays takeable, and stays reserved until its share is reached;
- *in order*: the endpoint took a newer one, so it dropped this one (``released_skipped``);
- *share*: the endpoint has ``endpoint_share`` descriptors (or that part of the pool's bytes:
  a third, half when its history is known, and for KEEP_LAST N at most 2 N + 4 descriptors)
  in flight. When its history is known (it advertises KEEP_LAST N or KEEP_ALL), nothing it
  can still take is given up: it gets its next messages as CPU bytes until it takes some (or,
  for KEEP_LAST, receives newer ones: :meth:`EndpointLedger.full`; ``cpu_past_share``), so a
  slow subscriber gets every frame its reader holds, as from stock rclpy, and a stopped one
  pins no more of the pool than its share. When its history is not known, its
  oldest are given up (``released_share``): it keeps getting descriptors, and a given-up one
  it takes later is refused as stale only if its slot was reused meanwhile;
- *gone*: the endpoint's process hung up its link: nothing it was sent pins anything (the slots
  leave such tokens out, see :meth:`.slots.Slot.pinning`).

A ledger counts per process token in its slots (``sent``, ``taken``, ``released``): several
endpoints of one process share those counts, which is why the in-order rule applies only to a
ledger of one channel (``per_channel``).
"""
import collections
from typing import Callable, Deque, Dict, List, NamedTuple, Optional, Tuple

from demo_buffer_backend import limits
from demo_buffer_backend.diagnostics import Counters
from demo_buffer_backend.slots import Slot


class InFlight(NamedTuple):
    """One descriptor an endpoint has not been seen to take."""

    slot: Slot
    generation: int
    seq: int  #: the endpoint's message number it was sent with


class EndpointLedger:
    """The descriptors in flight to one subscriber endpoint (see the module docstring).

    ``token``: the endpoint's process. ``depth``: its KEEP_LAST history depth, 0 for KEEP_ALL,
    None when unknown (or when the ledger may see the messages of several channels: not
    ``per_channel``). ``delivered``: whether its reader received everything sent so far
    (``EndpointInfo.delivered``; None: not known, what was sent counts).
    """

    __slots__ = ('token', 'depth', 'per_channel', 'delivered', 'seq', 'inflight')

    def __init__(self, token: str, depth: Optional[int] = None, per_channel: bool = True,
                 delivered: Optional[Callable[[], bool]] = None) -> None:
        self.token = token
        self.depth = depth
        self.per_channel = per_channel
        self.delivered = delivered
        self.seq = 0  #: messages described for the endpoint
        self.inflight: Deque[InFlight] = collections.deque()

    def summary(self) -> dict:
        return {'token': self.token, 'depth': self.depth, 'messages': self.seq,
                'in_flight': len(self.inflight)}

    def record(self, slot: Slot) -> None:
        """One descriptor of the slot's generation is sent with the current message number."""
        slot.sent[self.token] = slot.sent.get(self.token, 0) + 1
        self.inflight.append(InFlight(slot, slot.generation, self.seq))

    def settle(self, counters: Counters) -> None:
        """Bring the in-flight list up to date before message ``seq`` is sent: drop what the
        endpoint took or what was reclaimed, give up what it can no longer take and, when its
        history is not known, what exceeds its share."""
        if not self.inflight:  # nothing to settle (an endpoint that keeps up, between frames)
            return
        token = self.token
        kept: List[InFlight] = []
        for entry in self.inflight:
            slot = entry.slot
            # reclaimed or removed: nothing left to protect (slot.current(), inlined: this runs
            # for every entry on every message)
            if slot.closed or slot.generation != entry.generation:
                continue
            if slot.taken.get(token, 0) + slot.released.get(token, 0) >= slot.sent.get(token, 0):
                if self.per_channel:  # taken in order: what it had not taken, it dropped
                    for skipped in kept:
                        counters.released_skipped += self._give_up(skipped)
                    kept = []
                continue
            kept.append(entry)
        inflight = collections.deque(kept)
        depth = self.depth
        if depth and inflight:  # seq is the message being described now
            # what was sent counts (N newer), or, with ``delivered``, what reached the reader:
            # everything up to seq - 1, so more than N newer must have been sent
            behind = depth if self.delivered is None else depth + 1
            if self.seq - inflight[0].seq >= behind and (
                    self.delivered is None or self.delivered()):
                while inflight and self.seq - inflight[0].seq >= behind:
                    counters.released_window += self._give_up(inflight.popleft())
        if depth is None:  # it may no longer hold its oldest: give them up
            while inflight and _past_share(inflight, history_known=False):
                counters.released_share += self._give_up(inflight.popleft())
        self.inflight = inflight

    def full(self) -> bool:
        """The endpoint, whose history is known, has its share of the pool in flight, all of it
        still takeable: its next message goes as CPU bytes (after :meth:`settle`)."""
        return (self.depth is not None and bool(self.inflight) and
                _past_share(self.inflight, history_known=True, depth=self.depth))

    def _give_up(self, entry: InFlight) -> bool:
        """Stop ``entry`` pinning its slot; False when the slot moved on meanwhile."""
        slot = entry.slot
        if slot.closed or slot.generation != entry.generation:
            return False
        slot.released[self.token] = slot.released.get(self.token, 0) + 1
        return True


def _past_share(inflight: Deque[InFlight], history_known: bool, depth: int = 0) -> bool:
    """Whether ``inflight`` holds an endpoint's share of the pool (descriptors or bytes); for
    a KEEP_LAST ``depth``, at most :func:`keep_last_share` descriptors."""
    share = limits.current
    key = (history_known, depth, share.max_inflight_per_peer, share.max_slots,
           share.max_pool_bytes)
    # the share looked up once per value of what it depends on: full() asks on every descriptor
    count, nbytes = _SHARES.get(key) or _share(key)
    if len(inflight) >= count:
        return True
    pinned = 0  # (a loop, not sum() of a generator: one frame less on every descriptor)
    for entry in inflight:
        pinned += entry.slot.capacity
    return pinned >= nbytes


#: (history known, depth, the limits it reads) -> (descriptors, bytes): an endpoint's share
_SHARES: Dict[Tuple[bool, int, int, int, int], Tuple[int, int]] = {}


def _share(key: Tuple[bool, int, int, int, int]) -> Tuple[int, int]:
    history_known, depth = key[:2]
    share = limits.current
    count = share.endpoint_share(history_known)
    if depth:
        count = min(count, keep_last_share(depth))
    found = _SHARES[key] = (count, share.endpoint_share_bytes(history_known))
    return found


def keep_last_share(depth: int) -> int:
    """Descriptors a KEEP_LAST ``depth`` endpoint may have in flight at most: its history, and
    as many again plus a few for what is on its way and not yet acknowledged. A reader that
    keeps receiving frees them as it goes (the window); a stopped one pins no more than this
    (its later messages go as CPU bytes)."""
    return 2 * depth + 4
