"""The report line: what a program of this package says about its run, for another program.

Every runnable node (``image_publisher``, ``image_subscriber``, ...) and tool (``buffer_record``,
``buffer_play``) prints one report as it ends, on stdout, after everything else it prints there.
The demos, the benchmarks and the tests read it; this module is the whole interface between
them, and it imports nothing of the package. It sits beside the library, not in :mod:`.nodes`,
because the nodes and the tools (:mod:`.tools`) both write it.

The line is ``REPORT `` followed by one JSON object on the same line, keys sorted::

    REPORT {"node": "image_subscriber", "received": 150, "role": "subscriber"}

Its keys are the program's own (documented with the program); ``role`` names the program's
kind where more than one kind reports on one stream. A reader takes the last such line of a
process's stdout (:func:`last_report`); every other line is not a report.
"""
import json
from dataclasses import dataclass, field
from typing import Any, Dict, Iterable, Optional

#: What starts a report line; the JSON object follows it.
REPORT_PREFIX = 'REPORT '


@dataclass(frozen=True)
class Report:
    """One program's report: a JSON object's keys and values."""

    values: Dict[str, Any] = field(default_factory=dict)

    def to_line(self) -> str:
        """The one line that carries the report (no newline)."""
        return REPORT_PREFIX + json.dumps(self.values, sort_keys=True)

    @classmethod
    def from_line(cls, line: str) -> Optional['Report']:
        """The report a line carries, or None when it is not a report line."""
        if not line.startswith(REPORT_PREFIX):
            return None
        return cls(json.loads(line[len(REPORT_PREFIX):]))


def print_report(values: Dict[str, Any]) -> None:
    """Print ``values`` as this program's report line on stdout (flushed at once)."""
    print(Report(values).to_line(), flush=True)


def last_report(lines: Iterable[str]) -> Optional[Dict[str, Any]]:
    """The values of the last report among a process's stdout lines (None when it printed
    none)."""
    found = None
    for line in lines:
        report = Report.from_line(line.rstrip('\n'))
        if report is not None:
            found = report
    return found.values if found is not None else None
