"""The ``BUFBE:`` advertisement that buffer-aware endpoints carry in DDS USER_DATA.

rmw_fastrtps writes ``typehash=RIHS01_<hex>;`` into every endpoint's USER_DATA. A buffer-aware
endpoint appends ``BUFBE:<backend>=<metadata>;<backend>=<metadata>;...`` (the format of upstream's
rmw_fastrtps): publishers list ``cpu`` and every installed backend, subscriptions the backends
they accept. An endpoint whose USER_DATA has no ``BUFBE:`` is a legacy endpoint.

Stock Jazzy parses USER_DATA as ``key=value;`` pairs with alphanumeric keys and non-empty values
and drops the *whole* string, typehash included, at the first pair that breaks those rules, as
``BUFBE:cpu=;`` does. It stops cleanly at a NUL byte after a complete pair, so the advertisement
goes after one: ``typehash=RIHS01_<hex>;\0BUFBE:cpu=;demo=<meta>;``. Stock peers keep the type
hash; anyone who reads USER_DATA finds ``BUFBE:``.
"""
from typing import Mapping, Optional

from rosidl_buffer_py.registry import BACKEND_NAME_PATTERN

PREFIX = b'BUFBE:'
#: Where stock rmw's USER_DATA parser stops reading (see the module docstring).
SEPARATOR = b'\0'


class AdvertisementError(ValueError):
    """USER_DATA that cannot carry, or does not hold, a valid advertisement."""


def encode(backends: Mapping[str, str]) -> bytes:
    """Encode ``{backend: metadata}`` as the ``BUFBE:`` suffix for USER_DATA."""
    parts = []
    for name, metadata in backends.items():
        if not BACKEND_NAME_PATTERN.match(name):
            raise AdvertisementError(
                f'backend name {name!r} must match {BACKEND_NAME_PATTERN.pattern}')
        if ';' in metadata or any(ord(c) < 0x20 or ord(c) > 0x7e for c in metadata):
            raise AdvertisementError(
                f'metadata {metadata!r} of backend {name!r} must be printable ASCII without ";"')
        parts.append(f'{name}={metadata};')
    return PREFIX + ''.join(parts).encode('ascii')


def append(user_data: bytes, backends: Mapping[str, str]) -> bytes:
    """Return ``user_data`` with the advertisement appended (replacing an earlier one).

    ``user_data`` should end with a complete ``key=value;`` pair (rmw's typehash), so that the
    separator is where stock rmw stops parsing.
    """
    base = bytes(user_data)
    index = base.find(PREFIX)
    if index >= 0:
        base = base[:index]
    base = base.rstrip(SEPARATOR)
    return base + SEPARATOR + encode(backends)


def decode(user_data: bytes) -> Optional[Mapping[str, str]]:
    """Return ``{backend: metadata}`` from USER_DATA, or ``None`` for a legacy endpoint.

    Malformed entries (from a peer we do not control) are skipped, never raised: a peer with a
    garbled advertisement keeps whatever valid backends it lists.
    """
    data = bytes(user_data)
    index = data.find(PREFIX)
    if index < 0:
        return None
    text = data[index + len(PREFIX):].decode('ascii', errors='replace')
    backends = {}
    for entry in text.split(';'):
        name, sep, metadata = entry.partition('=')
        if sep and BACKEND_NAME_PATTERN.match(name):
            backends[name] = metadata
    return backends
