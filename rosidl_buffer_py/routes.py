"""The route protocol: which route a message takes to each subscription, and how a subscription
turns what arrives on its routes into one ordered stream per publisher.

Pure logic (no DDS, no rclpy): :class:`rosidl_buffer_py.publisher.Publisher` and
:class:`rosidl_buffer_py.subscription.Subscription` feed it events (a channel matched, probes
acknowledged, a sample taken, time passing, a peer gone) and carry out its decisions (write here,
withhold there, deliver, queue, drop).

The publisher asks its :class:`RouteTable` one question per message, :meth:`RouteTable.dispatch`
("what do I write, where, and what do I withhold"), answering the table's questions about DDS
through a :class:`RouteView`, and writes what the answer says in its order: probes, then per
channel the route fence (if any) and the message, then the main topic. A publisher that
prepared its writes for the table's steady answer asks :meth:`RouteTable.dispatch_prepared`
instead, and calls :meth:`RouteTable.advance` right after the message's writes when the table
says a periodic re-plan is due (:attr:`RouteTable.replan_due`). Between messages, a timer calls
:meth:`RouteTable.advance` while a route is being brought up. The table owns the order of the
steps and its cached plan; the route model test (``test/test_routes.py``) drives the same entry
points.

Publisher side: one :class:`Route` per buffer-aware subscription, the route of its private
channel, and one :class:`RouteTable` per publisher::

    UNMATCHED --matched--> PROBING  --acknowledged--> ACKNOWLEDGED --main written--> FENCING
        ^         (RELIABLE KEEP_LAST <= MAX_PROBE_DEPTH)    |  (or no main-topic message yet)
        |     \\--matched--> SETTLING --settle time---------+-----------------------> FENCING
        |                                    probes acknowledged: fence written |
        +-------unmatched-------- CONFIRMED <--channel acknowledged-- SERVING <-+ fence written
    any --gone--> GONE (nothing is written to it any more)

Until FENCING the main topic serves the subscription. A route becomes FENCING only when what its
channel carries from then on reaches the subscription's reader: the reader acknowledged the
probes (so it matched the channel writer), or the channel has been matched for the settle time.
Its first channel message is preceded by a *route fence* naming the last message the main topic
carried for it, which the subscription delivers first. The fence waits (the main topic serving a
while longer, at most ``FENCE_DEFER_SECONDS``) until the main topic's readers acknowledged all
they were sent, so that it can say its message reached the subscription's reader. Once serving,
a route stays on its channel while the channel is matched (the subscription drops main-topic
copies from the fence on). CONFIRMED: the channel's samples were acknowledged too, so main-topic
samples are withheld from that subscription (the DataWriter sends it a GAP instead of the
payload). A route whose probes were acknowledged becomes CONFIRMED with its fence, and the
fenced message's own main-topic copy is withheld too: it would race the channel copy.

Subscription side: one :class:`Stream` per publisher::

    MAIN --channel message--> CHANNEL
      \\--fence--> WAITING --fenced main-topic message delivered, or known lost (a newer
                            main-topic copy came, or it was delivered to the reader and the
                            reader has nothing left), or FENCE_TIMEOUT--> CHANNEL

Every copy of a message carries its publisher's source timestamp, increasing per publisher; a
stream delivers each timestamp at most once and in increasing order. In WAITING, channel
messages are queued (taken from DDS, so the channel's history cannot overflow) until the main
topic delivered the fenced message; main-topic messages are never held.

The subscription takes through a :class:`Receiver`, one :meth:`Receiver.step` at a time, which
owns the take order over its routes (channels first, then the main topic, whose duplicates are
dropped before they are taken) and asks about DDS through a :class:`ReceiveView`; the
subscription counts and decodes what each :class:`Step` gives. The route simulation
(``test/test_route_simulation.py``) drives the publisher's and the subscription's entry points,
over simulated DDS readers and writers.
"""
import collections
import enum
from dataclasses import dataclass, field
from typing import Deque, Dict, Generic, Hashable, Iterable, NamedTuple, Optional, Protocol, \
    Sequence, Tuple, TypeVar

#: How long a channel must have been matched before it serves its subscription, when its
#: reader's readiness cannot be acknowledged (BEST_EFFORT, KEEP_ALL or a deep KEEP_LAST).
CHANNEL_SETTLE_SECONDS = 0.2
#: A route whose probes are not acknowledged yet gets one more at most this often.
PROBE_INTERVAL_SECONDS = 0.01
#: A RELIABLE KEEP_LAST channel up to this depth proves that its reader matched by acknowledging
#: ``depth + 1`` probes (a heartbeat asks for acknowledgments when the writer's history is full).
MAX_PROBE_DEPTH = 100
#: How often a serving route asks whether its channel samples were acknowledged (CONFIRMED).
CONFIRM_INTERVAL_SECONDS = 0.05
#: Routes are recomputed at least this often, whatever else says they are current.
RECHECK_SECONDS = 0.5
#: How long channel messages wait for a fenced main-topic message before it counts as lost
#: (as DDS's KEEP_LAST loses a sample when the reader's history overflows).
FENCE_TIMEOUT_SECONDS = 1.0
#: How long a due route fence waits for the main topic's readers to acknowledge what they were
#: sent, the main topic serving the subscription meanwhile: a fence written after that
#: acknowledgment lets the subscription tell a lost fenced message from a late one at once.
FENCE_DEFER_SECONDS = 0.25


class RouteState(enum.Enum):
    """Where a publisher serves one buffer-aware subscription (see the module's diagram)."""

    UNMATCHED = 'unmatched'        #: the channel has no reader: the main topic serves it
    PROBING = 'probing'            #: channel matched, probes written, not acknowledged yet
    SETTLING = 'settling'          #: channel matched, waiting for the settle time
    ACKNOWLEDGED = 'acknowledged'  #: probes acknowledged; waits for a main-topic message to fence
    FENCING = 'fencing'            #: served on the channel; a fence precedes the next message
    SERVING = 'serving'            #: served on the channel (main-topic copies still reach it)
    CONFIRMED = 'confirmed'        #: served on the channel; main-topic samples withheld from it
    GONE = 'gone'                  #: its process is gone: nothing is written to it


#: States in which the channel carries every message.
ON_CHANNEL = frozenset({RouteState.FENCING, RouteState.SERVING, RouteState.CONFIRMED})


class Fence(NamedTuple):
    """The control message that precedes a route's first channel message."""

    #: Source timestamp of the last message the main topic carried for the subscription (0: none).
    last_main: int
    #: Every reader of the main topic, the subscription's included, had acknowledged that
    #: message when the fence was written: it reached the subscription's reader history, so once
    #: that history has nothing left to take, a fenced message not delivered is lost (KEEP_LAST
    #: overwrite, a startup race), not late, and nothing waits for it.
    delivered: bool = False


@dataclass
class Route:
    """The route of one buffer-aware subscription of a publisher."""

    #: Readiness is acknowledged (probes), not waited for (RELIABLE KEEP_LAST <= MAX_PROBE_DEPTH).
    handshake: bool
    #: Probes written first: the channel's KEEP_LAST depth + 1 (a heartbeat then asks for acks).
    first_probes: int = 1
    state: RouteState = RouteState.UNMATCHED
    matched_since: float = 0.0
    #: When probes were last written (None: none since the channel matched).
    probed_at: Optional[float] = None
    #: The reader acknowledged the probes (since the channel last matched), and the source
    #: timestamp of the last message published when that was seen.
    acknowledged_probes: bool = False
    acknowledged_after: int = 0
    #: Source timestamp of the last message the main topic carried for the subscription.
    last_main: Optional[int] = None
    #: When the channel's own samples were last asked about (SERVING with a handshake).
    asked_at: float = 0.0
    #: When the fence became due and was first deferred (see :meth:`RouteTable.dispatch`).
    fence_due_since: Optional[float] = None

    @property
    def on_channel(self) -> bool:
        return self.state in ON_CHANNEL

    @property
    def needs_main(self) -> bool:
        """The main topic serves this subscription (its channel does not yet)."""
        return self.state not in ON_CHANNEL and self.state is not RouteState.GONE

    @property
    def withheld(self) -> bool:
        """Main-topic samples are kept from this subscription: its channel reaches it
        (CONFIRMED, or FENCING after acknowledged probes, CONFIRMED from the fence on: the
        fenced message's main-topic copy would race its channel copy, and arrive first when
        the main topic's transport is the faster one)."""
        return self.state is RouteState.CONFIRMED or (
            self.state is RouteState.FENCING and self.acknowledged_probes)

    # events --------------------------------------------------------------------------------

    def channel_matched(self, matched: bool, now: float) -> None:
        """The channel's matched state, as DDS reports it now."""
        state = self.state
        if state is RouteState.GONE:
            return
        if not matched:
            if state is not RouteState.UNMATCHED:
                if state in ON_CHANNEL:
                    # a fence went out: the subscription may take later channel samples as
                    # messages, so no probe may follow; if the reader comes back, it settles
                    self.handshake = False
                self.state = RouteState.UNMATCHED
                self.probed_at, self.acknowledged_probes = None, False
                self.fence_due_since = None
            return
        if state is RouteState.UNMATCHED:
            self.matched_since = now
            self.state = RouteState.PROBING if self.handshake else RouteState.SETTLING

    def probes_due(self, now: float) -> int:
        """How many probes to write now (PROBING only): ``first_probes`` at first, then one at
        most every ``PROBE_INTERVAL_SECONDS`` while unacknowledged. The caller writes them."""
        if self.state is not RouteState.PROBING:
            return 0
        if self.probed_at is None:
            self.probed_at = now
            return self.first_probes
        if now - self.probed_at >= PROBE_INTERVAL_SECONDS:
            self.probed_at = now
            return 1
        return 0

    @property
    def awaits_acknowledgment(self) -> bool:
        """Whether the caller should ask DDS if the channel's samples were acknowledged: the
        probes (PROBING, once written), or the first channel messages (SERVING, handshake)."""
        return ((self.state is RouteState.PROBING and self.probed_at is not None) or
                (self.state is RouteState.SERVING and self.handshake))

    def acknowledged(self, last_published: int) -> None:
        """Every sample written on the channel so far was acknowledged by its reader."""
        if self.state is RouteState.PROBING:
            self.acknowledged_probes = True
            self.acknowledged_after = last_published
            # The fence names the last main-topic message written for the subscription, which
            # it waits for: none, or one written after this acknowledgment (its main-topic
            # reader had matched our writer by then; an older one may have left our KEEP_LAST
            # history before the new reader asked for it).
            self.state = (RouteState.FENCING if self.last_main is None
                          else RouteState.ACKNOWLEDGED)
        elif self.state is RouteState.SERVING and self.handshake:
            self.state = RouteState.CONFIRMED

    def tick(self, now: float) -> None:
        """Time passed: a channel matched for the settle time serves its subscription."""
        if (self.state in (RouteState.PROBING, RouteState.SETTLING, RouteState.ACKNOWLEDGED)
                and now - self.matched_since >= CHANNEL_SETTLE_SECONDS):
            self.state = RouteState.FENCING

    def next_tick(self, now: float) -> Optional[float]:
        """When this route next needs the caller's attention (a timed transition, a probe or an
        acknowledgment to ask for), or None."""
        state = self.state
        if state in (RouteState.PROBING, RouteState.SETTLING, RouteState.ACKNOWLEDGED):
            at = self.matched_since + CHANNEL_SETTLE_SECONDS
            if state is RouteState.PROBING:
                at = min(at, now if self.probed_at is None else
                         self.probed_at + PROBE_INTERVAL_SECONDS)
            return at
        if state is RouteState.SERVING and self.handshake:
            return now + CONFIRM_INTERVAL_SECONDS
        return None

    def take_fence(self) -> Optional[Fence]:
        """The fence to write before this message on the channel (FENCING), else None. A
        channel whose reader acknowledged the probes is known to reach it: CONFIRMED at once;
        one that settled by time alone SERVES until its own samples are acknowledged."""
        if self.state is not RouteState.FENCING:
            return None
        self.state = RouteState.CONFIRMED if self.acknowledged_probes else RouteState.SERVING
        self.fence_due_since = None
        return Fence(self.last_main or 0)

    def defer_fence(self, now: float) -> bool:
        """The main topic's readers have not acknowledged all they were sent: whether the due
        fence waits (the main topic serving this message), for at most
        ``FENCE_DEFER_SECONDS``."""
        if self.fence_due_since is None:
            self.fence_due_since = now
        return now - self.fence_due_since < FENCE_DEFER_SECONDS

    def main_written(self, timestamp: int) -> bool:
        """The main topic carried message ``timestamp`` for this subscription (whatever the
        state: a plan made before a transition still routes by the main topic, and the fence
        must name what the subscription was sent). True when the route changed state."""
        if self.state is RouteState.GONE:
            return False
        self.last_main = timestamp
        if self.state is RouteState.ACKNOWLEDGED and timestamp > self.acknowledged_after:
            self.state = RouteState.FENCING
            return True
        return False

    def gone(self) -> None:
        """The subscription's process is known to be gone: nothing more is written to it."""
        self.state = RouteState.GONE


K = TypeVar('K', bound=Hashable)


class Plan(NamedTuple):
    """Where one message goes, as :meth:`RouteTable.plan` decided."""

    #: Keys of the routes served on their channel (a fence first where one is due).
    channel: Tuple[Hashable, ...]
    #: Whether the main topic is written (some matched subscription is not on a channel, or
    #: the publisher is TRANSIENT_LOCAL and keeps the history there).
    main: bool
    #: Subscriptions the main-topic sample is kept from (their channel reaches them, or they
    #: are gone).
    withheld: Tuple[Hashable, ...]
    #: Subscriptions the main topic serves (their last main-topic message is noted).
    main_served: Tuple[Hashable, ...]
    #: Recompute at the latest then.
    recheck_at: float
    #: ``recheck_at`` is the periodic recheck alone (``RECHECK_SECONDS`` after planning; no
    #: route has a timed transition before it).
    periodic: bool = True


class RouteView(Protocol[K]):
    """What DDS says now, as the publisher reads it for :meth:`RouteTable.advance` and
    :meth:`RouteTable.dispatch` (each asked only when the table needs it)."""

    def signature(self, fresh: bool = False) -> Hashable:
        """A cheap summary of what is matched (the main topic's and every channel's matched
        counts): while it holds, so does the cached plan (until its ``recheck_at``). The view
        may answer from memory while nothing suggests a change; ``fresh``: read DDS now (a
        re-plan, so that the view's rechecks keep the plan's pace)."""

    def settled(self, now: float) -> bool:
        """Nothing that may move :meth:`signature` happened since it was last read (no
        discovery, no grace after one), the view's own periodic re-read aside: the table
        re-plans, reading it fresh, at least every ``RECHECK_SECONDS``. Asked by
        :meth:`RouteTable.dispatch_prepared` only."""

    def matched_subscriptions(self) -> Iterable[K]:
        """Keys of the main topic's matched subscriptions, legacy ones included."""

    def channel_matched(self, key: K) -> bool:
        """The channel of ``key``'s route has a matched reader."""

    def channel_acknowledged(self, key: K) -> bool:
        """Every sample written on ``key``'s channel so far was acknowledged by its reader."""

    def main_acknowledged(self) -> bool:
        """Every sample written on the main topic so far was acknowledged by every reader."""


class Advance(NamedTuple):
    """What :meth:`RouteTable.advance` asks the publisher to do."""

    #: Probes to write now, ``(key, count)`` per route being brought up.
    probes: Tuple[Tuple[Hashable, int], ...]
    #: Some route needs attention before ``RECHECK_SECONDS``: advance on a timer (every
    #: ``PROBE_INTERVAL_SECONDS``) too, publishing or not.
    timer: bool


class Dispatch(NamedTuple):
    """Where one message goes (:meth:`RouteTable.dispatch`), in the order to write it."""

    #: First, probes: ``(key, count)`` per route being brought up.
    probes: Tuple[Tuple[Hashable, int], ...]
    #: Then the message on these routes' channels, each preceded by its route fence if one is
    #: given: ``(key, fence or None)``.
    channel: Tuple[Tuple[Hashable, Optional[Fence]], ...]
    #: Then, when True, the main topic, its sample kept from the ``withheld`` subscriptions.
    main: bool
    withheld: Tuple[Hashable, ...]
    #: Whether the route timer runs from now on (see :attr:`Advance.timer`); None: unchanged.
    timer: Optional[bool]


class _Cached(NamedTuple):
    """A :class:`RouteTable`'s plan while the view's signature holds."""

    plan: Plan
    signature: Hashable
    #: The dispatch of every message under this plan, when that is always the same: no route
    #: fences, no main-topic write (whose per-subscription bookkeeping runs per message). Only
    #: a transition can change that, and every transition drops the cached plan.
    steady: Optional[Dispatch]


def _steady_dispatch(plan: Plan, routes: Dict[Hashable, Route]) -> Optional[Dispatch]:
    """The one Dispatch of every message under ``plan``, or None when a message may change a
    route (a fence to take, a main-topic write to note)."""
    if plan.main or any(routes[key].state is RouteState.FENCING for key in plan.channel):
        return None
    return Dispatch((), tuple((key, None) for key in plan.channel), False, plan.withheld, None)


class RouteTable(Generic[K]):
    """The routes of one publisher, by subscription key (its GID)."""

    def __init__(self, *, main_always: bool = False) -> None:
        #: TRANSIENT_LOCAL: every message goes to the main topic, whose history late joiners get.
        self.main_always = main_always
        self.routes: Dict[K, Route] = {}
        #: Last main-topic message per subscription not (yet) known as a buffer-aware peer.
        self._last_main: Dict[K, int] = {}
        #: Source timestamp of the last message dispatched (0: none yet).
        self.last_published = 0
        #: The plan of the next messages, the view's signature it was made with, and the
        #: dispatch that serves every message while it holds when that is always the same
        #: (None: plan again; asking DDS for the matched subscriptions takes tens of
        #: microseconds).
        self._cached: Optional[_Cached] = None
        #: :meth:`dispatch_prepared` answered past the plan's periodic recheck: the publisher
        #: calls :meth:`advance` once that message is written (cleared by :meth:`advance`).
        self.replan_due = False

    @property
    def steady(self) -> Optional[Dispatch]:
        """The cached plan's steady dispatch (see ``_Cached.steady``), or None. A re-plan that
        gives the same answer keeps this very object, so a publisher can prepare its writes
        for it once and use them while it is the one (:meth:`dispatch_prepared`)."""
        cached = self._cached
        return None if cached is None else cached.steady

    @property
    def steady_until(self) -> float:
        """The cached plan's ``recheck_at``: the steady dispatch holds until then at most."""
        cached = self._cached
        return 0.0 if cached is None else cached.plan.recheck_at

    def add(self, key: K, *, handshake: bool, depth: int = 0) -> Route:
        """A buffer-aware subscription was discovered: its route starts UNMATCHED."""
        route = Route(handshake=handshake and 0 < depth <= MAX_PROBE_DEPTH,
                      first_probes=depth + 1, last_main=self._last_main.pop(key, None))
        self.routes[key] = route
        self._cached = None
        return route

    def remove(self, key: K) -> None:
        """A subscription went away (or stopped being buffer-aware)."""
        self.routes.pop(key, None)
        self._last_main.pop(key, None)
        self._cached = None

    def gone(self, key: K) -> None:
        """``key``'s process is known to be gone (its backend said so before DDS): nothing
        more is written to it."""
        route = self.routes.get(key)
        if route is not None:
            route.gone()
        self._cached = None

    def invalidate(self) -> None:
        """Something the signature does not show changed (a subscription of the topic came,
        changed or went): the next message is planned again."""
        self._cached = None

    def advance(self, now: float, view: 'RouteView[K]',
                signature: Optional[Hashable] = None) -> Advance:
        """Bring the routes up to date with DDS (matched channels, acknowledged probes and
        channel samples, time passed) and plan the next messages."""
        if signature is None:
            signature = view.signature(fresh=True)
        self.replan_due = False
        probes = []
        for key, route in self.routes.items():
            route.channel_matched(view.channel_matched(key), now)
            if route.awaits_acknowledgment and view.channel_acknowledged(key):
                route.acknowledged(self.last_published)
            count = route.probes_due(now)
            if count:
                probes.append((key, count))
        plan = self.plan(now, view.matched_subscriptions())
        steady, before = _steady_dispatch(plan, self.routes), self.steady
        if steady is not None and steady == before:
            steady = before  # the same answer: writes prepared for it still serve
        self._cached = _Cached(plan, signature, steady)
        return Advance(tuple(probes), plan.recheck_at - now < RECHECK_SECONDS)

    def dispatch(self, now: float, timestamp: int, view: 'RouteView[K]') -> Dispatch:
        """Where message ``timestamp`` goes, the routes' transitions it makes (a fence goes
        out, the main topic's last message for a subscription) already taken: the publisher
        writes exactly what the answer says, in its order. The cached plan serves while the
        view's signature holds and its ``recheck_at`` has not passed."""
        cached = self._cached
        probes, timer = (), None
        if cached is None or now >= cached.plan.recheck_at or view.signature() != cached.signature:
            before = None if cached is None else cached.steady
            probes, timer = self.advance(now, view)
            cached = self._cached
            if before is not None and cached.steady is before and not probes and not timer:
                # a re-plan that kept the steady answer (the periodic recheck, a discovery that
                # changed nothing here): that object, which a publisher's prepared writes serve
                # (the route timer was stopped by the dispatch that first answered it)
                self.last_published = timestamp
                return before
        elif cached.steady is not None:
            self.last_published = timestamp
            return cached.steady
        plan = cached.plan
        channel, deferred = [], []
        delivered = None  # whether the main topic's readers acknowledged all they were sent
        for key in plan.channel:
            route = self.routes[key]
            if route.state is RouteState.FENCING:
                if delivered is None:
                    delivered = view.main_acknowledged()
                # the fence says whether its message reached the subscription's reader: if so,
                # and that history has nothing left, the message was lost there and nothing
                # waits for it; if not known yet, the main topic serves a while longer
                if not delivered and route.defer_fence(now):
                    deferred.append(key)
                    continue
                fence = route.take_fence()._replace(delivered=delivered)
                self._cached = None  # the route's state changed: plan the next message again
            else:
                fence = None
            channel.append((key, fence))
        main, withheld, main_served = plan.main, plan.withheld, plan.main_served
        if deferred:
            matched = set(view.matched_subscriptions())
            main = True
            withheld = tuple(key for key in withheld if key not in deferred)
            main_served += tuple(key for key in deferred if key in matched)
        if main and self.main_written(main_served, timestamp):
            self._cached = None  # a route may serve from the next message on
        self.last_published = timestamp
        return Dispatch(probes, tuple(channel), main, withheld, timer)

    def dispatch_prepared(self, prepared: Dispatch, now: float, timestamp: int,
                          view: 'RouteView[K]') -> Dispatch:
        """:meth:`dispatch`, for a publisher that prepared its writes for the steady dispatch
        ``prepared``: that very object, known without planning or asking DDS, while it is the
        table's steady answer and the view is settled; else what :meth:`dispatch` answers
        (``prepared`` again after a re-plan to the same answer). Either way message
        ``timestamp`` is dispatched: the publisher writes exactly that.

        Past the plan's periodic recheck (no timed transition due), the answer is still
        ``prepared`` and :attr:`replan_due` is set: the publisher re-plans (:meth:`advance`)
        right after writing this message, not before, so that the re-plan's reads of DDS
        (about 140 µs on cold caches) do not delay a message whose route nothing moved (the
        view would be unsettled if discovery had said anything). The next message goes by
        the new plan."""
        cached = self._cached
        if cached is None or cached.steady is not prepared or not view.settled(now):
            return self.dispatch(now, timestamp, view)
        if now >= cached.plan.recheck_at:
            if not cached.plan.periodic:
                return self.dispatch(now, timestamp, view)
            self.replan_due = True
        self.last_published = timestamp
        return prepared

    def plan(self, now: float, matched: Iterable[K]) -> Plan:
        """Decide the routes of the next messages; ``matched`` are the keys of the main topic's
        matched subscriptions (legacy ones included). Timed transitions happen here."""
        channel, withheld, gone = [], [], set()
        recheck_at, periodic = now + RECHECK_SECONDS, True
        for key, route in self.routes.items():
            route.tick(now)
            if route.on_channel:
                channel.append(key)
                if route.withheld and not self.main_always:
                    # (a TRANSIENT_LOCAL DataWriter that keeps samples from a reader makes
                    # Fast DDS 2.14 report some of them as lost to it, once its KEEP_LAST
                    # history moves on: those readers get the copies, and drop them uncopied)
                    withheld.append(key)
            elif route.state is RouteState.GONE:
                gone.add(key)
                withheld.append(key)  # its reader may be matched until DDS's lease ends
            at = route.next_tick(now)
            if at is not None and at < recheck_at:
                recheck_at, periodic = at, False
        skipped = gone.union(channel)
        main_served = tuple(key for key in matched if key not in skipped)
        return Plan(tuple(channel), bool(main_served) or self.main_always, tuple(withheld),
                    main_served, recheck_at, periodic)

    def main_written(self, keys: Iterable[K], timestamp: int) -> bool:
        """The main topic carried message ``timestamp`` for these subscriptions (those its plan
        served by the main topic). True when a route changed state: plan again."""
        changed = False
        for key in keys:
            route = self.routes.get(key)
            if route is None:
                self._last_main[key] = timestamp
            else:
                changed |= route.main_written(timestamp)
        return changed


# --- subscription side -----------------------------------------------------------------------

class StreamState(enum.Enum):
    """How a subscription receives one publisher (see the module's diagram)."""

    MAIN = 'main'          #: main topic only
    WAITING = 'waiting'    #: fenced: channel messages wait for the fenced main-topic message
    CHANNEL = 'channel'    #: on the channel: main-topic copies from the switch on are duplicates


class Verdict(enum.Enum):
    """What to do with one arriving copy of a message."""

    DELIVER = 'deliver'
    DUPLICATE = 'duplicate'  #: delivered already, or to be from the other route: dropped
    QUEUED = 'queued'        #: kept until its stream's fence passes (see :meth:`Stream.release`)


T = TypeVar('T')


@dataclass
class Stream(Generic[T]):
    """One publisher's messages as a subscription delivers them."""

    #: RELIABLE subscriptions wait for a fenced message; BEST_EFFORT ones may lose it anyway.
    reliable: bool = True
    state: StreamState = StreamState.MAIN
    #: Source timestamp of the last delivered message: older copies are late or duplicates.
    last: int = 0
    #: From the fence: main-topic messages up to ``fence`` come before channel messages, and
    #: main-topic copies from ``switch`` on duplicate channel messages.
    fence: int = 0
    switch: Optional[int] = None
    #: The fence said its message reached our reader (:attr:`Fence.delivered`).
    fence_delivered: bool = False
    waiting: Deque[Tuple[int, T]] = field(default_factory=collections.deque)
    waiting_since: float = 0.0
    timeouts: int = 0
    #: Fenced messages known lost (a newer main-topic copy came first).
    lost_fenced: int = 0
    #: The channel went away while messages were queued (see :meth:`channel_lost`).
    lost: bool = False

    def duplicate(self, timestamp: int) -> bool:
        """Whether a main-topic copy with this timestamp would be dropped (asked before taking
        it, so a duplicate is discarded without copying its payload)."""
        return timestamp <= self.last or (self.switch is not None and timestamp >= self.switch)

    def main(self, timestamp: int) -> Verdict:
        """A main-topic copy arrived."""
        if self.duplicate(timestamp):
            self.passed_by(timestamp)
            return Verdict.DUPLICATE
        self.last = timestamp
        return Verdict.DELIVER

    def passed_by(self, timestamp: int) -> None:
        """A main-topic copy of message ``timestamp`` arrived (delivered or dropped). A RELIABLE
        reader gets one writer's samples in order, so once a copy newer than the fenced message
        came, the fenced one will not come any more (DDS lost it, for example to a startup
        race): the channel's messages need not wait for it."""
        if (self.state is StreamState.WAITING and self.last < self.fence < timestamp):
            self.fence = 0
            self.lost_fenced += 1

    def fenced(self, timestamp: int, fence: Fence, now: float) -> None:
        """The publisher switched us to its channel from message ``timestamp`` on."""
        self.switch, self.fence = timestamp, fence.last_main
        self.fence_delivered = fence.delivered
        self._enter_waiting_or_channel(now)

    def channel(self, timestamp: int, item: T, now: float) -> Verdict:
        """A channel copy arrived (``item`` is queued while the stream waits for its fence)."""
        if timestamp <= self.last:
            return Verdict.DUPLICATE
        if self.switch is None:  # no fence: channel messages are newer than main's
            self.switch = timestamp
            self._enter_waiting_or_channel(now)
        if self.state is StreamState.WAITING:
            self.waiting.append((timestamp, item))
            return Verdict.QUEUED
        self.last = timestamp
        return Verdict.DELIVER

    def channel_steady(self, timestamp: int) -> bool:
        """:meth:`channel`'s common case alone: a newer copy on the channel that the stream
        is on (CHANNEL, nothing queued) is recorded, and True says to deliver it. False, with
        nothing changed, for anything else: ask :meth:`channel`."""
        if self.state is StreamState.CHANNEL and timestamp > self.last and \
                self.switch is not None and not self.waiting:
            self.last = timestamp
            return True
        return False

    def release(self, now: float, main_drained: bool = True) -> Optional[T]:
        """The next queued channel message that may be delivered now, or None. Ends WAITING once
        the fenced message was delivered; at once when the main topic has nothing left to take
        and the fence said its message had reached our reader (it was lost there: counted);
        else once ``FENCE_TIMEOUT_SECONDS`` passed while the main topic had nothing left to take
        (it was lost on the way: counted). A subscription that was slow to take never loses a
        message that is there."""
        if self.state is StreamState.WAITING:
            if self.last < self.fence:
                if not main_drained:
                    return None
                if self.fence_delivered:
                    self.lost_fenced += 1  # overwritten in our reader's history, or never ours
                elif now - self.waiting_since < FENCE_TIMEOUT_SECONDS:
                    return None
                else:
                    self.timeouts += 1  # the fenced message was lost on the way
            self.state = StreamState.CHANNEL
        while self.waiting:
            timestamp, item = self.waiting.popleft()
            if timestamp > self.last:
                self.last = timestamp
                return item
        if self.lost:
            self.lost = False
            self.state, self.switch, self.fence = StreamState.MAIN, None, 0
        return None

    @property
    def holding(self) -> bool:
        """Channel messages are queued here."""
        return bool(self.waiting)

    def wait_deadline(self) -> Optional[float]:
        """When a WAITING stream stops waiting for its fenced message."""
        if self.state is StreamState.WAITING:
            return self.waiting_since + FENCE_TIMEOUT_SECONDS
        return None

    def channel_lost(self) -> None:
        """The publisher's channel went away: its next messages come on the main topic. Channel
        messages queued here are delivered first, after their fenced message as before; the
        stream returns to the main topic once they are out (see :meth:`release`)."""
        if self.waiting:
            self.lost = True
        else:
            self.state, self.switch, self.fence = StreamState.MAIN, None, 0

    def _enter_waiting_or_channel(self, now: float) -> None:
        if self.reliable and self.fence > self.last:
            if self.state is not StreamState.WAITING:
                self.state, self.waiting_since = StreamState.WAITING, now
        elif self.state is not StreamState.WAITING:
            self.state = StreamState.CHANNEL


class StreamTable(Generic[T]):
    """The streams of one subscription, by publisher key (its GID)."""

    def __init__(self, *, reliable: bool = True) -> None:
        self.reliable = reliable
        self.streams: Dict[Hashable, Stream[T]] = {}
        self._ended = [0, 0]  # fence counts of the streams popped

    def __getitem__(self, key: Hashable) -> Stream[T]:
        stream = self.streams.get(key)
        if stream is None:
            stream = self.streams[key] = Stream(reliable=self.reliable)
        return stream

    @property
    def any_holding(self) -> bool:
        """Some stream holds queued channel messages."""
        return any(s.holding for s in self.streams.values())

    @property
    def any_switched(self) -> bool:
        """Some publisher serves us on its channel: its main-topic copies may be duplicates."""
        return any(s.switch is not None for s in self.streams.values())

    def next_deadline(self) -> Optional[float]:
        deadlines = [d for s in self.streams.values() if (d := s.wait_deadline()) is not None]
        return min(deadlines) if deadlines else None

    def pop(self, key: Hashable) -> Optional[Stream[T]]:
        stream = self.streams.pop(key, None)
        if stream is not None:
            self._ended[0] += stream.timeouts
            self._ended[1] += stream.lost_fenced
        return stream

    def waiting(self) -> int:
        """Streams waiting now for a fenced message (their channel messages queued)."""
        return sum(s.state is StreamState.WAITING for s in self.streams.values())

    def fence_counts(self) -> Tuple[int, int]:
        """Fenced messages given up after FENCE_TIMEOUT_SECONDS, and known lost, so far."""
        return (self._ended[0] + sum(s.timeouts for s in self.streams.values()),
                self._ended[1] + sum(s.lost_fenced for s in self.streams.values()))


class Incoming(enum.Enum):
    """What a subscription made of a sample it took from a channel (see ReceiveView.classify)."""

    DATA = 'data'        #: a message of the publisher
    FENCE = 'fence'      #: a route fence (:class:`Fence`)
    CONTROL = 'control'  #: a probe, or a sample rejected and counted: nothing to deliver


class Outcome(enum.Enum):
    """What one step of :meth:`Receiver.step` did."""

    DELIVER = 'deliver'      #: a message to hand to the callback (``Step.sample``)
    QUEUED = 'queued'        #: a channel message kept until its stream's fence opens
    DUPLICATE = 'duplicate'  #: a copy delivered already, or to be from the other route: dropped
    FENCE = 'fence'          #: a route fence: its stream may wait for a main-topic message
    CONTROL = 'control'      #: a probe or a rejected channel sample
    DISCARDED = 'discarded'  #: a main-topic duplicate dropped before it was taken (uncopied)


#: A channel message's verdict as a step's outcome.
_OUTCOME_OF = {Verdict.DELIVER: Outcome.DELIVER, Verdict.DUPLICATE: Outcome.DUPLICATE,
               Verdict.QUEUED: Outcome.QUEUED}

C = TypeVar('C')


class Step(NamedTuple, Generic[C, T]):
    """One step of a subscription's take order: what was taken, from where, and its outcome."""

    outcome: Outcome
    sample: Optional[T] = None
    #: The channel it came from; None for the main topic.
    channel: Optional[C] = None
    #: A queued channel message released now (its fence passed, or was given up).
    released: bool = False


class ReceiveView(Protocol[C, T]):
    """What :class:`Receiver` asks of a subscription's DDS readers: its channels (one per
    publisher that serves it) and its main-topic reader, shared by every publisher."""

    def channels(self) -> Sequence[C]:
        """The channel readers, in a stable order."""

    def channel_key(self, channel: C) -> Hashable:
        """The publisher whose channel it is (its stream's key)."""

    def take_channel(self, channel: C) -> Optional[T]:
        """The channel's next sample, taken; None when it has none."""

    def classify(self, channel: C, sample: T) -> Tuple[Incoming, Optional[Fence]]:
        """What a channel sample is (the fence when it is one); rejections are the view's to
        count and log."""

    def timestamp(self, sample: T) -> int:
        """A sample's source timestamp (its publisher's message number)."""

    def channels_drained(self) -> None:
        """Every channel was empty: the view may retire those of departed publishers."""

    def peek_main(self) -> Optional[Tuple[Hashable, int]]:
        """(publisher, timestamp) of the main reader's next sample, left untaken; None when
        it has none."""

    def discard_main(self) -> None:
        """Drop the main reader's next sample without copying its payload."""

    def take_main(self, publisher: Optional[Hashable]) -> Optional[T]:
        """Take the main reader's next sample (``publisher``: its publisher when just peeked,
        else None); None when it has none."""

    def main_key(self, sample: T) -> Hashable:
        """The publisher of a main-topic sample."""


class Receiver(Generic[C, T]):
    """A subscription's take order over its routes, one :meth:`step` at a time: channels first,
    in rotation (a stream's queued messages released as its fence allows, else the channel's
    next sample), then the main topic, whose copies of channel messages are dropped untaken.

    Channels go first because a channel message never waits on the main topic except behind a
    fence, and a fence's main-topic message is taken by the same loop once the channels are
    empty. The endpoint counts and decodes what the steps give; the route simulation
    (``test/test_route_simulation.py``) drives the same steps over simulated readers.
    """

    def __init__(self, streams: StreamTable[T]) -> None:
        self.streams = streams
        self._next_channel = 0

    def step(self, view: 'ReceiveView[C, T]', now: float) -> Optional[Step[C, T]]:
        """The next step, or None when nothing is left to take."""
        found = self._from_channels(view, now)
        return found if found is not None else self._from_main(view)

    def _from_channels(self, view: 'ReceiveView[C, T]', now: float) -> Optional[Step[C, T]]:
        channels = view.channels()
        count = len(channels)
        main_drained = None
        for i in range(count):
            channel = channels[(self._next_channel + i) % count]
            stream = self.streams[view.channel_key(channel)]
            found = None
            if stream.holding:
                if main_drained is None:  # a fence may time out only if nothing can come
                    main_drained = view.peek_main() is None
                released = stream.release(now, main_drained)
                if released is not None:
                    found = Step(Outcome.DELIVER, released, channel, released=True)
            if found is None:
                sample = view.take_channel(channel)
                if sample is None:
                    continue
                found = self.channel_step(view, channel, stream, sample, now)
            self._next_channel = (self._next_channel + i + 1) % count
            return found
        view.channels_drained()
        return None

    def only_channel_next(self, key: Hashable) -> Optional[Stream[T]]:
        """For a subscription whose one channel is ``key``'s: that channel's stream when the
        take order's next step is the channel's next sample (its stream holds nothing back, and
        the rotation starts at it, as :meth:`step` leaves it with one channel), else None (ask
        :meth:`step`). The caller then takes the sample and hands it to :meth:`channel_step`
        (a subscription's steady delivery)."""
        if self._next_channel:
            return None
        stream = self.streams.streams.get(key)
        return stream if stream is not None and not stream.holding else None

    @staticmethod
    def channel_step(view: 'ReceiveView[C, T]', channel: C, stream: Stream[T], sample: T,
                     now: float, data: bool = False) -> Step[C, T]:
        """The step of a sample taken from ``channel``, whose stream is ``stream``. ``data``:
        the caller already classified it as :attr:`Incoming.DATA` (``view.classify`` would)."""
        if not data:
            kind, fence = view.classify(channel, sample)
            if kind is Incoming.FENCE:
                stream.fenced(view.timestamp(sample), fence, now)
                return Step(Outcome.FENCE, sample, channel)
            if kind is Incoming.CONTROL:
                return Step(Outcome.CONTROL, sample, channel)
        verdict = stream.channel(view.timestamp(sample), sample, now)
        # (identity first: an Enum's hash is Python code, and most messages are delivered)
        return Step(Outcome.DELIVER if verdict is Verdict.DELIVER else _OUTCOME_OF[verdict],
                    sample, channel)

    def _from_main(self, view: 'ReceiveView[C, T]') -> Optional[Step[C, T]]:
        publisher = None
        if self.streams.any_switched:
            peeked = view.peek_main()
            if peeked is None:
                return None
            publisher, timestamp = peeked
            stream = self.streams.streams.get(publisher)
            if stream is not None and stream.duplicate(timestamp):
                stream.passed_by(timestamp)
                view.discard_main()
                return Step(Outcome.DISCARDED)
        sample = view.take_main(publisher)
        if sample is None:
            return None
        if self.streams[view.main_key(sample)].main(view.timestamp(sample)) is \
                Verdict.DUPLICATE:
            return Step(Outcome.DUPLICATE, sample)
        return Step(Outcome.DELIVER, sample)
