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
from typing import Callable, List, NamedTuple, Optional, Tuple

from rosidl_buffer_py._native import LedgerCore

from demo_buffer_backend import limits
from demo_buffer_backend.slots import Slot


class InFlight(NamedTuple):
    """One descriptor an endpoint has not been seen to take."""

    slot: Slot
    generation: int
    seq: int  #: the endpoint's message number it was sent with


class EndpointLedger(LedgerCore):
    """The descriptors in flight to one subscriber endpoint (see the module docstring).

    ``token``: the endpoint's process. ``depth``: its KEEP_LAST history depth, 0 for KEEP_ALL,
    None when unknown (or when the ledger may see the messages of several channels: not
    ``per_channel``). ``delivered``: whether its reader received everything sent so far
    (``EndpointInfo.delivered``; None: not known, what was sent counts).

    Its rules run natively (``rosidl_buffer_py._native.LedgerCore``: they run for every
    descriptor, where each Python line costs ten to thirty times its warm cost):

    - ``record(slot)``: one descriptor of the slot's generation is sent with the current
      message number ``seq``;
    - ``settle(counters)``: bring the in-flight list up to date before message ``seq`` is sent:
      drop what the endpoint took or what was reclaimed, give up what it can no longer take
      and, when its history is not known, what exceeds its share;
    - ``full()``: the endpoint, whose history is known, has its share of the pool in flight,
      all of it still takeable: its next message goes as CPU bytes (after ``settle``).

    Its share is :meth:`_share`'s, asked again whenever the limits it depends on change.
    """

    __slots__ = ()

    def __init__(self, token: str, depth: Optional[int] = None, per_channel: bool = True,
                 delivered: Optional[Callable[[], bool]] = None) -> None:
        super().__init__(token, depth, per_channel, delivered, limits.current)

    @property
    def inflight(self) -> List[InFlight]:
        """The descriptors in flight, oldest first."""
        return [InFlight(*entry) for entry in self._entries()]

    def summary(self) -> dict:
        return {'token': self.token, 'depth': self.depth, 'messages': self.seq,
                'in_flight': self.in_flight}

    @staticmethod
    def _share(history_known: bool, depth: int) -> Tuple[int, int]:
        """(descriptors, bytes) an endpoint may have in flight: its share of the pool (see
        :class:`~.limits.Limits`), and for a KEEP_LAST ``depth`` at most
        :func:`keep_last_share` descriptors."""
        share = limits.current
        count = share.endpoint_share(history_known)
        if depth:
            count = min(count, keep_last_share(depth))
        return count, share.endpoint_share_bytes(history_known)


def keep_last_share(depth: int) -> int:
    """Descriptors a KEEP_LAST ``depth`` endpoint may have in flight at most: its history, and
    as many again plus a few for what is on its way and not yet acknowledged. A reader that
    keeps receiving frees them as it goes (the window); a stopped one pins no more than this
    (its later messages go as CPU bytes)."""
    return 2 * depth + 4
