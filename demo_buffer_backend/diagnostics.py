"""What the demo backend tells about itself: its counters (``demo_buffer_backend.stats()``) and
its warnings, each cause logged once."""
import dataclasses
import re
from typing import Dict, Set

from rclpy.logging import get_logger

#: The backend's logger (its warnings name the cause; counters say how often).
logger = get_logger('demo_buffer_backend')


@dataclasses.dataclass(slots=True)
class Counters:
    """Events of this process's backend since its pool was created (see the package docstring
    of ``stats()``)."""

    segments_created: int = 0
    segments_removed: int = 0
    fallbacks: int = 0
    fallbacks_held: int = 0
    fallbacks_too_large: int = 0
    fallbacks_enospc: int = 0
    fallbacks_memory_error: int = 0
    descriptors_created: int = 0
    descriptors_declined: int = 0
    handovers_sent: int = 0
    handovers_busy: int = 0
    handovers_received: int = 0
    handovers_rejected: int = 0
    handovers_refused: int = 0
    verdicts_late: int = 0
    connections_refused: int = 0
    links_refused: int = 0
    acks: int = 0
    acks_unsent: int = 0
    taken: int = 0
    rejected: int = 0
    stale: int = 0
    reclaimed: int = 0
    mappings_opened: int = 0
    mappings_closed: int = 0
    released_window: int = 0
    released_skipped: int = 0
    released_share: int = 0
    cpu_past_share: int = 0
    peers_gone: int = 0
    cpu_foreign_peer: int = 0

    def add(self, name: str) -> None:
        """Count one event of a counter named at run time (``fallbacks_<cause>``)."""
        setattr(self, name, getattr(self, name) + 1)

    def as_dict(self) -> Dict[str, int]:
        return {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}


class Diagnostics:
    """The counters and the causes already warned about, shared by every part of one pool."""

    __slots__ = ('counters', 'warned')

    def __init__(self) -> None:
        self.counters = Counters()
        self.warned: Set[str] = set()

    def warn_once(self, cause: str, message: str) -> None:
        """Log ``message`` the first time its cause (numbers left out) is seen."""
        cause = re.sub(r'[0-9]+', '#', cause)[:48]
        if cause not in self.warned:
            self.warned.add(cause)
            logger.warning(f'{message} (logged once; see demo_buffer_backend.stats())')
