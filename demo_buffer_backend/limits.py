"""Every limit and every timing of the demo backend, in one place.

The pool limits are configurable (:func:`configure`, ``RBPY_DEMO_*`` environment variables or
``DemoBackend(...)`` keyword arguments) and live in :data:`current`; the other numbers are
module constants, read where they are used at the moment they are used (a test may set them).
"""
import os
from typing import Optional

from demo_buffer_backend.diagnostics import logger

# --- pool limits (configurable) --------------------------------------------------------------
DEFAULT_MAX_POOL_BYTES = 512 * 1024 * 1024
DEFAULT_MAX_SLOTS = 64
#: Seconds after which, at the limits, a slot whose descriptors were never all taken may be
#: reused (late takers then see a stale generation).
DEFAULT_RECLAIM_TIMEOUT = 5.0
ENV_MAX_POOL_BYTES = 'RBPY_DEMO_MAX_POOL_BYTES'
ENV_MAX_SLOTS = 'RBPY_DEMO_MAX_SLOTS'
ENV_RECLAIM_TIMEOUT = 'RBPY_DEMO_RECLAIM_TIMEOUT'
#: Per-endpoint share of in-flight descriptors; 0 (the default) means ``max(1, max_slots // 3)``.
ENV_MAX_INFLIGHT_PER_PEER = 'RBPY_DEMO_MAX_INFLIGHT_PER_PEER'

# --- subscriber side --------------------------------------------------------------------------
# What one connected process can make a subscriber process hold is bounded per process, so that
# no peer can use up what a genuine publisher needs (see :mod:`.inbox` and :mod:`.mappings`).
#: Received segments kept at most (beyond it, new handovers are refused; each costs two
#: descriptors, ours and the one CPython's mmap keeps).
MAX_MAPPINGS = 256
#: Received segments kept at most from one publisher process (a publisher's pool has at most
#: ``max_slots`` segments, 64 by default, plus retired ones until they are unused).
MAX_MAPPINGS_PER_PROCESS = 128
#: Connections kept at most from publisher processes that discovery shows as buffer-aware
#: publishers matched to this process (beyond it, new ones are refused).
MAX_INBOUND = 256
#: ... from one such process (a publisher process opens one; a new pool of it, one more).
MAX_CONNECTIONS_PER_PROCESS = 4
#: Connections kept unread, at most, from processes discovery has not shown as matched
#: publishers (yet: a publisher may connect before this process discovers it), in all and per
#: process; beyond it they are refused at once.
MAX_PENDING = 32
MAX_PENDING_PER_PROCESS = 2

# --- timings ----------------------------------------------------------------------------------
#: Seconds between drains of the listener when every descriptor names a known segment (and
#: the longest the inbox's thread sleeps).
SWEEP_INTERVAL = 1.0
#: Seconds a connection from a process not (yet) discovered as a matched publisher waits,
#: unread, before it is refused and closed.
PENDING_SECONDS = 3.0
#: Seconds a publisher waits for a subscriber process's verdict on a segment it hands over
#: before it describes a frame of it there (on time, a refusal costs no frame: CPU bytes go
#: instead); a late verdict makes it stop waiting on that link until the next one comes.
VERDICT_SECONDS = 0.05
#: Seconds a publisher sends CPU bytes to a subscriber process that refused its connection
#: before it connects again.
RELINK_SECONDS = 2.0
#: Seconds an unused segment of a publisher that hung up stays mapped: descriptors it sent
#: before it went may still be in our reader's history.
ORPHAN_SECONDS = 5.0
#: Pauses (seconds) of the bounded wait for the shared hold lock while a publisher holds it
#: exclusively, which it does for microseconds (about 0.08 s in all).
HOLD_RETRIES = (0.0002,) * 10 + (0.002,) * 40
#: Seconds between two warnings that a segment could not be created (the cause may last).
SEGMENT_WARNING_INTERVAL = 10.0


def _env_number(name: str, default, kind):
    raw = os.environ.get(name)
    if raw is None or not raw.strip():
        return default
    try:
        value = kind(raw)
        if value < 0:
            raise ValueError
        return value
    except ValueError:
        logger.warning(f'{name}={raw!r} is not a non-negative {kind.__name__}; using {default}')
        return default


class Limits:
    """The pool limits of this process (from the environment, then :func:`configure`)."""

    __slots__ = ('max_pool_bytes', 'max_slots', 'reclaim_timeout', 'max_inflight_per_peer')

    def __init__(self) -> None:
        self.max_pool_bytes = _env_number(ENV_MAX_POOL_BYTES, DEFAULT_MAX_POOL_BYTES, int)
        self.max_slots = _env_number(ENV_MAX_SLOTS, DEFAULT_MAX_SLOTS, int)
        self.reclaim_timeout = _env_number(ENV_RECLAIM_TIMEOUT, DEFAULT_RECLAIM_TIMEOUT, float)
        self.max_inflight_per_peer = _env_number(ENV_MAX_INFLIGHT_PER_PEER, 0, int)

    def endpoint_share(self, history_known: bool = False) -> int:
        """In-flight descriptors one subscriber endpoint may have (its share of the pool): a
        third of the slots, or half when its history is known (then nothing it can still take
        is given up, and a slow reader of a deep history holds what stock's reader would)."""
        return self.max_inflight_per_peer or max(1, self.max_slots // _divisor(history_known))

    def endpoint_share_bytes(self, history_known: bool = False) -> int:
        """Bytes of slots one subscriber endpoint may pin (the same part of the pool's bytes
        unless the share is set)."""
        return (self.max_pool_bytes if self.max_inflight_per_peer
                else max(1, self.max_pool_bytes // _divisor(history_known)))

    def as_dict(self) -> dict:
        """The configurable limits, as :func:`configure` takes them."""
        return {'max_pool_bytes': self.max_pool_bytes, 'max_slots': self.max_slots,
                'reclaim_timeout': self.reclaim_timeout,
                'max_inflight_per_peer': self.max_inflight_per_peer}


#: The limits in force in this process.
current = Limits()


def _divisor(history_known: bool) -> int:
    """One endpoint's share is this part of the pool (see :meth:`Limits.endpoint_share`)."""
    return 2 if history_known else 3


def configure(*, max_pool_bytes: Optional[int] = None, max_slots: Optional[int] = None,
              reclaim_timeout: Optional[float] = None,
              max_inflight_per_peer: Optional[int] = None) -> dict:
    """Set the process-wide pool limits (``None`` keeps a value); return the limits now in force.

    :param max_pool_bytes: Total data bytes of all slots of this process.
    :param max_slots: Number of slots (segments) of this process.
    :param reclaim_timeout: Seconds after which, at the limits, a slot whose descriptors were
        never all taken may be reused.
    :param max_inflight_per_peer: Descriptors one subscriber endpoint may have in flight before
        its oldest are given up; 0 means a third of ``max_slots`` (at least 1), half for an
        endpoint whose history is known.
    """
    for name, value in (('max_pool_bytes', max_pool_bytes), ('max_slots', max_slots),
                        ('reclaim_timeout', reclaim_timeout),
                        ('max_inflight_per_peer', max_inflight_per_peer)):
        if value is not None and (isinstance(value, bool) or not value >= 0):
            raise ValueError(f'{name} must be a non-negative number, got {value!r}')
    if max_inflight_per_peer is not None:
        current.max_inflight_per_peer = int(max_inflight_per_peer)
    if max_pool_bytes is not None:
        current.max_pool_bytes = int(max_pool_bytes)
    if max_slots is not None:
        current.max_slots = int(max_slots)
    if reclaim_timeout is not None:
        current.reclaim_timeout = float(reclaim_timeout)
    return current.as_dict()
