"""The peer endpoints a backend built on this machinery serves: the token of each compatible
peer's process and the ledger of each peer endpoint (per local publisher when known).

Shared by ``DemoBackend`` and ``cuda_buffer_backend.CudaBackend`` (one per device there).
"""
import threading
from typing import Dict, Optional, Tuple

from rosidl_buffer_py.backend import EndpointInfo

from demo_buffer_backend.ledgers import EndpointLedger


class ServedEndpoints:
    """Compatible peers (gid -> the token of their process) and their ledgers."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._peers: Dict[bytes, str] = {}
        #: (peer gid, local publisher gid or None) -> ledger of its descriptors in flight.
        self._ledgers: Dict[Tuple[bytes, Optional[bytes]], EndpointLedger] = {}

    def note(self, gid: bytes, token: Optional[str]) -> None:
        """Discovery says the peer's process is ``token`` (None: the peer cannot be served);
        its ledgers go when that changes."""
        with self._lock:
            if self._peers.get(gid, token) != token or token is None:
                self._forget_ledgers(gid)  # another process now, or none
            if token is not None:
                self._peers[gid] = token
            else:
                self._peers.pop(gid, None)

    def forget(self, gid: bytes) -> None:
        """The peer is gone: forget it and its ledgers (what it was sent settles through its
        link)."""
        with self._lock:
            self._peers.pop(gid, None)
            self._forget_ledgers(gid)

    def _forget_ledgers(self, gid: bytes) -> None:
        for key in [key for key in self._ledgers if key[0] == gid]:
            del self._ledgers[key]

    def token(self, gid: bytes) -> Optional[str]:
        """The token of a compatible peer's process (None: unknown peer)."""
        return self._peers.get(gid)

    def __contains__(self, gid: bytes) -> bool:
        return gid in self._peers

    def ledger_of(self, endpoint_info: EndpointInfo) -> Optional[EndpointLedger]:
        """The ledger of the peer endpoint (per local publisher when named), its depth and
        delivery check refreshed; None for a peer not known to be compatible.

        Its depth is the KEEP_LAST depth that bounds what the peer can take on one channel, 0
        for KEEP_ALL; None when unknown, or when the local publisher is not named (its window
        would count other channels' messages)."""
        gid = endpoint_info.gid
        token = self._peers.get(gid)
        if token is None:
            return None
        key = (gid, endpoint_info.local_gid)
        ledger = self._ledgers.get(key)  # (a dict read: safe without the lock)
        if ledger is None or ledger.token != token:
            with self._lock:
                ledger = self._ledgers.get(key)
                if ledger is None or ledger.token != token:
                    ledger = self._ledgers[key] = EndpointLedger(
                        token, None, per_channel=key[1] is not None)
        ledger.depth = None if key[1] is None else endpoint_info.history_depth
        ledger.delivered = endpoint_info.delivered
        return ledger

    def summary(self) -> Dict[str, dict]:
        """Per peer served so far (``<gid hex>`` or ``<gid hex>/<local publisher gid hex>``):
        its token, depth, messages and descriptors in flight."""
        with self._lock:
            ledgers = dict(self._ledgers)
        return {gid.hex() + (f'/{local.hex()}' if local else ''): ledger.summary()
                for (gid, local), ledger in ledgers.items()}
