"""Let generated message classes hold a :class:`Buffer` in their ``uint8[]`` fields.

Stock generated setters turn anything that is not an ``array.array('B')`` into one, which would
copy a Buffer's bytes (or fail). :func:`enable_buffer_fields` wraps the setter of each
``uint8[]`` field of a message class so that a Buffer is stored as-is; every other value goes to
the original setter untouched.

Enabling a class also enables the message classes of its fields, at any depth, so that
``disparity.image.data = buffer`` and ``pair.left.data = buffer`` keep the Buffer too.

``import rosidl_buffer_py`` enables every generated message class: those already imported, and,
through a meta path hook on generated message modules (``<pkg>.msg._<name>``, also ``srv`` and
``action``), every one imported later.
"""
import importlib
import importlib.abc
import re
import sys
import threading
from typing import List, Tuple, Type

from rosidl_parser import definition

from rosidl_buffer_py.buffer import Buffer

_UINT8_SEQUENCE = 'sequence<uint8>'
_lock = threading.Lock()
_ATTR = '_rosidl_buffer_py_fields'


def buffer_fields(msg_type: Type) -> Tuple[str, ...]:
    """Return the names of the top-level unbounded ``uint8[]`` fields of ``msg_type``."""
    try:
        fields = msg_type.get_fields_and_field_types()
    except AttributeError:
        raise TypeError(f'{msg_type!r} is not a generated ROS message class') from None
    return tuple(name for name, kind in fields.items() if kind == _UINT8_SEQUENCE)


def _buffer_aware_property(original: property) -> property:
    slot = '_' + original.fget.__name__
    original_set = original.fset

    def setter(self, value):
        if isinstance(value, Buffer):
            setattr(self, slot, value)
        else:
            original_set(self, value)

    setter.__name__ = original.fset.__name__
    setter.__doc__ = original.fset.__doc__
    setter.__wrapped__ = original_set
    return property(original.fget, setter, original.fdel, original.__doc__)


def _nested_types(msg_type: Type) -> List[Type]:
    """The message classes of ``msg_type``'s fields (alone, or as elements of an array or
    sequence); those that cannot be imported are left out."""
    nested = []
    for slot_type in getattr(msg_type, 'SLOT_TYPES', ()):
        value_type = getattr(slot_type, 'value_type', slot_type)
        if isinstance(value_type, definition.NamespacedType):
            try:
                module = importlib.import_module('.'.join(value_type.namespaces))
                nested.append(getattr(module, value_type.name))
            except (ImportError, AttributeError):
                continue
    return nested


def enable_buffer_fields(msg_type: Type) -> Tuple[str, ...]:
    """Make ``msg.<field> = buffer`` store the Buffer for every ``uint8[]`` field of ``msg_type``
    and of every message type it holds, at any depth (``disparity.image.data = buffer``).

    Idempotent and thread-safe. Returns the names of the top-level fields it covers.
    """
    with _lock:
        done = msg_type.__dict__.get(_ATTR)
        if done is not None:
            return done
        names = buffer_fields(msg_type)
        for name in names:
            prop = msg_type.__dict__.get(name)
            if not isinstance(prop, property) or prop.fset is None:
                raise TypeError(f'{msg_type.__name__}.{name} is not a generated field property')
            setattr(msg_type, name, _buffer_aware_property(prop))
        setattr(msg_type, _ATTR, names)
    for nested in _nested_types(msg_type):  # after the lock: it is not reentrant
        enable_buffer_fields(nested)
    return names


#: Generated Python message modules, e.g. ``sensor_msgs.msg._image``.
_GENERATED_MODULE = re.compile(r'^[A-Za-z_]\w*\.(msg|srv|action)\._\w+$')


def enable_module(module) -> None:
    """Enable every generated message class with ``uint8[]`` fields defined in ``module``."""
    for value in list(vars(module).values()):
        if (isinstance(value, type) and value.__module__ == module.__name__ and
                hasattr(value, 'get_fields_and_field_types')):
            try:
                if buffer_fields(value):
                    enable_buffer_fields(value)
            except Exception:  # not a generated message after all: leave it alone
                pass


class _EnablingLoader(importlib.abc.Loader):
    """Runs the real loader of a generated message module, then enables its classes."""

    def __init__(self, loader) -> None:
        self._loader = loader

    def create_module(self, spec):
        return self._loader.create_module(spec)

    def exec_module(self, module) -> None:
        self._loader.exec_module(module)
        enable_module(module)

    def __getattr__(self, name):  # get_filename, get_source, ... of the real loader
        return getattr(self._loader, name)


class _GeneratedModuleFinder(importlib.abc.MetaPathFinder):
    """Wraps the loader of generated message modules found by the other finders."""

    def find_spec(self, fullname, path, target=None):
        if not _GENERATED_MODULE.match(fullname):
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, 'find_spec'):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                if spec.loader is not None and hasattr(spec.loader, 'exec_module'):
                    spec.loader = _EnablingLoader(spec.loader)
                return spec
        return None


def enable_all_message_types() -> None:
    """Enable every generated message class imported so far and every one imported later."""
    with _lock:
        if not any(isinstance(f, _GeneratedModuleFinder) for f in sys.meta_path):
            sys.meta_path.insert(0, _GeneratedModuleFinder())
    for name, module in list(sys.modules.items()):
        if module is not None and _GENERATED_MODULE.match(name):
            enable_module(module)
