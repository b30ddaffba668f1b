"""Helpers of the in-process tests: spinning until something holds, and verifiable frames."""
import time

from rosidl_buffer_py.image import allocate_image_msg, from_output_msg
from rosidl_buffer_py.nodes.frames import pattern, stamp_frame


def spin_until(executor, predicate, timeout: float = 20.0) -> bool:
    """Spin ``executor`` until ``predicate()`` holds; False after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.05)
    return True


def frame(counter: int, backend: str = 'cpu', height: int = 8, width: int = 8):
    """An rgb8 Image carrying ``counter`` and the CRC32 the image nodes check."""
    msg = allocate_image_msg(height, width, 'rgb8', backend=backend)
    flat = from_output_msg(msg).reshape(-1)
    flat[...] = pattern(flat.nbytes)
    stamp_frame(msg, counter, flat)
    return msg
