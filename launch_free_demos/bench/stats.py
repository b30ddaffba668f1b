"""The benchmarks' statistics: percentiles of samples, one definition for every table.

A percentile is numpy's (linear interpolation between the two nearest ranks); ``max`` is the
100th. The nodes' reports (``latency_ms``) give the same quantiles, computed by the nodes.
"""
import statistics
from typing import Dict, Iterable, Optional, Sequence, Tuple

import numpy

#: The quantiles a latency is shown with: name and percent.
QUANTILES: Tuple[Tuple[str, float], ...] = (('p50', 50), ('p90', 90), ('p99', 99), ('max', 100))


def percentile(values: Iterable[float], percent: float) -> float:
    """The ``percent`` percentile (0..100) of ``values`` (at least one)."""
    return float(numpy.percentile(numpy.fromiter(values, dtype=float), percent))


def percentiles(values: Sequence[float], quantiles: Sequence[Tuple[str, float]] = QUANTILES,
                digits: Optional[int] = None) -> Dict[str, float]:
    """Name -> percentile of ``values`` (at least one) for each of ``quantiles``, rounded to
    ``digits`` decimals if given."""
    data = numpy.asarray(values, dtype=float)
    return {name: float(numpy.percentile(data, percent)) if digits is None
            else round(float(numpy.percentile(data, percent)), digits)
            for name, percent in quantiles}


def per_round_line(what: str, ratios: Sequence[float]) -> str:
    """``what``'s ratio in each interleaved round and their median, as one printed line."""
    return (f'{what} per round: ' + ', '.join(f'{r:.2f}' for r in ratios)
            + f' (median {statistics.median(ratios):.2f})')
