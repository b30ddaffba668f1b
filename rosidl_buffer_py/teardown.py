"""Exit-time teardown of the buffer-aware endpoints' peer tables.

Channels and discovery wake-ups pin their node (rclpy defers destroying it). A script that ends
without ``destroy_node()`` (Ctrl-C out of ``rclpy.spin``) would otherwise keep the DDS
participant alive until the process dies, and Fast DDS's shared-memory files with it; stock
rclpy frees everything when the interpreter exits, and so do we: every open
:class:`~rosidl_buffer_py.peers.PeerTable` is closed at exit at the latest.
"""
import atexit
import weakref
from typing import Protocol

from rclpy.logging import get_logger

_logger = get_logger('rosidl_buffer_py')


class Closable(Protocol):
    def close(self) -> None:
        """Free everything (idempotent); calls :func:`untrack`."""


_live: 'weakref.WeakSet[Closable]' = weakref.WeakSet()


def track(table: Closable) -> None:
    """Close ``table`` at interpreter exit unless it was closed before."""
    _live.add(table)


def untrack(table: Closable) -> None:
    _live.discard(table)


@atexit.register
def _close_live() -> None:
    for table in list(_live):
        try:
            table.close()
        except Exception as exc:  # exiting: report, never raise
            _logger.debug(f'teardown at exit: {type(exc).__name__}: {exc}')
