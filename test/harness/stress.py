"""How stable each equivalence scenario is: a rate, not one run (``./dev stress``).

A comparison with stock that stock against itself fails is a wrong test, not a flaky one. For
each scenario of :mod:`harness.equivalence` this runs ``--runs`` rounds of the scenario stock
against ours, and as many stock against stock (the oracle against itself: what timing alone
changes), optionally beside ``--load`` busy processes (a loaded CI machine), and prints per
scenario how many runs differed each way, with a verdict:

- ``stable``: neither differed;
- ``ours differs more``: ours differed in more runs than stock against stock (a difference of
  ours, or a tolerance too tight for ours alone);
- ``stock unstable``: stock against stock differed (the scenario or its tolerances are wrong:
  choose rates and depths at which stock loses nothing, or compare what timing cannot change).

The first difference seen each way is printed under the table, then what the comparison's
tolerances had to cover each way (:class:`harness.equivalence.Spread`): stock against stock is
what timing alone changes, so each tolerance should cover that and no more.

``./dev stress [names] [--runs 10] [--load 0]``
"""
import argparse
import multiprocessing
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

if __package__ in (None, ''):  # run as a file: harness is a package of test/, and
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    # launch_free_demos (not installed) is the checkout's, after the installed packages
    sys.path.append(str(Path(__file__).resolve().parents[2]))

from harness import equivalence  # noqa: E402 (after the path fix)
from harness.equivalence import Spread, run_scenario, scenarios, spread  # noqa: E402
from launch_free_demos.domains import claim_domain_ids  # noqa: E402


def _busy(stop) -> None:
    while not stop.is_set():
        sum(range(10000))


@dataclass
class Rate:
    """How often one scenario differed, ours against stock and stock against itself."""

    name: str
    runs: int
    ours: int = 0
    oracle: int = 0
    seconds: float = 0.0
    first_ours: Optional[str] = None
    first_oracle: Optional[str] = None
    #: what the tolerances had to cover: ours against stock, stock against stock
    spread_ours: Spread = field(default_factory=Spread)
    spread_oracle: Spread = field(default_factory=Spread)

    @property
    def verdict(self) -> str:
        if self.oracle:
            return 'stock unstable'
        return 'ours differs more' if self.ours else 'stable'

    def row(self) -> str:
        return (f'| {self.name} | {self.ours} of {self.runs} | {self.oracle} of {self.runs} | '
                f'{self.verdict} | {self.seconds:.0f} |')


HEADER = ('| scenario | ours vs stock differed | stock vs stock differed | verdict | s |\n'
          '|---|---|---|---|---|')


def measure(name: str, runs: int, domains) -> Rate:
    """``runs`` rounds of scenario ``name``, each variant pair in turn (stock vs ours, then
    stock vs stock), in the same two domains."""
    scenario = next(s for s in scenarios() if s.name == name)
    rate = Rate(name, runs)
    started = time.monotonic()
    for _ in range(runs):
        for variants, attribute in ((('stock', 'ours'), 'ours'),
                                    (('stock', 'stock'), 'oracle')):
            result = run_scenario(scenario, domains, False, variants)
            if attribute == 'ours':
                rate.spread_ours = rate.spread_ours.widen(
                    spread(scenario, result.stock, result.ours))
            else:  # neither run is the reference: both ways
                rate.spread_oracle = rate.spread_oracle.widen(
                    spread(scenario, result.stock, result.ours)).widen(
                    spread(scenario, result.ours, result.stock))
            if result.differences:
                setattr(rate, attribute, getattr(rate, attribute) + 1)
                first = f'first_{attribute}'
                if getattr(rate, first) is None:
                    setattr(rate, first, '; '.join(result.differences[:3]))
    rate.seconds = time.monotonic() - started
    return rate


def spread_table(rates: List[Rate]) -> str:
    """What each tolerance of the comparison had to cover, per scenario and way, and the
    tolerances in force (a stock-against-stock figure above its tolerance is a difference)."""
    kinds = list(equivalence.TOLERANCES)
    lines = ['| scenario | compared | ' + ' | '.join(kinds) +
             ' | missing | fraction | startup |',
             '|---|---|' + '---|' * (len(kinds) + 3)]
    for rate in rates:
        for label, value in (('stock vs stock', rate.spread_oracle),
                             ('ours vs stock', rate.spread_ours)):
            cells = [str(value.events.get(kind, 0)) for kind in kinds]
            lines.append(f'| {rate.name} | {label} | ' + ' | '.join(cells) +
                         f' | {value.missing} | {value.fraction:.2f} | {value.startup} |')
    lines.append(f'\ntolerances: deadline 2 + stock // 4, liveliness 1, message_lost '
                 f'max(2, stock // 5); missing {equivalence.LENIENT_MISSING}, fraction '
                 f'{equivalence.LENIENT_FRACTION}, startup {equivalence.STARTUP_RACE_MESSAGES}')
    return '\n'.join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='./dev stress', description=__doc__.split('\n\n')[0])
    parser.add_argument('names', nargs='*', help='scenarios (default: all)')
    parser.add_argument('--runs', type=int, default=10, help='rounds of each (default 10)')
    parser.add_argument('--load', type=int, default=0,
                        help='busy processes beside the runs (default 0)')
    args = parser.parse_args(argv)
    known = [s.name for s in scenarios()]
    unknown = sorted(set(args.names) - set(known))
    if unknown:
        parser.error(f'unknown scenarios {unknown}; known: {known}')
    if args.runs < 1 or args.load < 0:
        parser.error(f'--runs must be >= 1 and --load >= 0, got {args.runs} and {args.load}')
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    domains = tuple(claim_domain_ids(2))
    stop = multiprocessing.Event()
    busy = [multiprocessing.Process(target=_busy, args=(stop,), daemon=True)
            for _ in range(args.load)]
    for process in busy:
        process.start()
    rates: List[Rate] = []
    try:
        print(f'{args.runs} runs each, {args.load} busy processes beside them', flush=True)
        print(HEADER, flush=True)
        for name in args.names or known:
            rates.append(measure(name, args.runs, domains))
            print(rates[-1].row(), flush=True)
    finally:
        stop.set()
        for process in busy:
            process.join(5)
            if process.is_alive():
                process.kill()
    for rate in rates:
        for label, first in (('ours vs stock', rate.first_ours),
                             ('stock vs stock', rate.first_oracle)):
            if first:
                print(f'\n{rate.name}, {label}: {first}')
    print('\n' + spread_table(rates))
    stable = sum(r.verdict == 'stable' for r in rates)
    print(f'\n{stable} of {len(rates)} stable')
    return 0


if __name__ == '__main__':
    sys.exit(main())
