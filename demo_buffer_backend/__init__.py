"""demo_buffer_backend: the ``demo`` buffer backend, payloads in sealed anonymous memory.

Image bytes live in memfd segments: no name in any filesystem (nothing in /dev/shm to plant,
truncate or leak), pages backed when a segment is created and sealed against shrinking, growing
and writing by anyone but its creator before another process sees it (a reader can never hit
SIGBUS). A publisher hands each segment once to each subscriber process that may use it, as a
file descriptor over an abstract-namespace Unix socket (SCM_RIGHTS, peer credentials checked);
then only a 52-byte descriptor crosses DDS per frame and the subscriber gets a zero-copy
read-only view. The kernel frees a segment with its last descriptor or mapping: when its
publisher and every subscriber that held it are done, or dead (SIGKILL included). A descriptor
in flight in a socket outlives its sender, so frames a publisher sent before it died stay
readable until the subscriber drops them.

- :mod:`.buffer`: :class:`DemoBuffer` (``from_cpu``, ``allocate``, ``to_array``);
- :mod:`.backend`: :class:`DemoBackend`, the plugin;
- :mod:`.pool`: :class:`~.pool.Pool`, the process's backend composed behind one interface, of
  :mod:`.slots` (the publisher's segments and pins), :mod:`.ledgers` (per-endpoint fairness),
  :mod:`.links` (the publisher's links to subscriber processes), :mod:`.inbox` (the subscriber's
  listener and inbound connections) and :mod:`.mappings` (its received segments and holds),
  under one lock (:mod:`.guard`);
- :mod:`.lifecycle`: the process's one pool, made on first use, closed at exit, forgotten in a
  forked child;
- :mod:`.limits`: every limit and timing; :mod:`.diagnostics`: counters and warnings;
- :mod:`.memory`: sealed segments, their header, their OFD hold lock, and the checks of a
  received one;
- :mod:`.handover`: listeners, links, handover and acknowledgement records, credentials;
- :mod:`.descriptor`: the descriptor wire format and its validation.

Backend metadata: ``mfd1.<boot id>.<net ns>.<mnt ns>.<pid ns>.<euid>.<pid>_<16 hex>``, the
domain (peers are compatible when it is equal) then the token that names the process's listener.

Pool limits: ``configure(max_pool_bytes=, max_slots=, reclaim_timeout=,
max_inflight_per_peer=)``, the environment variables ``RBPY_DEMO_MAX_POOL_BYTES``,
``RBPY_DEMO_MAX_SLOTS``, ``RBPY_DEMO_RECLAIM_TIMEOUT``, ``RBPY_DEMO_MAX_INFLIGHT_PER_PEER``, or
``DemoBackend(...)`` keyword arguments. Defaults: 512 MiB, 64 slots, 5 s, a third of the slots
(half for a subscriber whose history is known).

Trust: a received descriptor is mapped only if it is a memfd carrying every seal, of the size
its record announces, all backed, with our header, handed over by a process of our uid; a frame
descriptor names a segment by the pid that handed it over (SO_PEERCRED), so no process can
answer for another. Everything refused is counted (:func:`stats`) and logged once per cause.
"""
from demo_buffer_backend.backend import DemoBackend
from demo_buffer_backend.buffer import BACKEND_TYPE, DemoBuffer
from demo_buffer_backend.lifecycle import shutdown, stats
from demo_buffer_backend.limits import configure


def sweep() -> None:
    """Take segments handed over meanwhile; close those nobody can use any more (retired by
    their publisher, or unused for ``limits.ORPHAN_SECONDS`` since their publisher hung up)."""
    from demo_buffer_backend import lifecycle
    lifecycle.get_pool().sweep()


__all__ = ['BACKEND_TYPE', 'DemoBackend', 'DemoBuffer', 'configure', 'shutdown', 'stats',
           'sweep']
