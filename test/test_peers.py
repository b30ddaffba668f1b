"""PeerTable and Reannouncer against stand-ins for the node, the discovery and the owner (no DDS):
the PeerHandlers are called as documented, and teardown happens once."""
from dataclasses import dataclass, field
from typing import Dict, Optional
import threading

import pytest

from rosidl_buffer_py import peers, reannounce
from rosidl_buffer_py.backend import EndpointInfo, EndpointKind
from rosidl_buffer_py.discovery import PeerEndpoint

TOPIC = '/camera/image'
OWN_GID = bytes(range(16))


class Timer:
    timer_period_ns = 1

    def __init__(self, callback):
        self.callback = callback


class Node:
    def __init__(self):
        self.destroyed = []

    def create_guard_condition(self, callback, group):
        return object()

    def create_timer(self, period, callback, group):
        return Timer(callback)

    def destroy_timer(self, timer):
        self.destroyed.append(timer)

    def destroy_guard_condition(self, guard):
        self.destroyed.append(guard)

    def get_publishers_info_by_topic(self, topic):
        return []

    get_subscriptions_info_by_topic = get_publishers_info_by_topic


class Discovery:
    def __init__(self):
        self.watching, self.known = set(), []

    def watch(self, topic, watcher):
        self.watching.add(topic)
        return list(self.known)

    def unwatch(self, topic, watcher):
        self.watching.discard(topic)

    def process(self):
        pass


class Channel:
    def __init__(self):
        self.matched, self.destroyed = 0, False

    def matched_count(self):
        return self.matched

    def destroy(self):
        self.destroyed = True


@dataclass
class Record:
    info: EndpointInfo
    backends: Dict[str, str]
    channel: Optional[Channel] = field(default_factory=Channel)
    created_at: float = 0.0


class Owner:
    """PeerHandlers (and an announce) that log their calls."""

    def __init__(self):
        self.calls, self.table = [], None

    def announce(self):
        self.calls.append('announce')

    def peer_seen(self):
        self.seen = getattr(self, 'seen', 0) + 1

    def channels_checked(self):
        self.checks = getattr(self, 'checks', 0) + 1

    def add_peer(self, info, backends):
        self.calls.append(('add', info.gid))
        return Record(info, backends)

    def update_peer(self, record, compatible):
        self.calls.append(('update', record.info.gid, frozenset(compatible)))

    def forget_peer(self, record):
        self.calls.append(('forget', record.info.gid))

    def peer_gone(self, gid):
        self.calls.append(('gone', gid))
        self.table.drop(gid)

    def release(self):
        self.calls.append('release')


class Backend:
    def __init__(self):
        self.removed = []

    def on_discovering_endpoint(self, info, existing, advertised):
        return True, []

    def on_removing_endpoint(self, info):
        self.removed.append(info.gid)


@pytest.fixture
def table(monkeypatch):
    discovery = Discovery()
    monkeypatch.setattr(peers.discovery, 'for_node', lambda node: discovery)
    owner, node, backend = Owner(), Node(), Backend()
    t = peers.PeerTable(owner, node, None, announce=owner.announce, lock=threading.RLock(),
                        peer_kind=EndpointKind.SUBSCRIPTION, topic_name=TOPIC, gid=OWN_GID,
                        backends={'demo': backend}, logger=None)
    owner.table = t
    t.open()
    yield t, owner, node, discovery, backend
    t.close()


def peer(gid: bytes, backends=None, kind=EndpointKind.SUBSCRIPTION, local=False):
    return PeerEndpoint(gid, kind, 'rt' + TOPIC, 'T', backends, local)


def test_a_buffer_aware_peer_gets_a_record_and_the_owner_hears_of_it(table):
    t, owner, _, discovery, _ = table
    assert discovery.watching == {'rt' + TOPIC}
    gid = b'\x01' * 16
    t.on_peer(peer(gid, {'cpu': '', 'demo': 'meta'}))
    # no announcement at once (see test_a_new_peers_unmatched_channel_is_announced_soon)
    assert owner.calls == [('add', gid), ('update', gid, frozenset({'demo'}))]
    assert gid in t and len(t) == 1 and t[gid].created_at > 0
    assert t.reannouncer.timer.running  # the first peer brings the unmatched check
    t.on_peer(peer(b'\x02' * 16, {'cpu': ''}, kind=EndpointKind.PUBLISHER))  # other kind
    assert owner.seen == 1
    t.on_peer(peer(b'\x03' * 16))  # a legacy endpoint: no record, yet routes may change
    assert len(t) == 1 and owner.seen == 2


def test_a_withdrawn_or_gone_peer_is_dropped_with_its_channel(table):
    t, owner, _, _, backend = table
    a, b = b'\x01' * 16, b'\x02' * 16
    t.on_peer(peer(a, {'cpu': ''}, local=True))
    t.on_peer(peer(b, {'cpu': ''}, local=True))
    channel_a, channel_b = t[a].channel, t[b].channel
    owner.calls.clear()
    t.on_peer(peer(a))  # withdrew its advertisement: a legacy endpoint now
    t.on_peer_gone(b)
    assert owner.calls == [('forget', a), ('gone', b), ('forget', b)]
    assert channel_a.destroyed and channel_b.destroyed and len(t) == 0
    assert backend.removed == [a, b]


def test_close_drops_every_peer_and_releases_the_owner_once(table):
    t, owner, node, discovery, _ = table
    t.on_peer(peer(b'\x01' * 16, {'cpu': ''}, local=True))
    timer = t.reannouncer.timer.timer
    t.close()
    t.close()
    assert t.closed and not discovery.watching
    assert owner.calls.count('release') == 1 and len(t) == 0
    assert node.destroyed == [timer] and not t.reannouncer.timer.running
    t.on_peer(peer(b'\x02' * 16, {'cpu': ''}))  # nothing is added after teardown
    assert len(t) == 0


def test_an_unmatched_channel_is_re_announced_and_a_matched_one_retires_the_timer(
        table, monkeypatch):
    t, owner, _, _, _ = table
    now = [1000.0]
    monkeypatch.setattr(reannounce.time, 'monotonic', lambda: now[0])
    node = Node()
    t.reannouncer = reannounce.Reannouncer(node, None, t, owner.announce,
                                           owner.channels_checked, None)
    gid = b'\x01' * 16
    t.on_peer(peer(gid, {'cpu': ''}, local=True))
    t[gid].created_at = now[0]
    assert not t.reannouncer.spinning(now[0])
    owner.calls.clear()
    now[0] += reannounce.UNMATCHED_REANNOUNCE_SECONDS
    t.reannouncer._on_timer()
    assert owner.calls == ['announce'] and t.reannouncer.spinning(now[0])
    t[gid].channel.matched = 1
    timer = t.reannouncer.timer.timer
    t.reannouncer._on_timer()
    # retired: every channel is matched; destroyed, not cancelled (rclpy's executor waits on
    # cancelled timers too, and pays for each on every wake-up)
    assert not t.reannouncer.timer.running and node.destroyed == [timer]
    now[0] += 10 * reannounce.SPIN_EVIDENCE_SECONDS
    assert t.reannouncer.spinning(now[0])  # only a spun node retires its timer


def test_a_new_peers_unmatched_channel_is_announced_soon_but_not_at_once(table, monkeypatch):
    """A new remote peer may have missed our advertisement: if its channel is still unmatched
    NEW_PEER_REANNOUNCE_SECONDS after it appeared, we announce once; not when it appears (a
    USER_DATA change while its participant matches our main endpoint delays that match), and
    not when its channel matched meanwhile (both taps saw each other)."""
    t, owner, _, _, _ = table
    now = [1000.0]
    monkeypatch.setattr(reannounce.time, 'monotonic', lambda: now[0])
    t.reannouncer = reannounce.Reannouncer(Node(), None, t, owner.announce,
                                           owner.channels_checked, None)
    now[0] += reannounce.UNMATCHED_REANNOUNCE_SECONDS  # the endpoint is not brand new
    missed, seen = b'\x01' * 16, b'\x02' * 16
    for gid in (missed, seen):
        t.on_peer(peer(gid, {'cpu': ''}))
    assert 'announce' not in owner.calls
    t[seen].channel.matched = 1
    now[0] += reannounce.NEW_PEER_REANNOUNCE_SECONDS / 2
    t.reannouncer._on_timer()
    assert 'announce' not in owner.calls  # too soon
    now[0] += reannounce.NEW_PEER_REANNOUNCE_SECONDS / 2
    t.reannouncer._on_timer()
    assert owner.calls.count('announce') == 1
    t.reannouncer._on_timer()
    assert owner.calls.count('announce') == 1  # then at most once a second
    now[0] += reannounce.UNMATCHED_REANNOUNCE_SECONDS
    t.reannouncer._on_timer()
    assert owner.calls.count('announce') == 2
    # a peer that appears right after an announcement gets its own, not a second later
    late = b'\x03' * 16
    t.on_peer(peer(late, {'cpu': ''}))
    t[late].created_at = now[0]
    now[0] += reannounce.NEW_PEER_REANNOUNCE_SECONDS
    t.reannouncer._on_timer()
    assert owner.calls.count('announce') == 3
    t[missed].channel.matched = t[late].channel.matched = 1
    t.reannouncer._on_timer()
    assert not t.reannouncer.timer.running
    assert owner.checks == 6  # each run: a channel may have matched (a publisher re-plans)

