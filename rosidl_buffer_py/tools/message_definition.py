"""Message types by name, and their full definition text as rosbag2 stores it in a bag.

rosbag2 writes, for each recorded type, a *complete message definition*: the type's ``.msg``
text followed by the text of every type it uses, recursively, each after a two-line delimiter
(80 ``=`` then ``MSG: <pkg>/<Type>``) -- the ``ros2msg`` schema encoding of its MCAP storage
(rosbag2's ``docs/message_definition_encoding.md``). Types without a ``.msg`` file fall back to
``ros2idl``: every ``.idl`` text after an ``IDL: <pkg>/msg/<Type>`` delimiter.

:func:`full_definition` reproduces rosbag2's ``LocalMessageDefinitionSource``: dependencies are
the non-primitive field types found by the same regular expression, visited depth first in
sorted order, each once; texts are the installed files, unchanged. The files are looked up in
``<prefix>/share/<pkg>/msg/`` for every prefix of ``AMENT_PREFIX_PATH`` and then the
interpreter's own prefix (where the PyPI ROS wheels put them: a venv made by ``./dev``).
"""
import importlib
import json
import os
import re
import sys
from pathlib import Path
from typing import List, NamedTuple, Optional, Type

__all__ = [
    'DefinitionNotFoundError',
    'MessageDefinition',
    'full_definition',
    'import_message_type',
    'type_hash',
    'type_name',
]

#: rosbag2's delimiter line before every dependency's text.
DELIMITER = '=' * 80 + '\n'

# The field types of a .msg text ("foo_msgs/Bar" in "foo_msgs/Bar[] bar"), rosbag2's expression.
_MSG_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
_IDL_INCLUDE = re.compile(r'(?:^|\n)#include\s+(?:"|<)([a-zA-Z0-9_/]+)\.idl(?:"|>)')
_PRIMITIVES = frozenset({'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16',
                         'uint16', 'int32', 'uint32', 'int64', 'uint64', 'string'})
_NAME = re.compile(r'^([a-zA-Z][a-zA-Z0-9_]*)/(?:([a-zA-Z][a-zA-Z0-9_]*)/)?'
                   r'([a-zA-Z][a-zA-Z0-9_]*)$')
_MAX_DEPTH = 50


class DefinitionNotFoundError(LookupError):
    """No installed ``.msg`` or ``.idl`` file for a type; the message names the paths tried."""


class MessageDefinition(NamedTuple):
    """A schema as rosbag2 writes it: ``encoding`` is ``ros2msg`` or ``ros2idl``."""

    encoding: str
    text: str


def _parse_name(name: str):
    match = _NAME.match(name)
    if match is None:
        raise ValueError(f'{name!r} is not a message type name; expected "pkg/msg/Type" or '
                         '"pkg/Type"')
    package, namespace, type_ = match.groups()
    return package, namespace or 'msg', type_


def share_directories(package: str) -> List[Path]:
    """Candidate ``share/<package>`` directories, most preferred first."""
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    return [Path(p) / 'share' / package for p in dict.fromkeys(prefixes)]


def _read_interface(name: str, extension: str) -> str:
    package, namespace, type_ = _parse_name(name)
    tried = []
    for share in share_directories(package):
        path = share / namespace / f'{type_}{extension}'
        tried.append(str(path))
        if path.is_file():
            return path.read_text(encoding='utf-8')
    raise DefinitionNotFoundError(f'no {extension} file for {name}; tried {", ".join(tried)}')


def _msg_dependencies(text: str, package: str) -> List[str]:
    found = set()
    for match in _MSG_FIELD_TYPE.finditer(text):
        field_type = match.group(1)
        if field_type in _PRIMITIVES:
            continue
        found.add(field_type if '/' in field_type else f'{package}/{field_type}')
    return sorted(found)


def _idl_dependencies(text: str, package: str) -> List[str]:
    return sorted({match.group(1) for match in _IDL_INCLUDE.finditer(text)})


def _complete(root: str, extension: str, dependencies, kind: str) -> str:
    seen = set()

    def append(name: str, depth: int) -> str:
        if depth <= 0:
            raise RecursionError(f'message definition of {root} nests more than {_MAX_DEPTH} '
                                 'levels deep')
        text = _read_interface(name, extension)
        result = text
        for dependency in dependencies(text, _parse_name(name)[0]):
            if dependency not in seen:
                seen.add(dependency)
                result += '\n' + DELIMITER + f'{kind}: {dependency}\n'
                result += append(dependency, depth - 1)
        return result

    return append(root, _MAX_DEPTH)


def full_definition(name: str) -> MessageDefinition:
    """The complete definition of message type ``name`` (``"sensor_msgs/msg/Image"``).

    :raises DefinitionNotFoundError: when neither the ``.msg`` nor the ``.idl`` files of the
        type or of one of its dependencies are installed.
    """
    try:
        return MessageDefinition('ros2msg', _complete(name, '.msg', _msg_dependencies, 'MSG'))
    except DefinitionNotFoundError as msg_error:
        try:
            text = _complete(name, '.idl', _idl_dependencies, 'IDL')
        except DefinitionNotFoundError:
            raise msg_error from None
        return MessageDefinition('ros2idl', DELIMITER + f'IDL: {name}\n' + text)


def type_hash(name: str) -> str:
    """The type's ``RIHS01_<hex>`` hash from its installed type description, or ``''``."""
    try:
        description = json.loads(_read_interface(name, '.json'))
    except (DefinitionNotFoundError, ValueError):
        return ''
    package, namespace, type_ = _parse_name(name)
    for entry in description.get('type_hashes', ()):
        if entry.get('type_name') == f'{package}/{namespace}/{type_}':
            return entry.get('hash_string', '')
    return ''


def import_message_type(name: str) -> Type:
    """The generated Python class of ``name`` (``"sensor_msgs/msg/Image"``).

    :raises ValueError: when the name is malformed or the type cannot be imported.
    """
    package, namespace, type_ = _parse_name(name)
    try:
        module = importlib.import_module(f'{package}.{namespace}')
        cls = getattr(module, type_)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f'cannot import message type {name}: {exc}') from None
    if not hasattr(cls, 'SLOT_TYPES'):
        raise ValueError(f'{name} is not a generated message type')
    return cls


def type_name(msg_type: Type) -> str:
    """``"pkg/msg/Type"`` of a generated message class."""
    module = msg_type.__module__.split('.')
    return f'{module[0]}/{module[1]}/{msg_type.__name__}'


def definition_or_none(name: str) -> Optional[MessageDefinition]:
    """:func:`full_definition`, or ``None`` when no definition is installed."""
    try:
        return full_definition(name)
    except (DefinitionNotFoundError, ValueError, RecursionError):
        return None
