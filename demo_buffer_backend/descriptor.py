"""The demo descriptor: the few bytes that cross DDS instead of the payload.

Layout (little endian), 36 bytes plus the segment name (about 70 bytes in all)::

    magic 'RBDM' | version u8 | name_len u8 | reserved u16 (0) | owner pid u32 |
    offset u64 | size u64 | generation u64 | name (ASCII, name_len bytes)

:func:`unpack` checks everything that can be checked without opening the segment; the pool checks
the rest (the segment exists, offset and size fit in it, the generation is current and the size
is the one its publisher recorded).
"""
import struct
from typing import NamedTuple

from demo_buffer_backend.shm import NAME_PATTERN

MAGIC = b'RBDM'
VERSION = 1
_HEAD = struct.Struct('<4sBBHIQQQ')
MAX_NAME = 64
#: Largest payload a descriptor may name (1 TiB): anything bigger is garbage.
MAX_SIZE = 1 << 40


class Descriptor(NamedTuple):
    name: str
    owner: int
    offset: int
    size: int
    generation: int


def pack(desc: Descriptor) -> bytes:
    name = desc.name.encode('ascii')
    return _HEAD.pack(MAGIC, VERSION, len(name), 0, desc.owner, desc.offset, desc.size,
                      desc.generation) + name


def unpack(data) -> Descriptor:
    """Parse and validate a descriptor received from the network; ``ValueError`` otherwise."""
    try:
        data = bytes(data)
    except TypeError:
        raise ValueError(f'demo descriptor must be bytes, got {type(data).__name__}') from None
    if len(data) < _HEAD.size:
        raise ValueError(f'demo descriptor is truncated: {len(data)} bytes, the fixed part alone '
                         f'is {_HEAD.size}')
    magic, version, name_len, reserved, owner, offset, size, generation = \
        _HEAD.unpack_from(data, 0)
    if magic != MAGIC:
        raise ValueError(f'not a demo descriptor (magic {magic!r}, expected {MAGIC!r})')
    if version != VERSION:
        raise ValueError(f'unsupported demo descriptor version {version} (expected {VERSION})')
    if reserved != 0:
        raise ValueError(f'demo descriptor has non-zero reserved bits {reserved:#x}')
    if not 0 < name_len <= MAX_NAME:
        raise ValueError(f'demo descriptor segment name length {name_len} is not in 1..{MAX_NAME}')
    if len(data) != _HEAD.size + name_len:
        raise ValueError(f'demo descriptor length {len(data)} does not match its name length '
                         f'(expected {_HEAD.size + name_len})')
    raw_name = data[_HEAD.size:]
    try:
        name = raw_name.decode('ascii')
    except UnicodeDecodeError:
        raise ValueError(f'demo descriptor segment name {raw_name!r} is not ASCII') from None
    match = NAME_PATTERN.match(name)
    if match is None:
        raise ValueError(f'demo descriptor segment name {name!r} does not match '
                         f'{NAME_PATTERN.pattern}')
    if int(match.group(1)) != owner:
        raise ValueError(f'demo descriptor owner {owner} does not match segment {name!r}')
    if generation == 0:
        raise ValueError('demo descriptor generation 0 is never published')
    if size > MAX_SIZE or offset > MAX_SIZE:
        raise ValueError(f'demo descriptor offset {offset} / size {size} is implausibly large')
    return Descriptor(name, owner, offset, size, generation)
