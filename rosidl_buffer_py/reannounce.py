"""Re-announcing an endpoint whose peer's channel stays unmatched, and whether its node spins.

Both ends create a channel once each knows the other's advertisement. If one of them missed
ours (discovery before its tap existed, or a lost update), our end of the channel stays
unmatched: announcing again lets it see us as a 'changed' endpoint. Each side detects this on
its own, so no back channel is needed. The check runs on a timer that exists only while some
peer's channel is to be watched; the timer's runs are also the evidence that an executor spins
the node (:meth:`Reannouncer.spinning`).
"""
import time
from typing import Callable, Set

from rosidl_buffer_py.on_demand import OnDemandTimer

#: A channel unmatched this long means the peer probably missed our advertisement: re-announce
#: (at most this often).
UNMATCHED_REANNOUNCE_SECONDS = 1.0

#: A new peer's channel still unmatched this long after the peer appeared: it probably
#: discovered us before its tap existed: announce once, sooner than the second above (and
#: whenever the last announcement was). Never at once: a USER_DATA change while the new
#: participant was still matching our main endpoint made Fast DDS leave the match (and the
#: first frames) pending until the next announcement, about 0.9 s, in 5 of 7 runs of
#: ``test/harness/first_frame.py`` (and in 2 of 5 when only the side that was there first
#: announced at once); when both taps saw each other, the channel matches within this time
#: and nothing is announced.
NEW_PEER_REANNOUNCE_SECONDS = 0.25

#: How recently the re-announce timer must have run for the node to count as spinning.
SPIN_EVIDENCE_SECONDS = 2.5 * UNMATCHED_REANNOUNCE_SECONDS


class Reannouncer:
    """The re-announce check of one endpoint over its :class:`~rosidl_buffer_py.peers.PeerTable`.

    The timer is created with the first peer, calls ``checked`` at each run (a channel may
    have matched: no DDS event says so), retires (is destroyed) once every channel is matched,
    and a new peer creates it again. An endpoint without buffer-aware peers, or whose peers'
    channels are all matched, has no timer, as a stock one: it never wakes its executor (each
    wake-up costs a node about half a millisecond of CPU, which at camera rates was most of
    what a publisher spent beyond stock rclpy's), and adds nothing to the executor's other
    wake-ups (see :mod:`rosidl_buffer_py.on_demand`).
    """

    def __init__(self, node, callback_group, peers, announce: Callable[[], None],
                 checked: Callable[[], None], logger) -> None:
        self._peers = peers
        self._announce = announce
        #: called under the peers' lock after each look at the channels (see
        #: PeerHandlers.channels_checked)
        self._checked = checked
        self._announced_at = time.monotonic()
        #: peers that were there at an announcement since they appeared
        self._greeted: Set[bytes] = set()
        self._spun_at = 0.0
        self._retired = False
        #: the timer, running while some peer's channel is to be watched
        self.timer = OnDemandTimer(node, NEW_PEER_REANNOUNCE_SECONDS, self._on_timer,
                                   callback_group, logger)

    def rearm(self) -> None:
        """A new peer's channel is to be watched (under the lock, on the executor's thread:
        only a spun node retires its timer, and a spun node handles discovery there)."""
        self._retired = False
        self.timer.start()

    def close(self) -> None:
        """Stop checking (the endpoint is torn down)."""
        self.timer.stop()

    @property
    def retired(self) -> bool:
        """It retired its timer (every peer's channel matched, on a spinning executor): until
        the next :meth:`rearm` (a new peer), :meth:`spinning` holds whatever the time."""
        return self._retired

    def spinning(self, now: float) -> bool:
        """Whether an executor runs our node: then discovery wakes us by itself.

        Evidence: the timer ran lately, or it retired itself (which only a spinning executor
        does). A node that stops spinning after that keeps its matched channels; peers that come
        later are served on the main topic until it spins again.
        """
        return self._retired or now - self._spun_at < SPIN_EVIDENCE_SECONDS

    def reannounce_if_unmatched(self) -> None:
        """Re-announce our USER_DATA if a known peer's channel stays unmatched."""
        with self._peers.lock:
            if self._peers.closed:
                return
            now = time.monotonic()
            current = {peer.info.gid for peer in self._peers}
            self._greeted &= current
            rested = now - self._announced_at >= UNMATCHED_REANNOUNCE_SECONDS
            for peer in self._peers:
                # a peer's first announcement is not held back by the last one's
                if (peer.channel is not None and peer.channel.matched_count() == 0 and
                        now - peer.created_at >= NEW_PEER_REANNOUNCE_SECONDS and
                        (rested or peer.info.gid not in self._greeted)):
                    self._announced_at = now
                    self._greeted = current  # every peer there now gets this one
                    self._announce()
                    return

    def _on_timer(self) -> None:
        self._spun_at = time.monotonic()  # evidence that an executor spins our node
        self.reannounce_if_unmatched()
        with self._peers.lock:
            if self._peers.closed:
                return
            self._checked()
            if all(peer.channel is None or peer.channel.matched_count() > 0
                   for peer in self._peers):
                self.timer.stop()
                self._retired = True
