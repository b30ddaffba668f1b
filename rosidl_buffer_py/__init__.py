"""rosidl_buffer_py: zero-copy uint8[] payloads for rclpy on stock ROS 2 Jazzy.

The pieces, each in its own module:

- :mod:`.buffer`: :class:`Buffer`, a payload held in backend memory;
- :mod:`.backend`: the :class:`BufferBackend` plugin interface and :class:`EndpointInfo`;
- :mod:`.registry`: backend discovery from entry points, ``acceptable_buffer_backends`` parsing;
- :mod:`.message_support`: ``msg.data = buffer`` for generated message classes;
- :mod:`.codec`: the wire format (legacy CDR bytes, or a descriptor behind a marker);
- :mod:`.image`: numpy views and copies of ``sensor_msgs/Image``;
- :mod:`.advertisement`, :mod:`.discovery`, :mod:`.channel`: who supports which backend, and
  the per-endpoint channels;
- :mod:`.publisher`, :mod:`.subscription`: :func:`create_publisher`, :func:`create_subscription`.

Beside the library, and built on it (it imports neither): :mod:`.tools`, the command-line tools
(recorder, player, bag repair, topic inspector), and :mod:`.nodes`, the runnable image nodes.
"""
#: The package's version (package.xml's <version>, which setup.py reads too).
__version__ = '0.1.0'

from rosidl_buffer_py.backend import (  # noqa: E402 (after __version__, readable without ROS)
    BufferBackend, EndpointInfo, EndpointKind, MAX_DESCRIPTOR_SIZE)
from rosidl_buffer_py.buffer import Buffer
from rosidl_buffer_py.message_support import buffer_fields, enable_buffer_fields
from rosidl_buffer_py.publisher import Publisher, create_publisher
from rosidl_buffer_py.subscription import Subscription, create_subscription
from rosidl_buffer_py.registry import (
    get_backend, get_installed_backends, parse_acceptable_buffer_backends)

from rosidl_buffer_py import message_support as _message_support

_message_support.enable_all_message_types()

__all__ = [
    '__version__',
    'Buffer',
    'BufferBackend',
    'EndpointInfo',
    'EndpointKind',
    'MAX_DESCRIPTOR_SIZE',
    'Publisher',
    'Subscription',
    'buffer_fields',
    'create_publisher',
    'create_subscription',
    'enable_buffer_fields',
    'get_backend',
    'get_installed_backends',
    'parse_acceptable_buffer_backends',
]
