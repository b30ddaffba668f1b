"""At most one log line per period from a live path (a publish, a take).

rclpy's ``throttle_duration_sec`` filter looks its caller up (``inspect``) on every call, logged
or not, so a line that may come with every message throttles itself here and is logged with
:func:`rosidl_buffer_py.rclpy_seams_7_1.log`.
"""
import time


class Throttle:
    """``due()`` is True at most once per ``period`` seconds (the first time: True)."""

    __slots__ = ('period', '_last')

    def __init__(self, period: float) -> None:
        self.period = period
        self._last = -period

    def due(self) -> bool:
        now = time.monotonic()
        if now - self._last < self.period:
            return False
        self._last = now
        return True
