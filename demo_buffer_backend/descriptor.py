"""The demo descriptor: the few bytes that cross DDS instead of the payload.

Layout (little endian, 52 bytes)::

    magic 'RBDM' | version u8 | reserved u8, u16 (0) | publisher pid u32 | publisher nonce u64 |
    segment id u32 | reserved u32 (0) | generation u64 | offset u64 | size u64

The publisher (pid, nonce) and segment id name a segment that publisher handed over on the
socket (see :mod:`.handover`); :func:`unpack` checks what can be checked without it, the pool
the rest (the segment was handed over by that pid, the range fits, the generation is current and
the size is the one its publisher recorded).
"""
import struct
from typing import NamedTuple

MAGIC = b'RBDM'
VERSION = 2
_LAYOUT = struct.Struct('<4sBBHIQIIQQQ')
SIZE = _LAYOUT.size
#: Largest payload a descriptor may name (1 TiB): anything bigger is garbage.
MAX_SIZE = 1 << 40


class Descriptor(NamedTuple):
    pid: int
    nonce: int
    segment_id: int
    generation: int
    offset: int
    size: int


def pack(desc: Descriptor, magic: bytes = MAGIC) -> bytes:
    """The descriptor's bytes; ``magic`` names the medium (another backend built on this
    machinery has its own)."""
    return _LAYOUT.pack(magic, VERSION, 0, 0, desc.pid, desc.nonce, desc.segment_id, 0,
                        desc.generation, desc.offset, desc.size)


def prefix(magic: bytes = MAGIC) -> bytes:
    """The first 8 bytes of every valid descriptor with ``magic``: the magic, the version and
    the zero reserved bytes (what native code compares in one go)."""
    return _LAYOUT.pack(magic, VERSION, 0, 0, 0, 0, 0, 0, 0, 0, 0)[:8]


def unpack(data, magic: bytes = MAGIC) -> Descriptor:
    """Parse and validate a descriptor received from the network; ``ValueError`` otherwise.

    A valid one passes one test (it runs for every message taken); what is wrong with another
    :func:`_invalid` says."""
    try:
        found, version, reserved1, reserved2, pid, nonce, segment_id, reserved3, generation, \
            offset, size = _LAYOUT.unpack(data)
    except (TypeError, struct.error):
        raise _invalid(data, magic) from None
    if (found != magic or version != VERSION or reserved1 or reserved2 or reserved3 or
            not pid or not generation or size > MAX_SIZE or offset > MAX_SIZE):
        raise _invalid(data, magic)
    return Descriptor(pid, nonce, segment_id, generation, offset, size)


def _invalid(data, magic: bytes) -> ValueError:
    """What is wrong with ``data``, which :func:`unpack` refused."""
    try:
        data = bytes(data)
    except TypeError:
        return ValueError(f'demo descriptor must be bytes, got {type(data).__name__}')
    if len(data) != SIZE:
        return ValueError(f'demo descriptor has {len(data)} bytes, expected {SIZE}')
    found, version, reserved1, reserved2, pid, _, _, reserved3, generation, offset, size = \
        _LAYOUT.unpack(data)
    if found != magic:
        return ValueError(f'not a demo descriptor (magic {found!r}, expected {magic!r})')
    if version != VERSION:
        return ValueError(f'unsupported demo descriptor version {version} (expected {VERSION})')
    if reserved1 or reserved2 or reserved3:
        return ValueError('demo descriptor has non-zero reserved bits')
    if pid == 0:
        return ValueError('demo descriptor names publisher pid 0')
    if generation == 0:
        return ValueError('demo descriptor generation 0 is never published')
    return ValueError(f'demo descriptor offset {offset} / size {size} is implausibly large')
