"""Let generated message classes hold a :class:`Buffer` in their ``uint8[]`` fields.

Stock generated setters turn anything that is not an ``array.array('B')`` into one, which would
copy a Buffer's bytes (or fail). :func:`enable_buffer_fields` wraps the setter of each
``uint8[]`` field of a message class so that a Buffer is stored as-is; every other value goes to
the original setter untouched. ``import rosidl_buffer_py`` enables the common image types, and the
package's publishers, subscriptions and codec enable any type they are given.
"""
import threading
from typing import Tuple, Type

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


def enable_buffer_fields(msg_type: Type) -> Tuple[str, ...]:
    """Make ``msg.<field> = buffer`` store the Buffer for every ``uint8[]`` field of ``msg_type``.

    Idempotent and thread-safe. Returns the names of the fields it covers.
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
        return names


def enable_common_types() -> None:
    """Enable the message types users publish images and blobs with."""
    from sensor_msgs.msg import CompressedImage, Image
    for msg_type in (Image, CompressedImage):
        enable_buffer_fields(msg_type)
