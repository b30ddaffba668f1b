"""Where a field sits in a message: :class:`FieldPath`, and :func:`get_at` / :func:`set_at`.

A path is a tuple of field names (``str``) and element indices (``int``), from the message down:
``('data',)`` is ``msg.data``, ``('image', 'data')`` is ``msg.image.data`` (stereo_msgs'
DisparityImage), ``('images', 3, 'data')`` is ``msg.images[3].data``. A *template* path, as
:func:`rosidl_buffer_py.codec.buffer_paths` gives for a message type, has :data:`EACH` where an
element index of a sequence or array of messages goes: ``('images', EACH, 'data')``.

:class:`FieldPath` is a ``tuple`` (it compares and hashes as one, so ``('image', 'data')`` finds
it in a dict) that prints as the field would be written in Python: ``images[3].data``.
"""
import re
from typing import Any, Iterable, Union

__all__ = ['EACH', 'FieldPath', 'get_at', 'set_at']

#: The element index of a template path: any element of a sequence or array of messages.
EACH = Ellipsis

_PART = re.compile(r'\s*(?:\.?\s*([A-Za-z_][A-Za-z0-9_]*)|\[\s*(\d+|\*)\s*\])')


class FieldPath(tuple):
    """A field of a message: field names and element indices, outermost first."""

    __slots__ = ()

    def __new__(cls, parts: Iterable[Union[str, int]] = ()) -> 'FieldPath':
        if isinstance(parts, str):
            return cls.parse(parts)
        path = super().__new__(cls, parts)
        for part in path:
            if not (isinstance(part, str) and part) and part is not EACH and not (
                    isinstance(part, int) and not isinstance(part, bool) and part >= 0):
                raise ValueError(f'a field path holds field names and element indices >= 0, '
                                 f'got {part!r} in {tuple(path)!r}')
        return path

    @classmethod
    def parse(cls, text: str) -> 'FieldPath':
        """The path written as in Python: ``'image.data'``, ``'images[3].data'`` (``[*]``:
        :data:`EACH`)."""
        parts = []
        pos = 0
        while pos < len(text):
            match = _PART.match(text, pos)
            if match is None or match.end() == pos:
                raise ValueError(f'cannot read a field path from {text!r} (at offset {pos})')
            name, index = match.groups()
            parts.append(name if name is not None else EACH if index == '*' else int(index))
            pos = match.end()
        if not parts:
            raise ValueError('an empty field path')
        return tuple.__new__(cls, parts)

    @property
    def is_template(self) -> bool:
        """True when an element index is :data:`EACH` (a path of a type, not of a message)."""
        return EACH in self

    def __str__(self) -> str:
        out = ''
        for part in self:
            if isinstance(part, str):
                out += f'.{part}' if out else part
            else:
                out += '[*]' if part is EACH else f'[{part}]'
        return out

    def __repr__(self) -> str:
        return f'FieldPath({str(self)!r})'


def get_at(msg: Any, path: Iterable[Union[str, int]]) -> Any:
    """The value at ``path`` in ``msg`` (``msg.images[3].data`` for ``('images', 3, 'data')``).

    :raises LookupError: when ``msg`` has no such field or element; the message names the path.
    """
    value = msg
    done = []
    for part in path:
        try:
            value = value[part] if isinstance(part, int) else getattr(value, part)
        except (AttributeError, IndexError, KeyError, TypeError):
            raise LookupError(f'{type(msg).__name__} has no {FieldPath(done + [part])}') \
                from None
        done.append(part)
    return value


def set_at(msg: Any, path: Iterable[Union[str, int]], value: Any) -> None:
    """Set the field (or element) at ``path`` in ``msg`` to ``value``, through the generated
    setter: a ``uint8[]`` field keeps a :class:`~rosidl_buffer_py.Buffer` as it is (see
    :func:`~rosidl_buffer_py.enable_buffer_fields`), other values are checked as usual.

    :raises LookupError: when the field's parent does not exist.
    """
    path = tuple(path)
    if not path:
        raise LookupError('an empty field path names no field')
    parent = get_at(msg, path[:-1]) if len(path) > 1 else msg  # (a top-level field: no walk)
    last = path[-1]
    if isinstance(last, int):
        try:
            parent[last] = value
        except (IndexError, TypeError):
            raise LookupError(f'{type(msg).__name__} has no {FieldPath(path)}') from None
    elif not hasattr(type(parent), last):
        raise LookupError(f'{type(msg).__name__} has no {FieldPath(path)}')
    else:
        setattr(parent, last, value)
