"""Keep what native libraries print off a tool's stdout.

Fast DDS logs through ``std::cout`` (``RTPS_TRANSPORT_SHM Error Failed init_port ...`` when a
shared-memory port is busy or stale): in a tool whose stdout is a table or JSON read by
scripts, those lines are noise in the data. :func:`native_stdout_to_stderr` points file
descriptor 1 at stderr, where diagnostics belong, and gives Python's ``sys.stdout`` a
descriptor of its own on the original stdout: Python prints there, native code prints to stderr.
"""
import io
import os
import sys

__all__ = ['native_stdout_to_stderr']


def native_stdout_to_stderr() -> None:
    """Route native writes to file descriptor 1 to stderr; Python's prints keep stdout.

    Call before rclpy creates a context (Fast DDS may log as soon as a participant exists).
    Calling it again does nothing.
    """
    if getattr(sys.stdout, '_rbpy_own_stdout', False):
        return
    sys.stdout.flush()
    own = os.dup(1)
    os.dup2(2, 1)
    stream = io.TextIOWrapper(io.FileIO(own, 'w', closefd=True), encoding=sys.stdout.encoding,
                              errors=sys.stdout.errors, line_buffering=True)
    stream._rbpy_own_stdout = True
    sys.stdout = stream
