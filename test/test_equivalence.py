"""The equivalence suite: each scenario's graph run with stock rclpy endpoints (the oracle) and
with buffer-aware ones, in real processes over real Fast DDS, side by side in two domains.

A failure lists every difference between the two outcomes (see test/harness/equivalence.py
for what is compared and the tolerances). One scenario by hand:
``.venv/bin/python test/harness/equivalence.py <name> [--echo]``.
"""
import os
import re
import subprocess
import sys

import pytest

from harness import equivalence
from harness.equivalence import Scenario, compare, pub, sub, table

SCENARIOS = equivalence.scenarios()


@pytest.mark.parametrize('scenario', SCENARIOS, ids=[s.name for s in SCENARIOS])
def test_same_outcome_as_stock(scenario, extra_domain_ids):
    result = equivalence.run_scenario(scenario, tuple(extra_domain_ids))
    if result.differences:
        pytest.fail('\n' + table([result]), pytrace=False)


def test_command_line_runs_named_scenarios():
    """README's command, on one scenario, the stock graph against itself (equal whatever
    the buffer-aware endpoints do); --echo shows the probes' signals."""
    done = subprocess.run(
        [sys.executable, equivalence.__file__, '--oracle-vs-oracle',
         '--echo', 'reliable_pub_first_wait'], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert '| reliable_pub_first_wait |' in done.stdout and '| equal |' in done.stdout
    assert '[stock:pubs] SIGNAL go' in done.stdout
    unknown = subprocess.run([sys.executable, equivalence.__file__, 'nope'],
                             capture_output=True, text=True, timeout=60)
    assert unknown.returncode == 2 and 'reliable_pub_first_wait' in unknown.stderr


def test_stress_prints_each_scenarios_rate_ours_and_stock_against_itself():
    """docs/development.md's ./dev stress, one round of one scenario beside one busy process:
    a row with how many runs differed each way and the verdict; a bad argument is refused."""
    script = os.path.join(os.path.dirname(equivalence.__file__), 'stress.py')
    done = subprocess.run([sys.executable, script, 'keep_last_1_mixed', '--runs', '1',
                           '--load', '1'], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert '1 runs each, 1 busy processes beside them' in done.stdout, done.stdout
    row = re.search(r'^\| keep_last_1_mixed \| ([01]) of 1 \| ([01]) of 1 \| '
                    r'(stable|ours differs more|stock unstable) \|', done.stdout, re.M)
    assert row, done.stdout
    assert (row.group(3) == 'stable') == (row.group(1) == row.group(2) == '0'), done.stdout
    for bad in (['nope'], ['--runs', '0']):
        refused = subprocess.run([sys.executable, script, *bad], capture_output=True,
                                 text=True, timeout=60)
        assert refused.returncode == 2, refused.stderr


# The comparison itself, on outcomes made up for the purpose ----------------------------------

def _graph(startup_race: bool = False) -> Scenario:
    qos = {'reliability': 'reliable', 'history': 'keep_last', 'depth': 5}
    return Scenario('made_up', '', {'p': pub('t', qos), 's': sub('t', qos)}, {'x': []},
                    startup_race=startup_race)


def _outcome(live=(), history=(), events=None, warnings=0) -> dict:
    endpoint = {'kind': 'sub', 'ours': True, 'destroy': [], 'owned': [True], 'acked': [],
                'published': None,
                'incompatible_warnings': warnings, 'history': {'p': list(history)} if history
                else {}, 'live': {'p': list(live)}, 'backends': {}, 'checksum_failures': 0,
                'events': events or {}, 'liveliness_states': [],
                'matched': {'max_current': 1, 'total': 1}}
    return {'endpoints': {'s': endpoint},
            'processes': {'x': {'errors': [], 'warnings': {}}}}


def test_compare_finds_reordering_loss_and_missing_history():
    graph = _graph()
    stock = _outcome(live=range(5, 10), history=range(0, 5))
    assert compare(graph, stock, _outcome(live=range(5, 10), history=range(0, 5))) == []
    assert compare(graph, stock, _outcome(live=[5, 7, 6, 8, 9], history=range(0, 5)))
    assert compare(graph, stock, _outcome(live=range(5, 9), history=range(0, 5)))
    assert compare(graph, stock, _outcome(live=range(0, 10)))  # history came as live


def test_compare_tolerances():
    graph = _graph()
    stock = _outcome(live=range(3, 30), events={'deadline@silent': 6})
    # stock missed a startup prefix (it published from the first matched instant): ours may
    # get more, in order, and a deadline count within its tolerance
    assert compare(graph, stock, _outcome(live=range(0, 30),
                                          events={'deadline@silent': 8})) == []
    assert compare(graph, stock, _outcome(live=range(0, 30), events={'deadline@silent': 0}))
    assert compare(graph, stock, _outcome(live=[0, 2, 1] + list(range(3, 30)),
                                          events={'deadline@silent': 6}))
    warned = _outcome(live=range(3, 30), events={'deadline@silent': 6}, warnings=1)
    assert compare(graph, warned, _outcome(live=range(3, 30), events={'deadline@silent': 6},
                                           warnings=1)) == []
    assert compare(graph, warned, _outcome(live=range(3, 30), events={'deadline@silent': 6},
                                           warnings=2))  # more than once per peer (1 peer)
    assert compare(graph, warned, _outcome(live=range(3, 30), events={'deadline@silent': 6}))


def test_compare_startup_race():
    stock = _outcome(live=range(0, 30))
    assert compare(_graph(), stock, _outcome(live=range(2, 30)))  # a loss after a wait
    raced = _graph(startup_race=True)
    assert compare(raced, stock, _outcome(live=range(2, 30))) == []
    assert compare(raced, _outcome(live=range(2, 30)), _outcome(live=range(0, 30))) == []
    assert compare(raced, stock, _outcome(live=range(10, 30)))  # more than a startup race
    assert compare(raced, stock, _outcome(live=[2, 0, 1] + list(range(3, 30))))
    assert compare(raced, stock, _outcome(live=list(range(2, 20)) + list(range(21, 30))))


def test_compare_volatile_late_joiner_history_is_one_unbroken_run_of_the_retained_history():
    """Fast DDS gives a VOLATILE reader that matches a TRANSIENT_LOCAL writer late no history,
    all of it, or one unbroken run of it (the oracle showed none, 3-7 and 6-7): each of those
    is equal, a gap or a reordering is not."""
    graph = _graph()
    graph.volatile_history = {'s': [3, 4, 5, 6, 7]}
    none, whole = _outcome(live=range(8, 13)), _outcome(live=range(8, 13), history=range(3, 8))
    assert compare(graph, none, whole) == [] and compare(graph, whole, none) == []
    for run in (range(6, 8), range(3, 6), [5]):
        assert compare(graph, whole, _outcome(live=range(8, 13), history=run)) == [], run
    assert compare(graph, none, _outcome(live=range(8, 13), history=[3, 4, 6, 7]))  # a gap
    assert compare(graph, whole, _outcome(live=range(8, 13), history=[3, 5, 4, 6, 7]))
    assert compare(graph, whole, _outcome(live=range(8, 13), history=[2, 3]))  # not retained
    assert compare(graph, whole, _outcome(live=range(9, 13), history=range(3, 8)))  # live lost
    assert compare(_graph(), none, whole)  # a TRANSIENT_LOCAL late joiner: exact
    # nothing waits for that history: its tail may arrive after the phase ended
    split = _outcome(live=range(7, 13), history=range(3, 7))
    assert compare(graph, none, split) == [] and compare(graph, split, whole) == []
    assert compare(graph, split, _outcome(live=range(6, 13), history=[3, 4]))  # gap: 5


def test_spread_measures_what_each_tolerance_had_to_cover():
    """./dev stress prints how far runs were apart where compare() has tolerances: the
    largest event count difference per kind, the live messages a promised subscription got
    fewer (where its counterpart missed some too), the lowest share of a not-promised one's,
    and the first messages a racing start missed."""
    graph = _graph()
    a = _outcome(live=[0, 1, 2, 4, 5, 6], events={'deadline@silent': 6, 'liveliness@run': 1})
    b = _outcome(live=[0, 1, 2], events={'deadline@silent': 9})
    found = equivalence.spread(graph, a, b)
    assert found.events == {'deadline': 3, 'liveliness': 1}
    assert (found.missing, found.fraction, found.startup) == (3, 1.0, 0)
    assert equivalence.spread(graph, a, a) == equivalence.Spread(
        {'deadline': 0, 'liveliness': 0})
    # a whole stream is compared exactly, not with a tolerance: no missing counted
    assert equivalence.spread(graph, _outcome(live=range(0, 7)), b).missing == 0
    best_effort = Scenario('made_up', '', {'p': pub('t', {'reliability': 'best_effort'}),
                                           's': sub('t', {'reliability': 'best_effort'})},
                           {'x': []})
    assert equivalence.spread(best_effort, a, b).fraction == 0.5
    raced = _graph(startup_race=True)
    assert equivalence.spread(raced, _outcome(live=range(0, 30)),
                              _outcome(live=range(4, 30))).startup == 4
    assert found.widen(equivalence.Spread({'deadline': 5}, 1, 0.4, 2)) == \
        equivalence.Spread({'deadline': 5, 'liveliness': 1}, 3, 0.4, 2)
