"""The route protocol (rosidl_buffer_py.routes and .control), without DDS: every transition of
both state machines from a table, then a model-based test of the invariants over random
interleavings of publishes, matches, acknowledgments, losses, slow and dead subscribers."""
import collections
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from rosidl_buffer_py import control
from rosidl_buffer_py.routes import (
    CHANNEL_SETTLE_SECONDS, CONFIRM_INTERVAL_SECONDS, FENCE_DEFER_SECONDS, FENCE_TIMEOUT_SECONDS,
    PROBE_INTERVAL_SECONDS, RECHECK_SECONDS, Dispatch, Fence, Incoming, Outcome, Receiver,
    Route, RouteState, RouteTable, Step, Stream, StreamState, StreamTable, Verdict)

S = RouteState


def _route(state: RouteState, *, handshake=True, last_main=None, acknowledged_after=0,
           probed_at=None, matched_since=0.0, acknowledged_probes=False) -> Route:
    return Route(handshake=handshake, first_probes=6, state=state, last_main=last_main,
                 acknowledged_after=acknowledged_after, probed_at=probed_at,
                 matched_since=matched_since, acknowledged_probes=acknowledged_probes)


# (start state, route arguments, event, event arguments) -> end state
ROUTE_TRANSITIONS = [
    (S.UNMATCHED, {}, 'channel_matched', (True, 1.0), S.PROBING),
    (S.UNMATCHED, {'handshake': False}, 'channel_matched', (True, 1.0), S.SETTLING),
    (S.UNMATCHED, {}, 'channel_matched', (False, 1.0), S.UNMATCHED),
    (S.PROBING, {'probed_at': 0.0}, 'channel_matched', (False, 1.0), S.UNMATCHED),
    (S.SETTLING, {}, 'channel_matched', (False, 1.0), S.UNMATCHED),
    (S.ACKNOWLEDGED, {}, 'channel_matched', (False, 1.0), S.UNMATCHED),
    (S.FENCING, {}, 'channel_matched', (False, 1.0), S.UNMATCHED),
    (S.SERVING, {}, 'channel_matched', (False, 1.0), S.UNMATCHED),
    (S.CONFIRMED, {}, 'channel_matched', (False, 1.0), S.UNMATCHED),
    (S.SERVING, {}, 'channel_matched', (True, 1.0), S.SERVING),  # stays while matched
    (S.PROBING, {'probed_at': 0.0}, 'acknowledged', (5,), S.FENCING),  # no main message yet
    (S.PROBING, {'probed_at': 0.0, 'last_main': 3}, 'acknowledged', (5,), S.ACKNOWLEDGED),
    (S.SETTLING, {}, 'acknowledged', (5,), S.SETTLING),
    (S.SERVING, {}, 'acknowledged', (5,), S.CONFIRMED),
    (S.SERVING, {'handshake': False}, 'acknowledged', (5,), S.SERVING),
    (S.ACKNOWLEDGED, {'acknowledged_after': 5}, 'main_written', (6,), S.FENCING),
    (S.ACKNOWLEDGED, {'acknowledged_after': 5}, 'main_written', (5,), S.ACKNOWLEDGED),
    (S.PROBING, {}, 'tick', (CHANNEL_SETTLE_SECONDS,), S.FENCING),
    (S.PROBING, {}, 'tick', (CHANNEL_SETTLE_SECONDS / 2,), S.PROBING),
    (S.SETTLING, {}, 'tick', (CHANNEL_SETTLE_SECONDS,), S.FENCING),
    (S.ACKNOWLEDGED, {}, 'tick', (CHANNEL_SETTLE_SECONDS,), S.FENCING),
    (S.SERVING, {}, 'tick', (10.0,), S.SERVING),
    (S.FENCING, {}, 'take_fence', (), S.SERVING),  # settled by time alone
    (S.FENCING, {'acknowledged_probes': True}, 'take_fence', (), S.CONFIRMED),
    (S.SERVING, {}, 'take_fence', (), S.SERVING),
    *[(state, {}, 'gone', (), S.GONE) for state in RouteState],
    (S.GONE, {}, 'channel_matched', (True, 1.0), S.GONE),
    (S.GONE, {}, 'main_written', (9,), S.GONE),
    (S.FENCING, {}, 'main_written', (9,), S.FENCING),  # a plan made before: noted, see below
]


@pytest.mark.parametrize('start, kwargs, event, args, end', ROUTE_TRANSITIONS,
                         ids=[f'{t[0].value}-{t[2]}{t[3]}-{t[4].value}'
                              for t in ROUTE_TRANSITIONS])
def test_route_transition(start, kwargs, event, args, end):
    route = _route(start, **kwargs)
    getattr(route, event)(*args)
    assert route.state is end


def test_route_decisions_per_state():
    """Which routes a state implies: the main topic until the channel serves, withholding only
    once the channel's samples were acknowledged, nothing at all once gone."""
    for state in RouteState:
        route = _route(state)
        assert route.on_channel == (state in (S.FENCING, S.SERVING, S.CONFIRMED)), state
        assert route.needs_main == (state in (S.UNMATCHED, S.PROBING, S.SETTLING,
                                              S.ACKNOWLEDGED)), state
        assert route.withheld == (state is S.CONFIRMED), state
    # acknowledged probes: the fenced message's main-topic copy is kept away too (it raced the
    # channel copy, and a demo subscription got a played frame as CPU bytes)
    assert _route(S.FENCING, acknowledged_probes=True).withheld


def test_probes_first_a_history_then_one_per_interval():
    route = _route(S.PROBING)
    assert route.probes_due(1.0) == 6 and route.awaits_acknowledgment
    assert route.probes_due(1.0 + PROBE_INTERVAL_SECONDS / 2) == 0
    assert route.probes_due(1.0 + PROBE_INTERVAL_SECONDS) == 1
    assert _route(S.SETTLING).probes_due(1.0) == 0
    assert not _route(S.PROBING).awaits_acknowledgment  # nothing written: nothing to ask


def test_the_fence_names_the_last_main_topic_message_then_the_route_serves():
    route = _route(S.PROBING, probed_at=0.0)
    route.main_written(7)
    route.acknowledged(7)
    assert route.state is S.ACKNOWLEDGED  # message 7 may be gone from the history: one more
    route.main_written(8)
    assert route.take_fence() == Fence(8) and route.state is S.CONFIRMED  # probes acknowledged
    assert route.take_fence() is None


def test_the_fence_names_a_main_topic_message_sent_by_a_plan_made_before_fencing():
    """A cached plan may still route by the main topic after the route became FENCING: those
    messages went to the subscription on the main topic, so the fence names the last of them
    (it once named an older one, and the subscription dropped them as late)."""
    route = _route(S.FENCING, last_main=9)
    assert route.main_written(10) is False and route.main_written(11) is False
    assert route.take_fence() == Fence(11)


def test_a_route_that_lost_its_channel_after_its_fence_settles_without_probes():
    route = _route(S.SERVING)
    route.channel_matched(False, 1.0)
    route.channel_matched(True, 2.0)
    assert route.state is S.SETTLING and route.probes_due(2.0) == 0


def test_next_tick_names_each_timed_transition():
    assert _route(S.SETTLING, matched_since=1.0).next_tick(1.0) == 1.0 + CHANNEL_SETTLE_SECONDS
    assert _route(S.PROBING, matched_since=1.0).next_tick(1.0) == 1.0  # probes are due now
    assert _route(S.PROBING, matched_since=1.0, probed_at=1.0).next_tick(1.0) == \
        1.0 + PROBE_INTERVAL_SECONDS
    assert _route(S.SERVING).next_tick(1.0) == 1.0 + CONFIRM_INTERVAL_SECONDS
    assert _route(S.SERVING, handshake=False).next_tick(1.0) is None
    assert _route(S.CONFIRMED).next_tick(1.0) is None and _route(S.GONE).next_tick(1.0) is None


def test_table_plans_main_topic_for_legacy_and_unserved_subscriptions():
    table = RouteTable()
    route = table.add('a', handshake=True, depth=5)
    table.main_written(['a', 'legacy', 'later'], 3)  # 'later' is not a known peer yet
    assert route.last_main == 3
    assert table.add('later', handshake=False).last_main == 3
    plan = table.plan(0.0, ['a', 'legacy'])
    assert plan.channel == () and plan.main and set(plan.main_served) == {'a', 'legacy'}
    route.state, route.acknowledged_probes = S.FENCING, True  # the fence goes with this one
    plan = table.plan(0.0, ['a', 'legacy'])
    assert plan.channel == ('a',) and plan.withheld == ('a',) and plan.main_served == ('legacy',)
    route.state = S.CONFIRMED
    plan = table.plan(0.0, ['a', 'legacy'])
    assert plan.channel == ('a',) and plan.withheld == ('a',) and plan.main_served == ('legacy',)
    assert not table.plan(0.0, ['a']).main
    durable = RouteTable(main_always=True)  # TRANSIENT_LOCAL: the main topic keeps history
    durable.add('a', handshake=True, depth=5).state = S.CONFIRMED
    plan = durable.plan(0.0, ['a'])
    assert plan.main and plan.channel == ('a',) and plan.withheld == ()  # see RouteTable.plan
    table.routes['a'].gone()
    plan = table.plan(0.0, ['a'])  # DDS still matches it: nothing is written to it anyway
    assert plan.channel == () and not plan.main and plan.withheld == ('a',)


def test_deep_or_unbounded_histories_settle_instead_of_probing():
    table = RouteTable()
    assert table.add('deep', handshake=True, depth=101).handshake is False
    assert table.add('all', handshake=True, depth=0).handshake is False
    assert table.add('five', handshake=True, depth=5).first_probes == 6


@dataclass
class FakeView:
    """A RouteView with answers set by the test (what DDS would say)."""

    channels: Dict[str, bool] = field(default_factory=dict)
    acknowledged: Dict[str, bool] = field(default_factory=dict)
    matched: List[str] = field(default_factory=list)
    main_acked: bool = True
    asked: List[str] = field(default_factory=list)
    #: what settled() answers (the publisher's view: no discovery since its last reading)
    calm: bool = True

    def signature(self, fresh=False):
        self.asked.append('fresh signature' if fresh else 'signature')
        return (tuple(self.matched), tuple(sorted(self.channels.items())))

    def settled(self, now):
        self.asked.append('settled')
        return self.calm

    def matched_subscriptions(self):
        self.asked.append('matched')
        return list(self.matched)

    def channel_matched(self, key):
        return self.channels.get(key, False)

    def channel_acknowledged(self, key):
        return self.acknowledged.get(key, False)

    def main_acknowledged(self):
        self.asked.append('main_acknowledged')
        return self.main_acked


def test_dispatch_brings_a_route_up_in_the_order_the_publisher_writes():
    """Probes first, the main topic until the channel is acknowledged, then the fence with the
    message on the channel, the main-topic sample kept from the subscription from then on."""
    table, view = RouteTable(), FakeView(matched=['a'])
    table.add('a', handshake=True, depth=2)
    first = table.dispatch(0.0, 1, view)
    assert first.probes == () and first.channel == () and first.main and first.withheld == ()
    view.channels['a'] = True  # the signature changes: planned again
    second = table.dispatch(0.001, 2, view)
    assert second.probes == (('a', 3),) and second.timer is True and second.main
    view.acknowledged['a'] = True
    third = table.dispatch(0.002, 3, view)  # cached plan: the acknowledgment is not asked yet
    assert third.channel == () and third.main and table.routes['a'].state is S.PROBING
    fourth = table.dispatch(0.002 + PROBE_INTERVAL_SECONDS, 4, view)  # recheck: acknowledged,
    assert fourth.main and table.routes['a'].state is S.FENCING  # fenced after this message
    fifth = table.dispatch(0.02, 5, view)
    assert fifth.channel == (('a', Fence(4, delivered=True)),)
    assert fifth.withheld == ('a',) and not fifth.main  # no other reader: no main-topic write
    assert table.routes['a'].state is S.CONFIRMED and table.last_published == 5
    sixth = table.dispatch(0.03, 6, view)
    assert sixth.channel == (('a', None),) and not sixth.main and sixth.probes == ()


def test_dispatch_uses_its_cached_plan_until_the_signature_or_recheck_time_changes():
    table, view = RouteTable(), FakeView(matched=['legacy'])
    table.dispatch(0.0, 1, view)
    view.asked.clear()
    table.dispatch(0.1, 2, view)
    assert view.asked == ['signature']  # no GID list asked for: the plan holds
    view.matched.append('other')
    table.dispatch(0.2, 3, view)
    assert 'matched' in view.asked
    view.asked.clear()
    table.invalidate()  # a subscription changed in a way the counts do not show
    table.dispatch(0.3, 4, view)
    assert 'matched' in view.asked


def test_a_steady_plan_serves_every_message_with_one_dispatch_until_a_transition():
    """Routes served on their channels, no fence due and no main-topic write: every message
    under that plan goes the same way, and the table answers with the same Dispatch (no
    per-route work per message); a transition plans again."""
    table, view = RouteTable(), FakeView(matched=['a'], channels={'a': True})
    route = table.add('a', handshake=False, depth=0)
    route.state = S.SERVING
    first = table.dispatch(0.0, 1, view)
    second = table.dispatch(0.01, 2, view)
    assert second is table.dispatch(0.02, 3, view)
    assert first == Dispatch((), (('a', None),), False, (), False)  # (the timer stops)
    assert second == Dispatch((), (('a', None),), False, (), None)
    assert table.last_published == 3
    table.gone('a')
    assert table.dispatch(0.03, 4, view).channel == ()
    # a due fence or a main-topic write is never served by a steady dispatch
    table, view = RouteTable(), FakeView(matched=['a', 'legacy'], channels={'a': True})
    table.add('a', handshake=False, depth=0).state = S.SERVING
    mixed = [table.dispatch(0.01 * i, i, view) for i in range(1, 4)]
    assert all(d.main and d.channel == (('a', None),) for d in mixed)
    assert table._last_main['legacy'] == 3  # the main topic's bookkeeping ran per message
    table, view = RouteTable(), FakeView(matched=['a'], channels={'a': True})
    route = table.add('a', handshake=True, depth=2)
    route.state, route.acknowledged_probes, route.last_main = S.FENCING, True, 1
    fenced = table.dispatch(0.0, 2, view)
    assert fenced.channel == (('a', Fence(1, delivered=True)),)
    assert table.dispatch(0.01, 3, view).channel == (('a', None),)


def _steady_table():
    table, view = RouteTable(), FakeView(matched=['a'], channels={'a': True})
    table.add('a', handshake=False, depth=0).state = S.SERVING
    table.dispatch(0.0, 1, view)
    return table, view


def test_a_replan_that_gives_the_same_steady_answer_keeps_it_and_a_transition_drops_it():
    """``RouteTable.steady`` is the cached plan's steady dispatch, the same object across the
    rechecks that re-plan to the same answer (a publisher's prepared writes serve on); any
    transition drops it, and a new plan makes a new one."""
    table, view = _steady_table()
    steady = table.steady
    assert steady == Dispatch((), (('a', None),), False, (), None)
    assert table.steady_until == RECHECK_SECONDS
    view.asked.clear()
    table.dispatch(RECHECK_SECONDS, 2, view)  # re-planned (this one stops the route timer)
    assert 'fresh signature' in view.asked  # a re-plan reads DDS, not the view's memory
    assert table.steady is steady and table.steady_until == 2 * RECHECK_SECONDS
    assert table.dispatch(RECHECK_SECONDS + 0.1, 3, view) is steady
    table.invalidate()
    assert table.steady is None
    table.dispatch(1.0, 3, view)
    assert table.steady == steady and table.steady is not steady  # prepared writes go
    for transition in (RouteTable.invalidate, lambda t: t.gone('a'), lambda t: t.remove('a'),
                       lambda t: t.add('b', handshake=False)):
        table, view = _steady_table()
        transition(table)
        assert table.steady is None
    table, view = _steady_table()
    view.matched.append('legacy')  # a main-topic write per message: no steady answer
    table.dispatch(0.1, 2, view)
    assert table.steady is None


def test_dispatch_prepared_answers_the_prepared_object_while_the_steady_dispatch_holds():
    """What a publisher that prepared its writes for ``steady`` asks instead of dispatch():
    that very object, without a re-plan or a signature, while it is the table's steady answer,
    before its recheck time, with the view settled; what dispatch() answers otherwise, which is
    ``steady`` again when the view's reading or the re-plan finds nothing changed."""
    table, view = _steady_table()
    steady = table.steady
    view.asked.clear()
    assert table.dispatch_prepared(steady, 0.1, 2, view) is steady
    assert table.last_published == 2 and view.asked == ['settled']
    other = Dispatch(*steady)  # equal, not it: dispatch() answers, with the table's object
    assert table.dispatch_prepared(other, 0.1, 3, view) is steady
    view.calm, view.asked = False, []
    assert table.dispatch_prepared(steady, 0.1, 4, view) is steady  # the view read, same counts
    assert view.asked == ['settled', 'signature'] and table.last_published == 4
    view.calm, view.asked = True, []
    # past the periodic recheck: still the prepared answer, the re-plan due after its writes
    assert not table.replan_due
    assert table.dispatch_prepared(steady, RECHECK_SECONDS, 5, view) is steady
    assert view.asked == ['settled'] and table.replan_due and table.last_published == 5
    assert table.advance(RECHECK_SECONDS, view) == ((), False)  # what the publisher does then
    assert 'fresh signature' in view.asked and table.steady_until == 2 * RECHECK_SECONDS
    assert table.steady is steady and not table.replan_due
    view.matched.append('legacy')  # found by the next re-plan: a main-topic write per message
    assert table.dispatch_prepared(steady, 2 * RECHECK_SECONDS, 6, view) is steady
    table.advance(2 * RECHECK_SECONDS, view)
    assert table.steady is None
    moved = table.dispatch_prepared(steady, 2 * RECHECK_SECONDS + 0.1, 7, view)
    assert moved is not steady and moved.main and moved.channel == (('a', None),)
    assert table.last_published == 7 and not table.replan_due
    table, view = _steady_table()
    steady = table.steady
    table.gone('a')
    gone = table.dispatch_prepared(steady, 0.2, 3, view)
    assert gone is not steady and gone.channel == () and table.last_published == 3


def test_a_timed_transition_due_is_planned_before_the_message_not_after():
    """Only the periodic recheck waits for the message's writes: a plan whose recheck is a
    route's timed transition is planned again before the message, by dispatch()."""
    table, view = _steady_table()
    steady = table.steady
    table.routes['a'].next_tick = lambda now: now + 0.2  # (a transition, as a fence's)
    table.invalidate()
    assert table.dispatch(0.0, 2, view) is not steady
    steady = table.steady
    assert steady is not None and table.steady_until == 0.2 and not table._cached.plan.periodic
    view.asked.clear()
    table.dispatch_prepared(steady, 0.2, 3, view)
    assert 'fresh signature' in view.asked and not table.replan_due


def test_a_replan_to_the_steady_answer_is_that_object_unless_it_writes_probes_or_needs_the_timer():
    """dispatch() after a re-plan answers the steady object itself (the publisher's prepared
    writes serve) only when the re-plan asks for nothing more: no probes, no route timer."""
    table, view = _steady_table()
    steady = table.steady
    assert table.dispatch(RECHECK_SECONDS, 2, view) is steady
    table.routes['a'].tick = lambda now: None
    table.routes['a'].next_tick = lambda now: now + 0.01  # some route wants the timer
    replanned = table.dispatch(2 * RECHECK_SECONDS, 3, view)
    assert replanned == steady._replace(timer=True) and replanned is not steady


def test_a_due_fence_waits_for_the_main_topics_acknowledgment_then_names_the_last_message():
    """Written while the main topic's readers had not acknowledged the fenced message, a fence
    could not tell the subscription whether that message was lost: the main topic serves the
    subscription meanwhile, for at most FENCE_DEFER_SECONDS."""
    table, view = RouteTable(), FakeView(matched=['a'], channels={'a': True}, main_acked=False)
    route = table.add('a', handshake=True, depth=2)
    route.state, route.acknowledged_probes, route.last_main = S.FENCING, True, 1
    deferred = table.dispatch(1.0, 2, view)
    assert deferred.channel == () and deferred.main and deferred.withheld == ()
    assert route.state is S.FENCING and route.last_main == 2
    view.main_acked = True
    fenced = table.dispatch(1.01, 3, view)
    assert fenced.channel == (('a', Fence(2, delivered=True)),) and fenced.withheld == ('a',)
    # never acknowledged (a reader that stopped answering): the fence goes out unconfirmed
    table, view = RouteTable(), FakeView(matched=['a'], channels={'a': True}, main_acked=False)
    route = table.add('a', handshake=False, depth=0)
    route.state, route.last_main = S.FENCING, 1
    assert table.dispatch(1.0, 2, view).channel == ()
    assert table.dispatch(1.0 + FENCE_DEFER_SECONDS / 2, 3, view).channel == ()
    late = table.dispatch(1.0 + FENCE_DEFER_SECONDS, 4, view)
    assert late.channel == (('a', Fence(3, delivered=False)),) and not late.main
    assert route.state is S.SERVING


def test_gone_and_removed_routes_are_planned_again_at_once():
    table, view = RouteTable(), FakeView(matched=['a'], channels={'a': True})
    route = table.add('a', handshake=False, depth=0)
    route.state = S.SERVING
    assert table.dispatch(0.0, 1, view).channel == (('a', None),)
    table.gone('a')
    after = table.dispatch(0.0, 2, view)
    assert after.channel == () and after.withheld == ('a',) and not after.main
    table.remove('a')
    assert table.dispatch(0.0, 3, view).main  # planned again: an unknown matched reader


# --- the stream -------------------------------------------------------------------------------

def test_stream_main_topic_only_delivers_in_order_once():
    stream = Stream()
    assert [stream.main(t) for t in (1, 2, 2, 1, 3)] == [
        Verdict.DELIVER, Verdict.DELIVER, Verdict.DUPLICATE, Verdict.DUPLICATE, Verdict.DELIVER]


def test_stream_fence_holds_channel_messages_until_the_fenced_message():
    stream = Stream()
    stream.main(1)
    stream.fenced(3, Fence(2), now=0.0)
    assert stream.state is StreamState.WAITING
    assert stream.channel(3, 'm3', now=0.0) is Verdict.QUEUED
    assert stream.release(0.1) is None
    assert stream.main(2) is Verdict.DELIVER
    assert stream.main(3) is Verdict.DUPLICATE  # from the switch on: the channel's
    assert stream.release(0.1) == 'm3' and stream.state is StreamState.CHANNEL
    assert stream.channel(4, 'm4', now=0.2) is Verdict.DELIVER


def test_stream_fence_without_a_missing_message_switches_at_once():
    stream = Stream()
    stream.main(5)
    stream.fenced(6, Fence(5), now=0.0)
    assert stream.state is StreamState.CHANNEL
    assert stream.channel(6, 'm6', now=0.0) is Verdict.DELIVER


def test_stream_fence_timeout_counts_the_lost_message():
    stream = Stream()
    stream.fenced(3, Fence(2), now=0.0)
    stream.channel(3, 'm3', now=0.0)
    assert stream.wait_deadline() == FENCE_TIMEOUT_SECONDS
    assert stream.release(FENCE_TIMEOUT_SECONDS - 0.01) is None
    assert stream.release(FENCE_TIMEOUT_SECONDS) == 'm3' and stream.timeouts == 1


def test_stream_fence_never_times_out_while_the_main_topic_has_samples_to_take():
    stream = Stream()
    stream.fenced(3, Fence(2), now=0.0)
    stream.channel(3, 'm3', now=0.0)
    assert stream.release(5.0, main_drained=False) is None and stream.timeouts == 0
    assert stream.main(2) is Verdict.DELIVER and stream.release(5.0) == 'm3'


def test_a_channel_lost_with_queued_messages_delivers_them_after_the_fenced_one_first():
    stream = Stream()
    stream.fenced(2, Fence(1), now=0.0)
    stream.channel(2, 'm2', now=0.0)
    stream.channel_lost()
    assert stream.release(0.1) is None  # message 1 is still to come on the main topic
    assert stream.main(1) is Verdict.DELIVER and stream.release(0.1) == 'm2'
    assert stream.release(0.1) is None and stream.state is StreamState.MAIN
    assert stream.main(3) is Verdict.DELIVER


def test_a_newer_main_topic_copy_proves_the_fenced_message_lost():
    """DDS delivers one writer's samples in order: once a copy newer than the fenced message
    came on the main topic, the fenced one is lost (a startup race), so nothing waits for it."""
    stream = Stream()
    stream.fenced(5, Fence(3), now=0.0)
    stream.channel(5, 'm5', now=0.0)
    assert stream.main(5) is Verdict.DUPLICATE  # the switch message's main-topic copy
    assert stream.release(0.1) == 'm5' and stream.lost_fenced == 1 and stream.timeouts == 0
    assert stream.main(3) is Verdict.DUPLICATE  # too late now: older than what was delivered


def test_a_fenced_message_delivered_to_the_reader_and_not_there_is_lost_without_a_wait():
    """The fence said its message had reached the reader (every main-topic reader had
    acknowledged it): once the reader has nothing left to take, a fenced message not delivered
    was lost there (KEEP_LAST overwrite, or never the reader's: a startup race), and the
    queued channel messages go at once, not after FENCE_TIMEOUT_SECONDS."""
    stream = Stream()
    stream.main(1)
    stream.fenced(5, Fence(3, delivered=True), now=0.0)
    assert stream.state is StreamState.WAITING
    assert stream.channel(5, 'm5', now=0.0) is Verdict.QUEUED
    assert stream.release(0.0, main_drained=False) is None  # it may still be there: take it
    assert stream.release(0.0, main_drained=True) == 'm5'
    assert stream.state is StreamState.CHANNEL
    assert stream.lost_fenced == 1 and stream.timeouts == 0
    assert stream.main(3) is Verdict.DUPLICATE  # never delivered out of order or twice


def test_a_delivered_fenced_message_still_in_the_reader_comes_first():
    stream = Stream()
    stream.fenced(5, Fence(3, delivered=True), now=0.0)
    stream.channel(5, 'm5', now=0.0)
    assert stream.release(0.0, main_drained=False) is None
    assert stream.main(3) is Verdict.DELIVER  # taken from the reader first
    assert stream.release(0.0) == 'm5' and stream.lost_fenced == 0


def test_the_table_shows_the_streams_waiting_now():
    """statistics()'s waiting_for_fence: a wait shows while it lasts, not only once it ended."""
    table = StreamTable()
    table['a'].fenced(3, Fence(2), now=0.0)
    table['a'].channel(3, 'm3', now=0.0)
    table['b'].main(1)
    assert table.waiting() == 1 and table.fence_counts() == (0, 0)
    assert table['a'].main(2) is Verdict.DELIVER and table['a'].release(0.0) == 'm3'
    assert table.waiting() == 0


def test_best_effort_stream_never_waits():
    stream = Stream(reliable=False)
    stream.fenced(3, Fence(2), now=0.0)
    assert stream.state is StreamState.CHANNEL and stream.channel(3, 'm', 0.0) is Verdict.DELIVER


def test_stream_channel_without_fence_switches_and_lost_channel_goes_back_to_main():
    stream = Stream()
    assert stream.channel(4, 'm4', now=0.0) is Verdict.DELIVER
    assert stream.main(5) is Verdict.DUPLICATE  # the channel carries it
    stream.channel_lost()
    assert stream.state is StreamState.MAIN and stream.main(5) is Verdict.DELIVER


# --- control messages -------------------------------------------------------------------------

class _Readers:
    """A routes.ReceiveView over lists: channel samples ('fence', n) / ('probe', n) / ('data',
    n) per publisher key, and main-topic samples (publisher, n); what was taken, in order."""

    def __init__(self, channels: Dict[str, list], main: list) -> None:
        self.queues = {key: collections.deque(samples) for key, samples in channels.items()}
        self.main = collections.deque(main)
        self.taken: List[tuple] = []
        self.drained = 0

    def channels(self):
        return list(self.queues)

    def channel_key(self, channel):
        return channel

    def take_channel(self, channel):
        queue = self.queues[channel]
        if not queue:
            return None
        self.taken.append((channel, *queue[0]))
        return queue.popleft()

    def classify(self, channel, sample):
        if sample[0] == 'fence':
            return Incoming.FENCE, Fence(sample[2])
        return (Incoming.CONTROL, None) if sample[0] == 'probe' else (Incoming.DATA, None)

    def timestamp(self, sample):
        return sample[1]

    def channels_drained(self):
        self.drained += 1

    def peek_main(self):
        return self.main[0] if self.main else None

    def discard_main(self):
        self.taken.append(('discarded', *self.main.popleft()))

    def take_main(self, publisher):
        if not self.main:
            return None
        self.taken.append(('main', *self.main[0]))
        return self.main.popleft()

    def main_key(self, sample):
        return sample[0]


def _steps(readers: _Readers, receiver: Receiver, now: float = 0.0) -> List[tuple]:
    steps = []
    while (step := receiver.step(readers, now)) is not None:
        steps.append((step.outcome.value, step.sample, step.channel, step.released))
    return steps


def test_receiver_takes_channels_in_rotation_before_the_main_topic():
    readers = _Readers({'a': [('data', 1), ('data', 2)], 'b': [('data', 1)]}, [('x', 5)])
    steps = _steps(readers, Receiver(StreamTable()))
    assert [(s[0], s[2]) for s in steps] == [('deliver', 'a'), ('deliver', 'b'),
                                            ('deliver', 'a'), ('deliver', None)]
    assert readers.drained == 2  # each time every channel was empty: before the main topic, last


def test_receiver_drops_main_topic_duplicates_untaken_once_a_channel_serves():
    streams = StreamTable()
    readers = _Readers({'a': [('data', 3)]}, [('a', 2), ('a', 3), ('a', 4), ('x', 1)])
    steps = _steps(readers, Receiver(streams))
    # a's channel switched it at 3: its main-topic copies from 3 on are duplicates, dropped
    # before they are taken (no payload copied); 2 came late (older than 3): also dropped
    assert [s[0] for s in steps] == ['deliver', 'discarded', 'discarded', 'discarded',
                                     'deliver']
    assert [t[0] for t in readers.taken] == ['a', 'discarded', 'discarded', 'discarded', 'main']


def test_receiver_queues_behind_a_fence_and_releases_after_the_fenced_message():
    streams = StreamTable()
    readers = _Readers({'a': [('fence', 3, 2), ('data', 3), ('data', 4)]}, [])
    receiver = Receiver(streams)
    steps = _steps(readers, receiver)
    assert [s[0] for s in steps] == ['fence', 'queued', 'queued']
    readers.main.append(('a', 2))  # the fenced main-topic message arrives
    steps = _steps(readers, receiver)
    assert [(s[0], s[1], s[3]) for s in steps] == [
        ('deliver', ('a', 2), False), ('deliver', ('data', 3), True),
        ('deliver', ('data', 4), True)]


def test_receiver_gives_probes_and_rejected_samples_no_delivery():
    readers = _Readers({'a': [('probe', 0), ('data', 1)]}, [])
    steps = _steps(readers, Receiver(StreamTable()))
    assert [s[0] for s in steps] == ['control', 'deliver']


def _steady_first_steps(readers: _Readers, receiver: Receiver, now: float,
                        counts: Optional[collections.Counter] = None) -> List[tuple]:
    """What a subscription with one channel does (``Subscription._steady_step``): the channel's
    next sample taken while ``only_channel_next`` allows it; a data sample that
    ``Stream.channel_steady`` takes is delivered as it is, anything else handed to
    ``channel_step``, a data sample marked as such; ``step`` otherwise."""
    steps = []
    while True:
        step = None
        keys = readers.channels()
        stream = receiver.only_channel_next(keys[0]) if len(keys) == 1 else None
        if stream is not None:
            sample = readers.take_channel(keys[0])
            if sample is not None:
                if sample[0] == 'data' and stream.channel_steady(readers.timestamp(sample)):
                    step = Step(Outcome.DELIVER, sample, keys[0])
                    if counts is not None:
                        counts['channel_steady'] += 1
                else:
                    step = receiver.channel_step(readers, keys[0], stream, sample, now,
                                                 data=sample[0] == 'data')
        step = step or receiver.step(readers, now)
        if step is None:
            return steps
        steps.append((step.outcome.value, step.sample, step.channel, step.released))


def test_the_one_channel_shortcut_takes_and_delivers_what_step_does():
    """Random arrivals on one channel (data, duplicates, probes, fences) and on the main topic
    (its copies and another publisher's), time passing (fences given up): a receiver driven
    through ``only_channel_next`` and ``channel_step`` gives the steps, takes and stream
    states that ``step`` alone gives; a second channel ends the shortcut, and once it is gone
    the rotation goes on where ``step`` left it."""
    import random
    shortcuts = collections.Counter()
    for seed in range(400):
        rng = random.Random(seed)
        runs = []
        for shortcut in (False, True):
            rng.seed(seed)
            readers, receiver = _Readers({'a': []}, []), Receiver(StreamTable())
            trace, now, n = [], 0.0, 0
            for _ in range(rng.randint(5, 40)):
                kind = rng.choice(('data', 'data', 'data', 'old', 'probe', 'fence', 'main',
                                   'other', 'time', 'take', 'take', 'second', 'gone'))
                if kind in ('data', 'old'):
                    n += kind == 'data'
                    readers.queues['a'].append(('data', n if kind == 'data' else n - 2))
                elif kind == 'probe':
                    readers.queues['a'].append(('probe', 0))
                elif kind == 'fence':
                    n += 1
                    readers.queues['a'].append(('fence', n + 1, n))
                elif kind == 'main':
                    readers.main.append(('a', n))
                elif kind == 'other':
                    readers.main.append(('x', rng.randint(1, 9)))
                elif kind == 'time':
                    now += rng.choice((0.01, FENCE_TIMEOUT_SECONDS))
                elif kind == 'second' and 'b' not in readers.queues:
                    readers.queues['b'] = collections.deque([('data', n), ('data', n + 1)])
                elif kind == 'gone':  # the second publisher's channel goes
                    readers.queues.pop('b', None)
                else:
                    trace.append(_steady_first_steps(readers, receiver, now, shortcuts)
                                 if shortcut else _steps(readers, receiver, now))
            stream = receiver.streams.streams.get('a')
            runs.append((trace, readers.taken, stream and (
                stream.state, stream.last, stream.fence, list(stream.waiting))))
        assert runs[0] == runs[1], seed
    assert shortcuts['channel_steady'] > 100, shortcuts  # the common case, taken often


def test_channel_steady_takes_a_newer_copy_on_the_channel_and_nothing_else():
    """``Stream.channel_steady`` delivers what ``channel`` would deliver with nothing else to
    do: a newer copy while the stream is on the channel. Anything else changes nothing."""
    stream = Stream()
    assert not stream.channel_steady(5) and stream.state is StreamState.MAIN
    assert stream.channel(5, 'five', 0.0) is Verdict.DELIVER  # the switch, without a fence
    assert stream.state is StreamState.CHANNEL and stream.last == 5
    assert stream.channel_steady(6) and stream.last == 6
    for old in (6, 4):
        assert not stream.channel_steady(old) and stream.last == 6
    stream.waiting.append((9, 'nine'))
    assert not stream.channel_steady(7) and stream.last == 6
    stream.waiting.clear()
    stream.fenced(8, Fence(7), 0.0)  # waits for main-topic message 7
    assert stream.state is StreamState.WAITING
    assert not stream.channel_steady(8) and stream.last == 6 and not stream.waiting


def test_control_messages_round_trip_and_are_told_from_messages():
    for message in (control.PROBE, Fence(0), Fence(2 ** 64 - 1), Fence(123456789),
                    Fence(7, delivered=True)):
        raw = control.encode(message)
        assert control.is_control(raw) and control.parse(raw) == message
    cdr = b'\x00\x01\x00\x00' + bytes(12)  # every CDR message rmw or the codec writes
    assert control.parse(cdr) is None


@pytest.mark.parametrize('raw', [
    b'\x00\x01RB', b'\x00\x01RB' + bytes(13), b'\x00\x01RB\x03' + bytes(11),
    b'\x00\x01RB\x01\x00\x00\x00' + (1).to_bytes(8, 'little'),
    b'\x00\x01RB\x01\x01\x00\x00' + bytes(8),  # a probe has no flags
    b'\x00\x01RB\x02\x02\x00\x00' + bytes(8),  # a fence flag nobody defined
    b'\x00\x01RB\x02\x00\x01\x00' + bytes(8)])
def test_malformed_control_messages_are_rejected(raw):
    with pytest.raises(control.ControlError):
        control.parse(raw)


def test_control_encode_refuses_what_it_cannot_carry():
    with pytest.raises(ValueError, match='uint64'):
        control.encode(Fence(-1))
    with pytest.raises(TypeError, match='Probe or a Fence'):
        control.encode('probe')


# --- the model: one publisher, one buffer-aware subscription, real protocol objects ----------

@dataclass
class Link:
    """A RELIABLE KEEP_LAST DDS link (main topic or channel), modelled: in order, samples may be
    lost only when the reader's history overflows (older ones first), or when the writer's
    history had dropped them before a late reader matched."""

    depth: int
    queue: collections.deque = field(default_factory=collections.deque)

    def write(self, item) -> None:
        self.queue.append(item)
        while len(self.queue) > self.depth:
            self.queue.popleft()


class ModelView:
    """What the modelled DDS says, answered for the route table as the publisher's
    ``_RouteView`` answers from real DataWriters (:class:`rosidl_buffer_py.routes.RouteView`)."""

    def __init__(self, model: 'RouteProtocol') -> None:
        self.model = model
        self.read = None  #: the signature last read

    def signature(self, fresh=False):
        self.read = (1, (1 if self.model.channel_up else 0,))
        return self.read

    def settled(self, now):
        # the real view is unsettled after a discovery, which any change of the counts follows
        return self.read == (1, (1 if self.model.channel_up else 0,))

    def matched_subscriptions(self):
        return ['s']

    def channel_matched(self, key):
        self.model.seen_up = self.model.channel_up  # what the table last heard
        return self.model.channel_up

    def channel_acknowledged(self, key):
        return self.model.channel_acked

    def main_acknowledged(self):
        return self.model.main_acked


class RouteProtocol(RuleBasedStateMachine):
    """A publisher's RouteTable and a subscription's Stream connected by two modelled links;
    random publishes, matches, acknowledgments, takes, time and death. The publisher side is
    driven through the entry points the real publisher uses (``RouteTable.dispatch`` per
    message, ``RouteTable.dispatch_prepared`` once it has a steady answer to prepare for,
    ``RouteTable.advance`` on its route timer), and writes what they answer, in their order."""

    #: the QoS depth (RELIABLE KEEP_LAST 5: routes probe), and how much a link holds
    DEPTH = 5
    LINK_DEPTH = 5
    LOSSY = True

    def __init__(self) -> None:
        super().__init__()
        self.now = 0.0
        self.timestamp = 0
        self.table = RouteTable()
        self.route = self.table.add('s', handshake=True, depth=self.DEPTH)
        self.view = ModelView(self)
        self.stream = Stream()
        self.main = Link(self.LINK_DEPTH)
        self.channel = Link(self.LINK_DEPTH)
        self.channel_up = self.seen_up = False
        #: the channel's reader acknowledged every sample written on it (DDS's answer)
        self.channel_acked = False
        #: the main topic's readers acknowledged every sample (the writer knows it)
        self.main_acked = False
        self.timer_armed = False
        #: the steady dispatch the publisher prepared its writes for (``Publisher._lane``)
        self.lane = None
        self.published: List[int] = []
        self.delivered: List[int] = []
        self.queued_at: Dict[int, float] = {}
        self.written_after_gone = 0
        self.dead = False

    # the publisher side -----------------------------------------------------------------

    def _write_channel(self, item) -> None:
        if self.route.state is RouteState.GONE:
            self.written_after_gone += 1
        self.channel.write(item)
        self.channel_acked = False

    def _write_probes(self, probes, timestamp) -> None:
        for key, count in probes:
            assert key == 's'
            for _ in range(count):
                self._write_channel(('control', control.encode(control.PROBE), timestamp))

    @rule(acked=st.booleans())
    def publish(self, acked):
        """Publish one message as ``Publisher.publish`` does: ask the table, write what it
        says. A fence says its message reached the reader when the main topic's writer knows
        it was acknowledged: the modelled links deliver at once, so that is true whenever the
        writer knows, which ``acked`` says (False: the acknowledgment is not in yet)."""
        self.main_acked = acked
        if self.dead and self.route.state is not RouteState.GONE:
            self.table.gone('s')  # the backend said so; DDS still matches it
        previous = self.timestamp
        self.timestamp += 1
        ts = self.timestamp
        self.published.append(ts)
        if self.lane is not None:
            dispatch = self.table.dispatch_prepared(self.lane, self.now, ts, self.view)
        else:
            dispatch = self.table.dispatch(self.now, ts, self.view)
        if dispatch is self.table.steady:
            self.lane = dispatch
        self._write_probes(dispatch.probes, previous or ts - 1)
        self._write_dispatch(dispatch, ts)
        if self.table.replan_due:  # the periodic re-plan, after the message's writes
            self._advance()

    def _write_dispatch(self, dispatch, ts) -> None:
        if dispatch.timer is not None:
            self.timer_armed = dispatch.timer
        for key, fence in dispatch.channel:
            if fence is not None:
                self._write_channel(('control', control.encode(fence), ts))
            self._write_channel(('data', None, ts))
        if dispatch.main and 's' not in dispatch.withheld:
            if self.route.state is RouteState.GONE:
                self.written_after_gone += 1
            self.main.write(('data', None, ts))

    @precondition(lambda self: self.timer_armed)
    @rule()
    def route_timer_fires(self):
        """The publisher's route timer (armed while a route is being brought up) runs between
        messages, as ``Publisher._advance`` does."""
        self._advance()

    def _advance(self) -> None:
        probes, timer = self.table.advance(self.now, self.view)
        self._write_probes(probes, self.timestamp)
        self.timer_armed = timer

    @rule(count=st.integers(1, 2 * LINK_DEPTH))
    def another_publisher_writes(self, count):
        """A second publisher of the keyless topic writes ``count`` samples while the
        subscription does not take: they share its main reader history, and push this
        publisher's untaken ones out of it (KEEP_LAST), as in the startup of a real graph."""
        for _ in range(count):
            self.main.write(('other', None, 0))

    @rule()
    def channel_matches(self):
        self.channel_up = True

    @precondition(lambda self: self.channel_up and (self.LOSSY or not self.channel.queue))
    @rule()
    def channel_unmatches(self):
        """The channel's reader goes (what it had not taken is lost with it); the subscription
        forgets the channel and its publisher's next messages come on the main topic."""
        self.channel_up = False
        self.channel_acked = False
        self.channel.queue.clear()
        self.stream.channel_lost()

    @precondition(lambda self: self.channel_up and not self.channel_acked)
    @rule()
    def channel_acknowledges(self):
        """DDS learns that the channel's reader has every sample written on it so far (they
        are in its history; taken or not). The route table hears it when it next asks."""
        self.channel_acked = True

    @rule(seconds=st.sampled_from([0.005, 0.05, 0.3, 1.2]))
    def time_passes(self, seconds):
        self.now += seconds

    @rule()
    def subscriber_dies(self):
        self.dead = True

    # the subscription side --------------------------------------------------------------

    @precondition(lambda self: self.main.queue and not self.dead)
    @rule()
    def take_main(self):
        kind, _, ts = self.main.queue.popleft()
        if kind == 'other':  # the other publisher's stream: not this one's business
            self._release()
            return
        if self.stream.main(ts) is Verdict.DELIVER:
            self.delivered.append(ts)
        self._release()

    @precondition(lambda self: self.channel.queue and self.channel_up and not self.dead)
    @rule()
    def take_channel(self):
        kind, raw, ts = self.channel.queue.popleft()
        if kind == 'control':
            message = control.parse(raw)
            if isinstance(message, Fence):
                self.stream.fenced(ts, message, self.now)
            return
        verdict = self.stream.channel(ts, ts, self.now)
        if verdict is Verdict.DELIVER:
            self.delivered.append(ts)
        elif verdict is Verdict.QUEUED:
            self.queued_at[ts] = self.now
        self._release()

    @rule()
    def subscription_wakes(self):
        self._release()

    def _release(self):
        while (item := self.stream.release(self.now, not self.main.queue)) is not None:
            self.delivered.append(item)

    # invariants ---------------------------------------------------------------------------

    @invariant()
    def delivered_at_most_once_in_publish_order(self):
        assert self.delivered == sorted(set(self.delivered)), self.delivered

    @invariant()
    def nothing_written_to_a_dead_peer(self):
        assert self.written_after_gone == 0

    @invariant()
    def nothing_held_past_the_fence_timeout(self):
        """A channel message waits for its fenced main-topic message while that one can still
        come (the main topic has samples to take), else at most FENCE_TIMEOUT_SECONDS."""
        self._release()
        if self.main.queue:
            return
        for ts, since in self.queued_at.items():
            if ts in self.stream_waiting_timestamps():
                assert self.now - since < FENCE_TIMEOUT_SECONDS + 1e-9, (ts, since, self.now)

    @invariant()
    def nothing_waits_for_what_the_reader_lost(self):
        """A fence whose message reached the reader (acknowledged) waits only while the reader
        has something left to take: once empty, the message was overwritten there, and the
        channel's messages go at once, with no timeout."""
        self._release()
        if not self.main.queue and self.stream.fence_delivered:
            assert self.stream.state is not StreamState.WAITING, self.stream

    def stream_waiting_timestamps(self):
        return {ts for ts, _ in self.stream.waiting}

    @invariant()
    def main_topic_serves_until_the_channel_does(self):
        route = self.route
        if route.state in (RouteState.FENCING, RouteState.SERVING, RouteState.CONFIRMED):
            assert self.seen_up  # as the table last heard it from DDS
        if route.withheld:
            assert route.handshake  # only an acknowledged channel keeps main-topic samples away

    @invariant()
    def nothing_lost_while_links_keep_up(self):
        """Every message published is delivered, on one route or the other, unless a link
        overflowed (KEEP_LAST drops, as DDS would) or the subscriber died: checked by the
        drain at teardown."""

    def teardown(self):
        if self.dead:
            return
        # drain both links completely, then let time run out any fence wait
        self.channel_up = True
        for _ in range(1000):
            if self.channel.queue:
                self.take_channel()
            elif self.main.queue:
                self.take_main()
            else:
                break
        self.now += FENCE_TIMEOUT_SECONDS
        self._release()
        assert self.delivered == sorted(set(self.delivered))


def test_model_trace_a_fenced_message_lost_to_another_publishers_samples():
    """The ordering a CI run met (issue 27): the fenced message (the last main-topic one) is
    pushed out of the subscription's KEEP_LAST reader history by another publisher's samples
    before the subscription took it, and every later main-topic sample of its publisher is
    withheld from it. The fence said its message had reached the reader: once the reader has
    nothing left, the channel's messages go at once (before: held FENCE_TIMEOUT_SECONDS)."""
    model = RouteProtocol()
    model.channel_matches()
    model.publish(acked=True)  # message 1 on the main topic; probes written
    while model.channel.queue:
        model.take_channel()  # the probes
    model.channel_acknowledges()
    model.route_timer_fires()  # the table hears of it: ACKNOWLEDGED
    model.publish(acked=True)  # message 2: the last main-topic one
    model.publish(acked=True)  # message 3: fence (last main 2), on the channel
    assert model.route.state is RouteState.CONFIRMED and model.main.queue
    model.another_publisher_writes(count=RouteProtocol.LINK_DEPTH)  # 1 and 2 pushed out
    model.take_channel()  # the fence
    model.take_channel()  # message 3: queued behind the fenced message 2
    assert model.stream.state is StreamState.WAITING
    while model.main.queue:
        model.take_main()  # the other publisher's samples only
    model.nothing_waits_for_what_the_reader_lost()
    assert model.delivered == [3] and model.stream.lost_fenced == 1
    assert model.now == 0.0 and model.stream.timeouts == 0  # no time passed, no timeout


TestRouteProtocol = RouteProtocol.TestCase
TestRouteProtocol.settings = settings(max_examples=300, stateful_step_count=60, deadline=None,
                                      suppress_health_check=[HealthCheck.too_slow])


class LosslessRouteProtocol(RouteProtocol):
    """The same with links deep enough never to overflow (a reader that keeps up): then
    nothing is lost at all."""

    LINK_DEPTH = 10_000
    LOSSY = False

    def teardown(self):
        super().teardown()
        if not self.dead:
            assert self.delivered == self.published, (self.delivered, self.published)


TestLosslessRouteProtocol = LosslessRouteProtocol.TestCase
TestLosslessRouteProtocol.settings = TestRouteProtocol.settings
