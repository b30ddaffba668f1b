"""demo_buffer_backend: the ``demo`` buffer backend, payloads in POSIX shared memory.

Image bytes live in /dev/shm segments (``rbpy_demo_<pid>_<hex>``, mode 0600); only a small
descriptor crosses DDS and the subscriber gets a zero-copy read-only view.

- :mod:`.buffer`: :class:`DemoBuffer` (``from_cpu``, ``allocate``, ``to_array``);
- :mod:`.backend`: :class:`DemoBackend`, the plugin;
- :mod:`.pool`: the process-wide slot pool and mapping cache, per-peer ledgers (fairness: what
  one subscriber does costs only that subscriber), limits, counters, lifecycle and the
  housekeeping thread (dead owners' files leave /dev/shm within seconds);
- :mod:`.shm`: segment files, header layout (with the per-process takers table), liveness and
  scavenging;
- :mod:`.presence`: per-process presence files, so that a publisher stops keeping slots for a
  subscriber process that died (SIGKILL included) within ``pool.LIVENESS_TTL`` (0.1 s) instead of
  the DDS lease;
- :mod:`.locks`: Linux OFD byte-range locks;
- :mod:`.descriptor`: the descriptor wire format and its validation.

Backend metadata: ``shm1.<boot id>.<st_dev>.<st_ino of /dev/shm>.<euid>.<pid>_<16 hex>``, the shm
domain (peers are compatible when it is equal) then the process's presence token.

Pool limits: ``configure(max_pool_bytes=, max_slots=, reclaim_timeout=,
max_inflight_per_peer=)``, the environment variables ``RBPY_DEMO_MAX_POOL_BYTES``,
``RBPY_DEMO_MAX_SLOTS``, ``RBPY_DEMO_RECLAIM_TIMEOUT``, ``RBPY_DEMO_MAX_INFLIGHT_PER_PEER``, or
``DemoBackend(...)`` keyword arguments. Defaults: 512 MiB, 64 slots, 5 s, a third of the slots.

Trust: a segment is mapped only if it looks exactly as the backend creates them (regular file,
no symlink, our uid, mode 0600, our header naming the owner of its name); no lock is waited for
without bound (the take's mutex byte: 20 ms at most).
"""
from demo_buffer_backend.backend import DemoBackend
from demo_buffer_backend.buffer import BACKEND_TYPE, DemoBuffer
from demo_buffer_backend.pool import configure, shutdown, stats


def sweep() -> None:
    """Close unreferenced mappings of removed segments and remove segments of dead owners."""
    from demo_buffer_backend import pool
    pool.get_state().sweep()


def scavenge() -> int:
    """Remove every demo segment in /dev/shm whose owner process is gone; return how many."""
    from demo_buffer_backend import pool
    return pool.get_state().scavenge()


__all__ = ['BACKEND_TYPE', 'DemoBackend', 'DemoBuffer', 'configure', 'scavenge', 'shutdown',
           'stats', 'sweep']
