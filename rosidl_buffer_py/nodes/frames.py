"""Verifiable test frames: every image carries its frame counter and a checksum.

``header.frame_id`` is ``"frame=<n> crc=<crc32 of data>"``; the first 8 bytes of ``data`` repeat
the counter (little endian), so a frame whose bytes belong to another frame fails too.
``header.stamp`` is the wall-clock publish time, for latency.
"""
import re
import struct
import time
import zlib
from dataclasses import dataclass
from typing import Optional

import numpy

_FRAME_ID = re.compile(r'^frame=(\d+) crc=(\d+)$')
_COUNTER = struct.Struct('<Q')


def pattern(nbytes: int, seed: int = 7) -> numpy.ndarray:
    """Deterministic pseudo-random bytes that frames are built from."""
    return numpy.random.default_rng(seed).integers(0, 256, size=nbytes, dtype=numpy.uint8)


def stamp_frame(msg, counter: int, data: numpy.ndarray) -> None:
    """Write ``counter`` into ``data`` (the message's payload memory) and label ``msg``.

    ``data`` is a flat uint8 view of the payload, already filled with the frame's pixels.
    """
    if data.nbytes >= _COUNTER.size:
        data[:_COUNTER.size] = numpy.frombuffer(_COUNTER.pack(counter), dtype=numpy.uint8)
    msg.header.frame_id = f'frame={counter} crc={zlib.crc32(data)}'
    now = time.time_ns()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(now, 1_000_000_000)


@dataclass
class FrameCheck:
    counter: Optional[int]
    ok: bool
    reason: str = ''


def check_frame(msg) -> FrameCheck:
    """Verify a received frame's checksum and embedded counter."""
    match = _FRAME_ID.match(msg.header.frame_id)
    if match is None:
        return FrameCheck(None, False, f'bad frame_id {msg.header.frame_id[:40]!r}')
    counter, crc = int(match.group(1)), int(match.group(2))
    data = memoryview(msg.data).cast('B') if not isinstance(msg.data, (bytes, bytearray)) \
        else memoryview(msg.data)
    if zlib.crc32(data) != crc:
        return FrameCheck(counter, False, 'checksum mismatch')
    if data.nbytes >= _COUNTER.size and _COUNTER.unpack(data[:_COUNTER.size])[0] != counter:
        return FrameCheck(counter, False, 'embedded counter mismatch')
    return FrameCheck(counter, True)


def latency_ms(msg) -> float:
    """Wall-clock time from the publisher's stamp to now."""
    sent = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
    return (time.time_ns() - sent) / 1e6
