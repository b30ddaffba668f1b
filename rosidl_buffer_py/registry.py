"""Discovery of buffer backends (the Python counterpart of upstream's pluginlib registry).

A backend is any installed distribution that declares an entry point in the group
``rosidl_buffer_py.backends``, named after the backend and pointing at a :class:`BufferBackend`
subclass (or any zero-argument callable returning an instance)::

    entry_points={'rosidl_buffer_py.backends': ['demo = demo_buffer_backend:DemoBackend']}

``cpu`` is built in and always installed. A backend that fails to load is reported once, with its
error, and skipped: it never stops a node from starting.
"""
import re
import threading
from importlib import metadata
from typing import Dict, FrozenSet, Mapping, Optional, Set

from rclpy.logging import get_logger

from rosidl_buffer_py.backend import BackendUnavailable, BufferBackend
from rosidl_buffer_py.cpu_backend import CPU_BACKEND, CpuBackend

#: Entry point group that backends register under.
ENTRY_POINT_GROUP = 'rosidl_buffer_py.backends'

#: What a backend name may look like (it appears in DDS USER_DATA and topic names).
BACKEND_NAME_PATTERN = re.compile(r'^[a-z][a-z0-9_]{0,62}$')

#: ``acceptable_buffer_backends`` value meaning "every installed backend".
ANY_BACKEND = 'any'

_logger = get_logger('rosidl_buffer_py.registry')
_lock = threading.Lock()
_backends: Optional[Dict[str, BufferBackend]] = None
#: Installed backends this machine cannot run: name -> why (see ``BackendUnavailable``).
_unavailable: Dict[str, str] = {}
_warned_unknown: Set[str] = set()


def _load_entry_point(entry_point: metadata.EntryPoint) -> BufferBackend:
    name = entry_point.name
    if not BACKEND_NAME_PATTERN.match(name):
        raise ValueError(f'backend name {name!r} must match {BACKEND_NAME_PATTERN.pattern}')
    if name == CPU_BACKEND or name == ANY_BACKEND:
        raise ValueError(f'backend name {name!r} is reserved')
    backend = entry_point.load()()
    if not isinstance(backend, BufferBackend):
        raise TypeError(f'{entry_point.value} gave {type(backend).__name__}, not a BufferBackend')
    if backend.get_backend_type() != name:
        raise ValueError(f'{entry_point.value}.get_backend_type() returns '
                         f'{backend.get_backend_type()!r} but its entry point is named {name!r}')
    return backend


def _discover() -> Dict[str, BufferBackend]:
    backends: Dict[str, BufferBackend] = {CPU_BACKEND: CpuBackend()}
    seen = set()
    for entry_point in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP),
                              key=lambda ep: (ep.name, ep.value)):
        if (entry_point.name, entry_point.value) in seen:
            continue  # the same distribution visible twice on sys.path
        seen.add((entry_point.name, entry_point.value))
        if entry_point.name in backends:
            _logger.error(f'buffer backend {entry_point.name!r} from {entry_point.value} is '
                          'skipped: another backend already has that name')
            continue
        try:
            backends[entry_point.name] = _load_entry_point(entry_point)
        except BackendUnavailable as exc:
            if _unavailable.get(entry_point.name) != str(exc):
                # debug: a machine without a GPU is no news to a graph that never asks for it;
                # who names the backend is told why (parse_acceptable_buffer_backends,
                # get_backend)
                _logger.debug(f'buffer backend {entry_point.name!r} is unavailable here and is '
                              f'left out: {exc}')
            _unavailable[entry_point.name] = str(exc)
        except Exception as exc:  # a broken plugin must never stop a node from starting
            _logger.error(f'buffer backend {entry_point.name!r} ({entry_point.value}) failed to '
                          f'load and is skipped: {type(exc).__name__}: {exc}')
    return backends


def get_installed_backends(*, refresh: bool = False) -> Mapping[str, BufferBackend]:
    """Return every usable backend by name, ``cpu`` included, loading them on first use.

    :param refresh: Scan the entry points again (for backends installed since the first call).
    """
    global _backends
    with _lock:
        if _backends is None or refresh:
            _backends = _discover()
        return dict(_backends)


def unavailable_backends() -> Mapping[str, str]:
    """Installed backends this machine cannot run (no driver, no device), with the reason."""
    get_installed_backends()
    with _lock:
        return dict(_unavailable)


def get_backend(name: str) -> BufferBackend:
    """Return the installed backend called ``name``; ``KeyError`` names the installed ones."""
    backends = get_installed_backends()
    try:
        return backends[name]
    except KeyError:
        why = _unavailable.get(name)
        if why is not None:
            raise KeyError(f'buffer backend {name!r} is unavailable here: {why}') from None
        raise KeyError(f'buffer backend {name!r} is not installed; installed: '
                       f'{", ".join(sorted(backends))}') from None


def parse_acceptable_buffer_backends(value: Optional[str]) -> FrozenSet[str]:
    """Parse a subscription's ``acceptable_buffer_backends`` into the set of backend names.

    ``None``, ``""`` and ``"cpu"`` mean CPU only; ``"any"`` means every installed backend;
    otherwise a comma-separated list of names (spaces tolerated). ``cpu`` is always in the result:
    CPU data is deliverable as the fallback. A name that is not installed is left out, with one
    warning that names it and lists the installed backends.
    """
    if value is None:
        return frozenset({CPU_BACKEND})
    if not isinstance(value, str):
        raise TypeError('acceptable_buffer_backends must be None or a str such as "cpu", "any" '
                        f'or "demo,cpu", got {type(value).__name__} {value!r}')
    installed = get_installed_backends()
    names = [name.strip() for name in value.split(',')]
    if any(name == ANY_BACKEND for name in names):
        return frozenset(installed)
    accepted = {CPU_BACKEND}
    for name in names:
        if not name:
            continue
        if name in installed:
            accepted.add(name)
            continue
        with _lock:
            first_time = name not in _warned_unknown
            _warned_unknown.add(name)
        if first_time:
            why = _unavailable.get(name)
            _logger.warning(
                f'acceptable_buffer_backends names {name!r}, which is unavailable here ({why}); '
                'it gets CPU bytes' if why is not None else
                f'acceptable_buffer_backends names {name!r}, which is not an installed '
                f'buffer backend; installed: {", ".join(sorted(installed))}')
    return frozenset(accepted)
