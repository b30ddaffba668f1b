"""The process-wide state of the demo backend: the publisher's slot pool, the subscriber's mapping
cache, the limits, the counters and the lifecycle (scavenging, atexit, fork).

Publisher side: a pool of slots, one shm segment each, reused while they are free. A slot is free
when no DemoBuffer of this process pins it, every descriptor created for its current generation
has been taken (``taken >= sent`` in the header) and no process holds views of it (this process
gets the exclusive OFD lock on its hold byte); reuse bumps the generation under that lock.
Descriptors addressed to a subscriber process that died do not count: the pool records, per slot,
how many descriptors it created for each recipient (by presence token, :mod:`.presence`),
subscribers record their takes per token in the segment's takers table, and a slot whose untaken
descriptors were all addressed to dead processes is free (``taken - taken_by_dead >= sent -
sent_to_dead``). Liveness is an ``F_OFD_GETLK`` on the recipient's presence file, cached for
``LIVENESS_TTL`` seconds. When no slot is free the pool grows up to the limits; at the limits,
free slots of the wrong size are evicted, then slots whose last descriptor was created more than
``reclaim_timeout`` seconds ago and never taken are reclaimed (their late takers see a stale
generation), and only then does the allocation fall back to private memory (the message then
travels as CPU bytes).

Fairness: what one subscriber does costs only that subscriber. Each compatible peer endpoint has
a :class:`PeerLedger`, its descriptors in flight (sent, not seen taken), in send order:

- *KEEP_LAST depth N* (``EndpointInfo.history_depth``): a descriptor followed by N newer
  messages to the same peer has left its reader history and can no longer be taken by it, so it
  stops pinning its slot (``released_window``);
- *share*: a peer pins at most ``max_inflight_per_peer`` slots (default a third of
  ``max_slots`` and of ``max_pool_bytes``; also the bound for KEEP_ALL and unknown depths).
  Past its share that peer alone gets CPU bytes (``over_share``): its descriptors in flight
  stay valid, so a slow subscriber loses nothing that a stock one would get, and the others
  keep the rest of the pool;
- *in order*: a peer takes its channel in order, so descriptors older than one it took were
  dropped by it (best effort, or rejected) and stop pinning (``released_skipped``; only when
  the ledger sees one channel, see below);
- *not taking*: a peer that has had descriptors waiting for ``IDLE_SECONDS`` without taking any
  (stalled, stopped, or never taking) is served CPU bytes, plus, within its share, one probe
  descriptor every ``PROBE_SECONDS``; its first observed take makes it a normal peer again
  (``peers_idle``). What it has in flight stays valid for when it resumes;
- *dead or foreign*: a peer whose presence file is gone, or is not one this user created
  (another uid that claims our shm domain cannot open the segments), gets CPU bytes and pins
  nothing (``cpu_dead_peer``).

Whatever a peer still pins is bounded by its share and becomes reclaimable under pressure after
``reclaim_timeout``. Ledgers are per (peer, local publisher) when ``EndpointInfo.local_gid``
names the publisher: the KEEP_LAST window and the in-order rule need the messages of one
channel, so they are applied only then. Takes are recorded per subscriber *process* (the takers table), so the
subscriptions of one process are told apart only by their own ledgers: a descriptor counts as
taken when that process took as many of the slot's descriptors as it was sent. A process whose
subscriptions take at different paces is paced by its slowest, within each one's share.

The publisher hears of all this only as ``None`` from ``create_descriptor_with_endpoint``: that
peer gets the message as CPU bytes. Counters of each rule are in :func:`stats`, per-peer state in
``DemoBackend.peer_ledgers()``.

Housekeeping: every process that uses the backend runs one daemon thread (no Python callbacks
into rclpy, one ``listdir`` of /dev/shm and a few syscalls per file every
``HOUSEKEEPING_SECONDS``) that removes segments and presence files of dead owners and closes
unreferenced mappings of removed segments, so a SIGKILLed publisher's memory is returned within
seconds while any user of the backend lives. Unlinking never unmaps: views a live process holds
stay valid.

Subscriber side: segments are mapped once and cached by name. Per segment and process, the
number of live views is counted; the shared OFD lock on the hold byte is taken on 0 -> 1 and
dropped on 1 -> 0. A segment is mapped only if it looks exactly as the backend creates them
(regular file opened without following symlinks, our uid, mode 0600, header with our magic,
layout and the owner pid of its name). A descriptor is accepted only after that lock is held and
its generation and size match the header; then ``taken`` is incremented under the mutex byte,
waited for at most ``MUTEX_WAIT_SECONDS`` (past that the view is delivered anyway, the take
unrecorded: ``take_unrecorded``; the publisher then sees it as untaken, which costs only this
subscriber).

All of it is guarded by one lock. Releases triggered by garbage collection (a Buffer and its views
going away) never wait for that lock: they are queued and run by whoever holds or next takes it.
"""
import atexit
import collections
import errno
import os
import threading
import time
from typing import Deque, Dict, List, NamedTuple, Optional, Tuple

from rclpy.logging import get_logger

from demo_buffer_backend import descriptor as desc_codec
from demo_buffer_backend import locks, presence, shm

#: Defaults of the pool limits; each can be set with its environment variable, with
#: :func:`configure` or with ``DemoBackend(...)`` keyword arguments.
DEFAULT_MAX_POOL_BYTES = 512 * 1024 * 1024
DEFAULT_MAX_SLOTS = 64
DEFAULT_RECLAIM_TIMEOUT = 5.0
ENV_MAX_POOL_BYTES = 'RBPY_DEMO_MAX_POOL_BYTES'
ENV_MAX_SLOTS = 'RBPY_DEMO_MAX_SLOTS'
ENV_RECLAIM_TIMEOUT = 'RBPY_DEMO_RECLAIM_TIMEOUT'
#: Per-peer share of in-flight descriptors; 0 (the default) means ``max(1, max_slots // 4)``.
ENV_MAX_INFLIGHT_PER_PEER = 'RBPY_DEMO_MAX_INFLIGHT_PER_PEER'

#: A peer with descriptors waiting this long and no take observed meanwhile is "not taking".
IDLE_SECONDS = 2.0
#: A peer that is not taking gets one descriptor (a probe) at most this often.
PROBE_SECONDS = 1.0
#: Period of the housekeeping thread (reclaiming dead owners' segments and presence files).
HOUSEKEEPING_SECONDS = 2.0
#: Longest wait for a segment's mutex byte (its holders keep it for a few instructions).
MUTEX_WAIT_SECONDS = 0.02

#: Subscriber-side mappings kept open at most (unreferenced ones beyond this are closed).
MAX_MAPPINGS = 256
#: Seconds between sweeps of the mapping cache (closing mappings of removed segments).
SWEEP_INTERVAL = 1.0
#: Seconds a recipient's liveness answer is trusted before its presence lock is tested again.
LIVENESS_TTL = 0.1
#: Bounded wait for the shared hold lock while a publisher briefly holds it exclusively.
_HOLD_RETRIES = (0.0002,) * 10 + (0.002,) * 40

_logger = get_logger('demo_buffer_backend')


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
        _logger.warning(f'{name}={raw!r} is not a non-negative {kind.__name__}; using {default}')
        return default


class _Limits:
    def __init__(self) -> None:
        self.max_pool_bytes = _env_number(ENV_MAX_POOL_BYTES, DEFAULT_MAX_POOL_BYTES, int)
        self.max_slots = _env_number(ENV_MAX_SLOTS, DEFAULT_MAX_SLOTS, int)
        self.reclaim_timeout = _env_number(ENV_RECLAIM_TIMEOUT, DEFAULT_RECLAIM_TIMEOUT, float)
        self.max_inflight_per_peer = _env_number(ENV_MAX_INFLIGHT_PER_PEER, 0, int)

    def peer_share(self) -> int:
        """In-flight descriptors one peer may have (its share of the pool)."""
        return self.max_inflight_per_peer or max(1, self.max_slots // 3)

    def peer_share_bytes(self) -> int:
        """Bytes of slots one peer may pin (a third of the pool unless the share is set)."""
        return (self.max_pool_bytes if self.max_inflight_per_peer
                else max(1, self.max_pool_bytes // 3))

    def as_dict(self) -> dict:
        return {'max_pool_bytes': self.max_pool_bytes, 'max_slots': self.max_slots,
                'reclaim_timeout': self.reclaim_timeout,
                'max_inflight_per_peer': self.max_inflight_per_peer}


_limits = _Limits()


def configure(*, max_pool_bytes: Optional[int] = None, max_slots: Optional[int] = None,
              reclaim_timeout: Optional[float] = None,
              max_inflight_per_peer: Optional[int] = None) -> dict:
    """Set the process-wide pool limits (``None`` keeps a value); return the limits now in force.

    :param max_pool_bytes: Total data bytes of all slots of this process.
    :param max_slots: Number of slots (segments) of this process.
    :param reclaim_timeout: Seconds after which, at the limits, a slot whose descriptors were never
        all taken (a subscriber that dropped or never read the message) may be reused.
    :param max_inflight_per_peer: Descriptors one peer may have in flight (sent, not taken)
        before it gets CPU bytes; 0 means a third of ``max_slots`` (at least 1).
    """
    for name, value in (('max_pool_bytes', max_pool_bytes), ('max_slots', max_slots),
                        ('reclaim_timeout', reclaim_timeout),
                        ('max_inflight_per_peer', max_inflight_per_peer)):
        if value is not None and (isinstance(value, bool) or not value >= 0):
            raise ValueError(f'{name} must be a non-negative number, got {value!r}')
    if max_inflight_per_peer is not None:
        _limits.max_inflight_per_peer = int(max_inflight_per_peer)
    if max_pool_bytes is not None:
        _limits.max_pool_bytes = int(max_pool_bytes)
    if max_slots is not None:
        _limits.max_slots = int(max_slots)
    if reclaim_timeout is not None:
        _limits.reclaim_timeout = float(reclaim_timeout)
    return _limits.as_dict()


class _Slot:
    """A publisher-side slot: one segment this process created and owns."""

    __slots__ = ('name', 'fd', 'header', 'data', 'view', 'capacity', 'pins', 'generation',
                 'last_used', 'closed', 'recipients', 'released')

    def __init__(self, name, fd, header, data, capacity):
        self.name = name
        self.fd = fd
        self.header = header
        self.data = data
        self.view = memoryview(data)
        self.capacity = capacity
        self.pins = 0
        self.generation = 0
        self.last_used = 0
        self.closed = False
        #: Descriptors of the current generation per recipient token (None: a peer without one).
        self.recipients: Dict[Optional[str], int] = {}
        #: Of those, descriptors that no longer protect the slot (see PeerLedger), per token.
        self.released: Dict[Optional[str], int] = {}


class Pin:
    """Keepalive of a publisher-side DemoBuffer: the slot cannot be reused while it lives."""

    __slots__ = ('state', 'slot', 'generation', 'size', 'packed')

    def __init__(self, state, slot, size):
        self.state = state
        self.slot = slot
        self.generation = slot.generation
        self.size = size
        self.packed = None  # the descriptor, packed on first use

    @property
    def name(self) -> str:
        return self.slot.name

    def __del__(self):
        try:
            self.state._defer(self.state._unpin, self.slot)
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


class _Mapping:
    """A subscriber-side mapping of a segment (of any process, this one included)."""

    __slots__ = ('name', 'fd', 'header', 'data', 'view', 'capacity', 'refs', 'closed')

    def __init__(self, name, fd, header, data, capacity):
        self.name = name
        self.fd = fd
        self.header = header
        self.data = data
        self.view = memoryview(data).toreadonly()
        self.capacity = capacity
        self.refs = 0
        self.closed = False


class Hold:
    """Keepalive of a subscriber-side DemoBuffer: this process's hold on the slot's bytes."""

    __slots__ = ('state', 'mapping', 'generation')

    def __init__(self, state, mapping, generation):
        self.state = state
        self.mapping = mapping
        self.generation = generation

    @property
    def name(self) -> str:
        return self.mapping.name

    def __del__(self):
        try:
            self.state._defer(self.state._release, self.mapping)
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


class _InFlight(NamedTuple):
    """One descriptor a peer has not been seen to take."""

    slot: '_Slot'
    generation: int
    seq: int  #: the peer's message number it was sent with
    sent_ns: int


class PeerLedger:
    """Per-peer accounting of descriptors in flight (see the module docstring, "Fairness").

    One per compatible peer endpoint, owned by the backend, used under the state's lock.
    ``depth``: the peer's KEEP_LAST history depth, 0 for KEEP_ALL or unknown (or when the
    ledger may see the messages of several channels: no ``local_gid``).
    """

    __slots__ = ('token', 'depth', 'per_channel', 'seq', 'inflight', 'watch',
                 'pending_since_ns', 'idle', 'probe_ns')

    def __init__(self, token: Optional[str], depth: int = 0, per_channel: bool = True) -> None:
        self.token = token
        self.depth = depth
        #: Whether one channel's messages alone go through this ledger (the publisher is
        #: named): only then are takes in order, so that what precedes a take was dropped.
        self.per_channel = per_channel
        self.seq = 0  #: messages sent to the peer through the backend (descriptor or CPU)
        self.inflight: Deque[_InFlight] = collections.deque()
        #: Descriptors released unseen (by the window): still watched for takes, which show
        #: that the peer is taking.
        self.watch: Deque[_InFlight] = collections.deque(maxlen=8)
        self.pending_since_ns: Optional[int] = None  #: oldest descriptor sent since a take
        self.idle = False
        self.probe_ns = 0

    def summary(self) -> dict:
        return {'token': self.token, 'depth': self.depth, 'messages': self.seq,
                'in_flight': len(self.inflight), 'not_taking': self.idle}


_COUNTERS = ('segments_created', 'segments_removed', 'fallbacks', 'descriptors_created',
             'descriptors_declined', 'taken', 'rejected', 'stale', 'reclaimed', 'scavenged',
             'mappings_opened', 'mappings_closed', 'released_dead_recipients',
             'liveness_checks', 'released_window', 'released_skipped', 'released_idle',
             'over_share', 'cpu_not_taking', 'cpu_dead_peer', 'probes', 'peers_idle',
             'take_unrecorded', 'housekeeping_runs', 'untrusted_segments', 'fallbacks_held',
             'fallbacks_too_large', 'fallbacks_enospc', 'fallbacks_shm_error')


class _Locked:
    __slots__ = ('state',)

    def __init__(self, state):
        self.state = state

    def __enter__(self):
        self.state.lock.acquire()

    def __exit__(self, *exc):
        self.state.lock.release()
        self.state._drain()


class State:
    """Everything the demo backend holds in one process."""

    def __init__(self) -> None:
        self.pid = os.getpid()
        self.lock = threading.Lock()
        self.locked = _Locked(self)
        self.pending: List[tuple] = []
        self.slots: Dict[str, _Slot] = {}
        self.pool_bytes = 0
        self.mappings: Dict[str, _Mapping] = {}
        self.counters = dict.fromkeys(_COUNTERS, 0)
        self.closed = False
        self.started = False
        self.last_sweep = 0.0
        self.warned_fallback: set = set()
        self.grow_failure: Optional[str] = None
        self.presence: Optional[presence.Presence] = None
        #: recipient token -> (alive, monotonic ns until which the answer holds)
        self.liveness: Dict[str, Tuple[bool, int]] = {}
        #: the presence files of live recipients, kept open (a re-test is one fcntl)
        self.presences = presence.Watch()
        self.stop_housekeeping = threading.Event()

    # --- deferred releases -----------------------------------------------------------------
    def _defer(self, func, obj) -> None:
        self.pending.append((func, obj))
        self._drain()

    def _drain(self) -> None:
        # Whoever appends tries the lock after appending; whoever holds the lock drains after
        # releasing it: one of the two always sees every entry.
        while self.pending:
            if not self.lock.acquire(blocking=False):
                return
            try:
                while self.pending:
                    func, obj = self.pending.pop()
                    try:
                        func(obj)
                    except Exception as exc:  # pragma: no cover - never lose the others
                        _logger.error(f'demo backend release failed: {exc!r}')
            finally:
                self.lock.release()

    def _unpin(self, slot: _Slot) -> None:
        slot.pins -= 1

    def _release(self, mapping: _Mapping) -> None:
        mapping.refs -= 1
        if mapping.refs == 0 and not mapping.closed:
            locks.unlock(mapping.fd, shm.HOLD_BYTE)

    # --- lifecycle ---------------------------------------------------------------------------
    def _start(self) -> None:
        if self.started:
            return
        self.started = True
        self.counters['scavenged'] += shm.scavenge(skip=self.slots)
        threading.Thread(target=self._housekeeping, name='demo_buffer_backend housekeeping',
                         daemon=True).start()
        if _token_advertised():
            self._ensure_presence()  # back after a shutdown: the advertised token stays valid

    def _housekeeping(self) -> None:
        """The housekeeping thread: reclaim dead owners' files every HOUSEKEEPING_SECONDS,
        whether or not messages arrive (a subscriber that only maps a dead publisher's segments
        must not keep them in /dev/shm). Ends with the state (shutdown, fork)."""
        while not self.stop_housekeeping.wait(HOUSEKEEPING_SECONDS):
            if self.closed or self.pid != os.getpid():
                return
            try:
                self.housekeep()
            except Exception as exc:  # pragma: no cover - never let the thread die silently
                _logger.error(f'demo backend housekeeping failed: {exc!r}',
                              throttle_duration_sec=60.0)

    def housekeep(self) -> None:
        """Remove segments and presence files of dead owners, close unreferenced mappings of
        removed segments. The directory scan runs without the state's lock (our own files are
        skipped, and files we create meanwhile carry our owner lock)."""
        with self.locked:
            if self.closed:
                return
            skip = set(self.slots)
            self.counters['housekeeping_runs'] += 1
        removed = shm.scavenge(skip=skip)
        with self.locked:
            self.counters['scavenged'] += removed
            if not self.closed:
                self._sweep()

    def _ensure_presence(self) -> Optional[str]:
        if self.presence is None:
            try:
                self.presence = presence.Presence(own_token())
            except OSError as exc:
                _logger.warning(f'cannot create the demo presence file: {exc}; peers will keep '
                                'slots for this process until their reclaim timeout',
                                throttle_duration_sec=10.0)
                return None
        return self.presence.token

    def presence_token(self) -> Optional[str]:
        """This process's token, its presence file created (and locked) if need be; None when
        the file cannot be created (the metadata then carries no token)."""
        global _advertised_pid
        with self.locked:
            if self.closed:
                return None
            self._start()
            token = self._ensure_presence()
            if token is not None:
                _advertised_pid = self.pid
            return token

    def start(self) -> None:
        with self.locked:
            self._start()

    def shutdown(self) -> None:
        """Close every mapping (removing segments whose owner is gone) and remove every segment
        this process created. Views still alive keep their memory but lose their protection."""
        self.stop_housekeeping.set()
        with self.locked:
            self.closed = True
            for mapping in list(self.mappings.values()):
                try:
                    if not shm.owner_alive(mapping.fd):
                        self.counters['scavenged'] += shm.unlink(mapping.name)
                except OSError:
                    pass
                self._close_mapping(mapping)
            for slot in list(self.slots.values()):
                self._remove_slot(slot)
            if self.presence is not None:
                self.presence.close(remove=True)
                self.presence = None
            self.presences.close()

    def forget_after_fork(self) -> None:
        """In a forked child: drop the parent's resources without touching its segments."""
        self.closed = True
        self.stop_housekeeping = threading.Event()  # the parent's thread is not in the child
        for item in list(self.slots.values()) + list(self.mappings.values()):
            item.closed = True
            try:
                os.close(item.fd)
            except OSError:
                pass
        self.slots = {}
        self.mappings = {}
        if self.presence is not None:  # the parent's: close our copy of the fd, keep the file
            self.presence.close(remove=False)
            self.presence = None
        self.presences.close()

    # --- publisher side ----------------------------------------------------------------------
    def allocate(self, nbytes: int) -> Optional[Tuple[memoryview, Pin]]:
        """A writable view of ``nbytes`` in a slot and its pin, or ``None``: fall back."""
        with self.locked:
            if self.closed:
                return None
            self._start()
            capacity = shm.round_capacity(nbytes)
            self.grow_failure = None
            slot = (self._reuse(nbytes, stale_ok=False)
                    or self._grow(nbytes, capacity, stale_ok=False)
                    or self._reuse(nbytes, stale_ok=True)
                    or self._grow(nbytes, capacity, stale_ok=True))
            if slot is None:
                self.counters['fallbacks'] += 1
                cause = self.grow_failure or 'held'
                self.counters[f'fallbacks_{cause}'] += 1
                if cause not in self.warned_fallback:
                    self.warned_fallback.add(cause)
                    _logger.warning(
                        f'demo buffer pool: no shared memory for {nbytes} bytes '
                        f'({len(self.slots)} slots, {self.pool_bytes} bytes in use; limits '
                        f'{_limits.as_dict()}): {self._fallback_reason(cause, capacity)}; such '
                        'buffers fall back to private memory and are sent as CPU bytes (logged '
                        f'once per cause, see demo_buffer_backend.stats()["fallbacks_{cause}"])')
                return None
            slot.pins += 1
            slot.last_used = time.monotonic_ns()
            return slot.view[:nbytes], Pin(self, slot, nbytes)

    def _fallback_reason(self, cause: str, capacity: int) -> str:
        if cause == 'too_large':
            return (f'the request ({capacity} bytes in whole pages) is larger than max_pool_bytes '
                    f'({_limits.max_pool_bytes}) or max_slots is 0')
        if cause == 'enospc':
            return (f'/dev/shm has no room for another {capacity}-byte segment (ENOSPC: the '
                    'tmpfs is full or its size limit is reached)')
        if cause == 'shm_error':
            return 'creating a segment failed (see the warning before)'
        held = sum(1 for s in self.slots.values() if s.pins)
        return (f'every slot is in use: {held} pinned by buffers this process still holds, the '
                'others held by subscribers (views, or descriptors in flight within each '
                "peer's share)")

    @staticmethod
    def _fits(slot: _Slot, nbytes: int) -> bool:
        return nbytes <= slot.capacity <= 2 * max(nbytes, shm.PAGE_SIZE)

    def _maybe_free(self, slot: _Slot, stale_ok: bool, now_ns: int) -> bool:
        """Cheap pre-check (no syscall but cached liveness) of whether ``slot`` may be claimed."""
        if slot.pins:
            return False
        if self._pinning(slot, now_ns) == 0:
            return True
        if not stale_ok:
            return False
        last = shm.read_u64(slot.header, shm.OFF_LAST_PUBLISH)
        return now_ns - last >= _limits.reclaim_timeout * 1e9

    def _lock_free(self, slot: _Slot, stale_ok: bool) -> Optional[bool]:
        """Take the exclusive hold lock of a free slot. Returns None when the slot is not free,
        else whether it is reclaimed (descriptors that still protect it never taken). The caller
        unlocks."""
        if not locks.try_lock(slot.fd, shm.HOLD_BYTE, exclusive=True):
            return None  # some process holds views of it
        # Takers increment `taken` and the takers table only while holding the shared lock:
        # both are stable now.
        header = slot.header
        untaken = shm.read_u64(header, shm.OFF_TAKEN) < shm.read_u64(header, shm.OFF_SENT)
        if untaken and self._pinning(slot, time.monotonic_ns()) == 0:
            self.counters['released_dead_recipients'] += 1
            untaken = False
        if untaken and not stale_ok:
            locks.unlock(slot.fd, shm.HOLD_BYTE)
            return None
        return untaken

    def _pinning(self, slot: _Slot, now_ns: int) -> int:
        """Descriptors of the slot's generation that still protect it: sent to a live
        recipient, neither taken by its process nor released by its ledger.

        Per recipient token ``t``: ``sent_t - released_t - taken_t`` (takes from the takers
        table; a peer without a token is credited the takes nobody in the table made). When the
        table overflowed, only the aggregate ``sent - taken`` can be trusted.
        """
        header = slot.header
        sent = shm.read_u64(header, shm.OFF_SENT)
        taken = shm.read_u64(header, shm.OFF_TAKEN)
        if taken >= sent:
            return 0
        table = shm.takers(header)
        if table is None:
            return sent - taken
        pinning = 0
        for token, count in slot.recipients.items():
            if token is None:
                by = taken - sum(table.values())
            elif not self._alive(token, now_ns):
                continue
            else:
                by = table.get(presence.token_id(token), 0)
            pinning += max(0, count - slot.released.get(token, 0) - by)
        return pinning

    def _taken_by(self, slot: _Slot, token: Optional[str]) -> int:
        """Takes of the slot's current generation by ``token``'s process (0 when unknown)."""
        header = slot.header
        table = shm.takers(header)
        if table is None:
            return 0
        if token is None:
            return shm.read_u64(header, shm.OFF_TAKEN) - sum(table.values())
        return table.get(presence.token_id(token), 0)

    def _alive(self, token: str, now_ns: int) -> bool:
        known = self.liveness.get(token)
        if known is not None and now_ns < known[1]:
            return known[0]
        if token == own_token():
            alive = True  # this process: in-process subscriptions
        else:
            alive = self.presences.alive(token)
            self.counters['liveness_checks'] += 1
        self.liveness[token] = (alive, now_ns + int(LIVENESS_TTL * 1e9))
        if len(self.liveness) > 4 * MAX_MAPPINGS:  # forget long-expired answers
            self.liveness = {t: a for t, a in self.liveness.items() if now_ns < a[1]}
            self.presences.keep_only(self.liveness)
        return alive

    def forget_liveness(self, token: Optional[str]) -> None:
        """Test ``token``'s presence again on next use (its peer endpoint went away)."""
        with self.locked:
            self.liveness.pop(token, None)
            self.presences.forget(token)

    def _claim(self, slot: _Slot, nbytes: int, stale_ok: bool) -> bool:
        untaken = self._lock_free(slot, stale_ok)
        if untaken is None:
            return False
        try:
            self._set_generation(slot, slot.generation + 1, nbytes)
        finally:
            locks.unlock(slot.fd, shm.HOLD_BYTE)
        if untaken:
            self.counters['reclaimed'] += 1
        return True

    @staticmethod
    def _set_generation(slot: _Slot, generation: int, nbytes: int) -> None:
        header = slot.header
        shm.write_u64(header, shm.OFF_SENT, 0)
        shm.write_u64(header, shm.OFF_TAKEN, 0)
        shm.write_u64(header, shm.OFF_LAST_PUBLISH, 0)
        shm.write_u64(header, shm.OFF_OFFSET, 0)
        shm.write_u64(header, shm.OFF_SIZE, nbytes)
        shm.write_u64(header, shm.OFF_GENERATION, generation)
        shm.reset_takers(header)
        slot.generation = generation
        slot.recipients.clear()
        slot.released.clear()

    def _reuse(self, nbytes: int, stale_ok: bool) -> Optional[_Slot]:
        now = time.monotonic_ns()
        candidates = [s for s in self.slots.values()
                      if self._fits(s, nbytes) and self._maybe_free(s, stale_ok, now)]
        candidates.sort(key=lambda s: s.last_used)
        for slot in candidates:
            if self._claim(slot, nbytes, stale_ok):
                return slot
        return None

    def _grow(self, nbytes: int, capacity: int, stale_ok: bool) -> Optional[_Slot]:
        if capacity > _limits.max_pool_bytes or _limits.max_slots < 1:
            self.grow_failure = 'too_large'
            return None
        now = time.monotonic_ns()
        while (len(self.slots) + 1 > _limits.max_slots
               or self.pool_bytes + capacity > _limits.max_pool_bytes):
            # Make room by removing free slots (of the wrong size: fitting ones were tried).
            victims = [s for s in self.slots.values() if self._maybe_free(s, stale_ok, now)]
            victims.sort(key=lambda s: s.last_used)
            for victim in victims:
                untaken = self._lock_free(victim, stale_ok)
                if untaken is not None:
                    if untaken:
                        self.counters['reclaimed'] += 1
                    self._remove_slot(victim)  # closing the fd drops the lock
                    break
            else:
                return None
        try:
            name, fd, header, data = shm.create(capacity)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.ENOMEM, errno.EFBIG):
                self.grow_failure = 'enospc'
            else:
                self.grow_failure = 'shm_error'
                _logger.warning(f'cannot create a {capacity}-byte demo shm segment: {exc}',
                                throttle_duration_sec=10.0)
            return None
        slot = _Slot(name, fd, header, data, capacity)
        self._set_generation(slot, 1, nbytes)
        self.slots[name] = slot
        self.pool_bytes += capacity
        self.counters['segments_created'] += 1
        return slot

    def _remove_slot(self, slot: _Slot) -> None:
        slot.closed = True
        self.slots.pop(slot.name, None)
        self.pool_bytes -= slot.capacity
        shm.unlink(slot.name)
        self.counters['segments_removed'] += 1
        for closer in (slot.view.release, slot.data.close, slot.header.close):
            try:
                closer()
            except (BufferError, ValueError):
                pass  # a view is still exported: the mapping goes when it does
        os.close(slot.fd)

    def describe(self, pin: Pin, recipient: Optional[str] = None,
                 ledger: Optional[PeerLedger] = None) -> Optional[bytes]:
        """Record one more descriptor of ``pin``'s slot, addressed to the process of presence
        token ``recipient`` (None: unknown, never taken for dead), and return it; None when the
        pin is stale, or when ``ledger`` (the peer's, which then gives the token) says that this
        peer gets CPU bytes for this message (see the module docstring, "Fairness")."""
        with self.locked:
            slot = pin.slot
            if pin.state is not self or slot.closed or slot.generation != pin.generation:
                self.counters['descriptors_declined'] += 1
                return None
            now = time.monotonic_ns()
            if ledger is not None:
                recipient = ledger.token
                if not self._admit(ledger, now):
                    self.counters['descriptors_declined'] += 1
                    return None
            header = slot.header
            shm.write_u64(header, shm.OFF_SENT, shm.read_u64(header, shm.OFF_SENT) + 1)
            slot.recipients[recipient] = slot.recipients.get(recipient, 0) + 1
            shm.write_u64(header, shm.OFF_LAST_PUBLISH, now)
            slot.last_used = now
            if ledger is not None:
                ledger.inflight.append(_InFlight(slot, slot.generation, ledger.seq, now))
                if ledger.pending_since_ns is None:
                    ledger.pending_since_ns = now
            self.counters['descriptors_created'] += 1
            if pin.packed is None:
                pin.packed = desc_codec.pack(desc_codec.Descriptor(
                    slot.name, self.pid, 0, pin.size, pin.generation))
            return pin.packed

    def _admit(self, ledger: PeerLedger, now: int) -> bool:
        """Count one message to the ledger's peer; False when it gets CPU bytes."""
        ledger.seq += 1
        token = ledger.token
        if token is not None and not self._alive(token, now):
            self.counters['cpu_dead_peer'] += 1
            return False
        self._settle(ledger, now)
        if not ledger.idle and ledger.pending_since_ns is not None and \
                now - ledger.pending_since_ns >= IDLE_SECONDS * 1e9:
            ledger.idle = True
            self.counters['peers_idle'] += 1
            _logger.info(f'demo peer {token or "(no token)"} took none of its descriptors for '
                         f'{IDLE_SECONDS:g} s: it gets CPU bytes (and a probe descriptor every '
                         f'{PROBE_SECONDS:g} s) until it takes again', throttle_duration_sec=10.0)
        share = _limits.peer_share()
        if ledger.idle:
            if now - ledger.probe_ns < PROBE_SECONDS * 1e9:
                self.counters['cpu_not_taking'] += 1
                return False
            # Its descriptors in flight stay valid: a stalled peer that resumes takes them, as
            # a stock subscriber would take its backlog. Within its share it gets a probe, whose
            # take shows it is back; at its share, CPU bytes (its pins are its own share).
            if self._at_share(ledger, share):
                self.counters['cpu_not_taking'] += 1
                return False
            ledger.probe_ns = now
            self.counters['probes'] += 1
            return True
        if self._at_share(ledger, share):
            # past its share the peer alone gets CPU bytes: its descriptors in flight stay
            # valid (no message is lost, as with stock), and it pins no more than its share
            self.counters['over_share'] += 1
            return False
        return True

    @staticmethod
    def _at_share(ledger: PeerLedger, share: int) -> bool:
        """Whether the peer pins its share: ``share`` descriptors, or a third of the pool's
        bytes (large frames reach that first)."""
        return len(ledger.inflight) >= share or \
            sum(entry.slot.capacity for entry in ledger.inflight) >= _limits.peer_share_bytes()

    def _settle(self, ledger: PeerLedger, now: int) -> None:
        """Bring the peer's in-flight list up to date: drop what it took or what was reclaimed,
        release what it can no longer take (beyond its KEEP_LAST window, or skipped)."""
        token = ledger.token
        took = False
        for entry in ledger.watch:  # released unseen: a take still shows it is taking
            if entry.slot.generation == entry.generation and not entry.slot.closed and \
                    self._taken_by(entry.slot, token):
                took = True
        if took:
            ledger.watch.clear()
        kept: List[_InFlight] = []
        for entry in ledger.inflight:
            slot = entry.slot
            if slot.closed or slot.generation != entry.generation:
                continue  # reclaimed or removed: nothing left to protect
            if self._taken_by(slot, token) + slot.released.get(token, 0) >= \
                    slot.recipients.get(token, 0):
                took = True
                if ledger.per_channel:
                    # Taken in order: what it had not taken before this one, it dropped.
                    for skipped in kept:
                        self._release_entry(skipped, token, 'released_skipped')
                    kept = []
                continue
            kept.append(entry)
        if ledger.depth:
            while kept and ledger.seq - kept[0].seq >= ledger.depth:
                entry = kept.pop(0)
                self._release_entry(entry, token, 'released_window')
                ledger.watch.append(entry)
        ledger.inflight = collections.deque(kept)
        if took:
            ledger.pending_since_ns = kept[0].sent_ns if kept else None
            ledger.idle = False
        elif not kept and ledger.pending_since_ns is not None and not ledger.watch:
            ledger.pending_since_ns = None

    def _release_entry(self, entry: _InFlight, token: Optional[str], counter: str) -> None:
        """The peer can no longer take ``entry``: it stops protecting its slot."""
        slot = entry.slot
        if slot.closed or slot.generation != entry.generation:
            return
        slot.released[token] = slot.released.get(token, 0) + 1
        self.counters[counter] += 1

    def decline(self) -> None:
        with self.locked:
            self.counters['descriptors_declined'] += 1

    # --- subscriber side ---------------------------------------------------------------------
    def open_descriptor(self, raw) -> Tuple[memoryview, Hold]:
        """A read-only view of the bytes ``raw`` names and the hold that protects it."""
        try:
            d = desc_codec.unpack(raw)
        except ValueError:
            with self.locked:
                self.counters['rejected'] += 1
            raise
        with self.locked:
            try:
                if self.closed:
                    raise ValueError('the demo backend of this process is shut down')
                return self._open(d)
            except ValueError:
                self.counters['rejected'] += 1
                raise

    def _open(self, d: desc_codec.Descriptor) -> Tuple[memoryview, Hold]:
        self._start()
        now = time.monotonic()
        if now - self.last_sweep >= SWEEP_INTERVAL:
            self.last_sweep = now
            self._sweep()
        mapping = self.mappings.get(d.name) or self._map(d.name)
        try:
            size_now = os.fstat(mapping.fd).st_size
        except OSError as exc:  # pragma: no cover - our own fd
            raise ValueError(f'cannot stat demo segment {d.name!r}: {exc}') from None
        if size_now != shm.HEADER_SIZE + mapping.capacity:
            raise ValueError(f'demo segment {d.name!r} changed size ({size_now} bytes, mapped '
                             f'{shm.HEADER_SIZE + mapping.capacity})')
        if d.offset > mapping.capacity or d.size > mapping.capacity - d.offset:
            raise ValueError(f'demo descriptor range [{d.offset}, {d.offset + d.size}) is outside '
                             f'segment {d.name!r} ({mapping.capacity} data bytes)')
        if mapping.refs == 0 and not self._acquire_hold(mapping):
            self.counters['stale'] += 1
            raise ValueError(f'demo descriptor for {d.name!r} generation {d.generation} is stale: '
                             'its publisher is reusing the slot')
        mapping.refs += 1
        ok = False
        try:
            header = mapping.header
            generation = shm.read_u64(header, shm.OFF_GENERATION)
            if generation != d.generation:
                self.counters['stale'] += 1
                raise ValueError(f'demo descriptor for {d.name!r} is stale: generation '
                                 f'{d.generation}, the slot is at generation {generation}')
            offset = shm.read_u64(header, shm.OFF_OFFSET)
            size = shm.read_u64(header, shm.OFF_SIZE)
            if (offset, size) != (d.offset, d.size):
                raise ValueError(f'demo descriptor names bytes [{d.offset}, {d.offset + d.size}) '
                                 f'of {d.name!r} but its publisher recorded [{offset}, '
                                 f'{offset + size}) for generation {generation}')
            if locks.lock_within(mapping.fd, shm.MUTEX_BYTE, exclusive=True,
                                 timeout=MUTEX_WAIT_SECONDS):
                try:
                    shm.write_u64(header, shm.OFF_TAKEN, shm.read_u64(header, shm.OFF_TAKEN) + 1)
                    shm.record_taker(header, presence.token_id(own_token()))
                finally:
                    locks.unlock(mapping.fd, shm.MUTEX_BYTE)
            else:
                # Someone keeps the mutex byte (a stopped or hostile process of our user). The
                # view is valid (our hold lock is in place, the generation checked): deliver it,
                # unrecorded; its publisher sees this peer as not taking, which costs only us.
                self.counters['take_unrecorded'] += 1
                _logger.warning(f'demo segment {d.name!r}: its mutex byte stayed locked for '
                                f'{MUTEX_WAIT_SECONDS * 1000:g} ms; the message is delivered but '
                                'its take is not recorded (see demo_buffer_backend.stats()'
                                '["take_unrecorded"])', throttle_duration_sec=5.0)
            hold = Hold(self, mapping, generation)
            ok = True
        finally:
            if not ok:
                self._release(mapping)
        self.counters['taken'] += 1
        # Keep the cache in LRU order (dicts keep insertion order).
        self.mappings[d.name] = self.mappings.pop(d.name)
        return mapping.view[d.offset:d.offset + d.size], hold

    @staticmethod
    def _acquire_hold(mapping: _Mapping) -> bool:
        if locks.try_lock(mapping.fd, shm.HOLD_BYTE, exclusive=False):
            return True
        for pause in _HOLD_RETRIES:  # the publisher holds it exclusively for a few microseconds
            time.sleep(pause)
            if locks.try_lock(mapping.fd, shm.HOLD_BYTE, exclusive=False):
                return True
        return False

    def _map(self, name: str) -> _Mapping:
        try:
            fd, st = shm.open_existing(name)
        except FileNotFoundError:
            raise ValueError(f'demo segment {name!r} does not exist (its publisher removed it or '
                             'is gone, or it lives in another shm domain)') from None
        except OSError as exc:
            raise ValueError(f'cannot open demo segment {name!r}: {exc}') from None
        header = data = None
        try:
            problem = shm.untrusted(st)
            if problem:
                self.counters['untrusted_segments'] += 1
                raise ValueError(f'demo segment {name!r} is not one the demo backend creates: '
                                 f'{problem}')
            if st.st_size < shm.HEADER_SIZE + shm.PAGE_SIZE:
                raise ValueError(f'{name!r} ({st.st_size} bytes) is too small for a demo segment')
            header = shm.map_header(fd)
            fields = shm.read_header(header)
            if fields.magic != shm.MAGIC or fields.header_size != shm.HEADER_SIZE:
                raise ValueError(f'{name!r} is not an initialized demo segment')
            owner = int(shm.NAME_PATTERN.match(name).group(1))
            if fields.owner_pid != owner:
                self.counters['untrusted_segments'] += 1
                raise ValueError(f'demo segment {name!r} records owner pid {fields.owner_pid}, '
                                 f'its name says {owner}')
            if fields.capacity != st.st_size - shm.HEADER_SIZE:
                raise ValueError(f'demo segment {name!r} records capacity {fields.capacity} but '
                                 f'holds {st.st_size - shm.HEADER_SIZE} data bytes')
            data = shm.map_data_readonly(fd, fields.capacity)
        except BaseException as exc:
            for m in (data, header):
                if m is not None:
                    m.close()
            os.close(fd)
            if isinstance(exc, OSError):
                raise ValueError(f'cannot map demo segment {name!r}: {exc}') from None
            raise
        mapping = _Mapping(name, fd, header, data, fields.capacity)
        self.mappings[name] = mapping
        self.counters['mappings_opened'] += 1
        if len(self.mappings) > MAX_MAPPINGS:
            for other in list(self.mappings.values()):
                if len(self.mappings) <= MAX_MAPPINGS:
                    break
                if other.refs == 0 and other is not mapping:
                    self._close_mapping(other)
        return mapping

    def _close_mapping(self, mapping: _Mapping) -> None:
        mapping.closed = True
        self.mappings.pop(mapping.name, None)
        self.counters['mappings_closed'] += 1
        for closer in (mapping.view.release, mapping.data.close, mapping.header.close):
            try:
                closer()
            except (BufferError, ValueError):
                pass  # a view is still exported: the mapping goes when it does
        os.close(mapping.fd)

    def _sweep(self) -> None:
        for mapping in list(self.mappings.values()):
            try:
                gone = os.fstat(mapping.fd).st_nlink == 0
                if not gone and not shm.owner_alive(mapping.fd):
                    # Its publisher died: whoever notices first removes the file.
                    self.counters['scavenged'] += shm.unlink(mapping.name)
                    gone = True
            except OSError:
                gone = True
            if gone and mapping.refs == 0:
                self._close_mapping(mapping)

    def sweep(self) -> None:
        """Close unreferenced mappings of removed segments; remove segments of dead owners."""
        with self.locked:
            self._sweep()

    def scavenge(self) -> int:
        with self.locked:
            removed = shm.scavenge(skip=self.slots)
            self.counters['scavenged'] += removed
            return removed

    # --- diagnostics -------------------------------------------------------------------------
    def stats(self) -> dict:
        with self.locked:
            result = dict(self.counters)
            result.update(
                slots=len(self.slots),
                bytes=self.pool_bytes,
                slots_pinned=sum(1 for s in self.slots.values() if s.pins),
                mappings=len(self.mappings),
                mappings_held=sum(1 for m in self.mappings.values() if m.refs),
                views_held=sum(m.refs for m in self.mappings.values()),
                presence=self.presence.token if self.presence is not None else None,
                recipients_dead=sorted(t for t, (a, _) in self.liveness.items() if not a),
                peer_share=_limits.peer_share(),
                **_limits.as_dict())
            return result


_state: Optional[State] = None
_state_lock = threading.Lock()
_atexit_registered = False
#: (pid, token): this process's presence token, the same for its whole life (it is advertised in
#: the backend metadata, which endpoints keep), even across pool shutdowns.
_token: Optional[Tuple[int, str]] = None
#: The pid that advertised its token: its pool re-creates the presence file after a shutdown.
_advertised_pid = 0


def own_token() -> str:
    """This process's presence token (the presence file may not exist: see State)."""
    global _token
    token = _token
    if token is None or token[0] != os.getpid():
        token = _token = (os.getpid(), presence.new_token())
    return token[1]


def _token_advertised() -> bool:
    return _advertised_pid == os.getpid()


def get_state() -> State:
    """The process-wide state (created on first use, and anew after :func:`shutdown`)."""
    global _state, _atexit_registered
    state = _state
    if state is not None and state.pid == os.getpid():
        return state
    with _state_lock:
        if _state is None or _state.pid != os.getpid():
            _state = State()
            if not _atexit_registered:
                _atexit_registered = True
                atexit.register(_shutdown_at_exit)
        return _state


def shutdown() -> None:
    """Remove every segment this process created and close every mapping (also done at exit).

    The backend stays usable: the next use starts afresh.
    """
    global _state
    with _state_lock:
        state, _state = _state, None
    if state is not None and state.pid == os.getpid():
        state.shutdown()


def _shutdown_at_exit() -> None:
    try:
        shutdown()
    except Exception:  # pragma: no cover - never fail the interpreter's exit
        pass


def _after_fork_in_child() -> None:
    global _state, _state_lock
    _state_lock = threading.Lock()
    state, _state = _state, None
    if state is not None:
        state.forget_after_fork()


os.register_at_fork(after_in_child=_after_fork_in_child)


def stats() -> dict:
    """Counters and gauges of this process's demo backend (see the README of the package)."""
    return get_state().stats()
