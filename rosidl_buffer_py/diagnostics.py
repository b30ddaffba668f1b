"""What ``statistics()`` and ``buffer_peers()`` of the buffer-aware endpoints return.

Frozen dataclasses: read them by attribute (``peer.channel_serving``). For code written against
the earlier dicts, ``record['channel_serving']`` still works, and :meth:`as_dict` gives a plain
(JSON-ready) dict, nested records included.
"""
import dataclasses
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple


class _Record:
    """Item access and :meth:`as_dict` for the dataclasses below."""

    __slots__ = ()

    def __getitem__(self, name: str) -> Any:
        """``record['field']``, as the dicts these records replace were read."""
        if name not in self.__dataclass_fields__:
            raise KeyError(name)
        return getattr(self, name)

    def keys(self) -> Tuple[str, ...]:
        return tuple(self.__dataclass_fields__)

    def as_dict(self) -> Dict[str, Any]:
        """A plain dict (nested records and lists of them too), e.g. for ``json.dumps``."""
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class SubscriptionPeer(_Record):
    """A buffer-aware subscription a publisher serves, and how (``Publisher.buffer_peers()``)."""

    gid: str                        #: hex
    node: str                       #: fully qualified node name ('' until the graph lists it)
    advertised_backends: Dict[str, str]
    compatible_backends: List[str]  #: those that can serve it, sorted
    channel_topic: str
    channel_matched: bool
    channel_serving: bool           #: its route carries messages on the channel
    route_state: str                #: :class:`rosidl_buffer_py.routes.RouteState` value
    backend_in_use: Optional[str]   #: of the last message (None before the first)
    sent_as_descriptor: int
    sent_as_cpu: int


@dataclass(frozen=True)
class PublisherPeer(_Record):
    """A buffer-aware publisher serving a subscription (``Subscription.buffer_peers()``)."""

    gid: str
    node: str
    advertised_backends: Dict[str, str]
    channel_topic: str
    backend_in_use: Optional[str]
    received_as_descriptor: int
    received_as_cpu: int


@dataclass(frozen=True)
class PublisherStatistics(_Record):
    """``Publisher.statistics()``: counters of the main topic, and per peer."""

    gid: Optional[str]              #: hex; None when not buffer-aware
    buffer_aware: bool
    advertised_backends: Dict[str, str]
    sent_on_main_topic: int
    main_topic_withheld: int        #: main-topic samples kept from channel-served subscriptions
    #: main-topic samples that went to a subscription its channel carried too (a route not
    #: confirmed yet, see docs/design.md): the subscription drops them as duplicates
    main_topic_doubled: int
    cpu_copies_to_buffer_capable_peers: int
    peers_added: int
    peers_removed: int
    peers: List[SubscriptionPeer]
    #: messages published through the steady lane (the writes prepared for steady routes,
    #: docs/design.md); the others took the full path
    published_on_lane: int = 0


@dataclass(frozen=True)
class SubscriptionStatistics(_Record):
    """``Subscription.statistics()``: delivered, per route, dropped and rejected."""

    gid: Optional[str]              #: hex; None when not buffer-aware
    buffer_aware: bool
    advertised_backends: Dict[str, str]
    delivered: int = 0
    from_channels: int = 0
    from_main_topic: int = 0
    duplicates_dropped: int = 0
    rejected: int = 0
    fences: int = 0
    fence_timeouts: int = 0
    fenced_lost: int = 0
    #: publishers whose stream waits now for a fenced main-topic message (its channel's
    #: messages queued meanwhile): the waits that have not ended yet
    waiting_for_fence: int = 0
    peers: List[PublisherPeer] = field(default_factory=list)
    #: of ``from_channels``: delivered by the steady step, opened by the backend's steady
    #: opener (docs/design.md); the others took the general path
    delivered_steady: int = 0
