"""Types of ``rosidl_buffer_py._native``, the package's only native extension (src/native/).

How each call behaves (pinning, lifetimes, threading, padding) is in ``src/native/README.md``.
Every function taking an endpoint, a node or a guard condition accepts the rclpy entity, its
``.handle`` or the raw pointer int (then the caller keeps it alive). Middleware failures raise
:class:`DdsError`; an entity of another rmw raises :class:`UnsupportedRmwError`; wrong
arguments raise ``TypeError``/``ValueError``.
"""
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

from typing_extensions import Buffer as _Bytes  # anything with the buffer protocol

_Entity = Any      # rclpy entity, its .handle, or a pointer int
_Kind = str        # 'publisher' | 'subscription'
_Info = Dict[str, Any]  # source_timestamp, received_timestamp, publication_sequence_number,
                        # reception_sequence_number, from_intra_process
#: (kind, status, gid, topic, type_name, user_data, participant_gid, local):
#: _dds.EndpointEvent names the fields
_Event = Tuple[str, str, bytes, str, str, bytes, bytes, bool]


class DdsError(RuntimeError):
    """An rcl/rmw/DDS call failed (the message is rmw's)."""


class UnsupportedRmwError(DdsError):
    """The entity is not rmw_fastrtps_cpp's, or the private layout was not verified."""


#: The rmw implementation this layer works with ('rmw_fastrtps_cpp').
RMW_IMPLEMENTATION: str
#: Package -> version compiled against (rmw_fastrtps_cpp, rmw_fastrtps_shared_cpp, fastrtps).
BUILT_AGAINST: Dict[str, str]


def set_private_layout_verified(verified: bool) -> None:
    """Allow (or refuse) every access to rmw_fastrtps's private layout (``_dds.check_abi``)."""


def private_layout_verified() -> bool: ...


# buffers ------------------------------------------------------------------------------------

class BufferBase:
    """Buffer-protocol re-exporter: the base of :class:`rosidl_buffer_py.Buffer`."""

    def __init__(self, exporter: Optional[_Bytes] = None) -> None: ...
    @property
    def _has_host_memory(self) -> bool: ...


# DLPack -------------------------------------------------------------------------------------

def dlpack_capsule(address: int, nbytes: int, device_type: int, device_id: int, owner: object,
                   versioned: bool = False, readonly: bool = False) -> Any:
    """A DLPack capsule (a ``PyCapsule`` named ``'dltensor'``, or ``'dltensor_versioned'``
    with ``versioned``: DLPack 1.0) of a compact 1-D uint8 tensor of ``nbytes`` at
    ``address`` on ``(device_type, device_id)``: 1 kDLCPU, 2 kDLCUDA, 3 kDLCUDAHost. For
    ``__dlpack__``: torch/cupy/numpy ``from_dlpack`` take it without a copy. It holds a
    reference to ``owner`` until the consumer's deleter runs (any thread), or until the
    capsule is destroyed unconsumed. ``readonly`` sets the read-only flag (versioned only).
    Bad values raise ``ValueError``."""


# endpoints ----------------------------------------------------------------------------------

def endpoint_gid(endpoint: _Entity, kind: _Kind) -> bytes:
    """16-byte GID, equal to the graph's ``TopicEndpointInfo.endpoint_gid``."""


def get_user_data(endpoint: _Entity, kind: _Kind) -> bytes:
    """USER_DATA of the DataWriter/DataReader behind the endpoint."""


def set_user_data(endpoint: _Entity, kind: _Kind, data: bytes) -> None:
    """Replace that USER_DATA (keep rmw's ``typehash=...;``: append to :func:`get_user_data`);
    setting it, even to the same bytes, re-announces the endpoint."""


def hold_enabling(node: _Entity, kind: _Kind, hold: bool) -> None:
    """While held, the DataWriters (kind 'publisher') or DataReaders ('subscription') that rmw
    creates with the node's participant are created disabled, so that USER_DATA set on them
    goes out with their first announcement; letting go (``hold`` False) enables every one."""


def take_serialized_with_gid(subscription: _Entity) -> Optional[Tuple[bytes, bytes, _Info]]:
    """Take one serialized message (CDR with its encapsulation header), with the GID of the
    DataWriter that wrote it and an rclpy-like message info dict; None when none is there."""


def take_message_with_gid(subscription: _Entity, msg_class: type, max_size: int = -1,
                          program: Optional[tuple] = None) -> Optional[Tuple[Any, bytes, _Info]]:
    """Take one message, deserialized in C as rclpy's take does (built by the slot ``program``
    where it can: the same message). The first item is a ``msg_class`` instance, or the CDR
    ``bytes`` when they do not deserialize with the type's own type support (a descriptor
    payload, malformed data: for ``codec.decode``) or are longer than ``max_size`` (when
    >= 0)."""


def peek_untaken(subscription: _Entity) -> Optional[Tuple[bytes, int]]:
    """``(publisher_gid, source_timestamp)`` of the next unread sample, from its DDS sample
    info: nothing is taken or copied. None when there is none."""


def discard_untaken(subscription: _Entity) -> Optional[Tuple[bytes, int]]:
    """Take the next unread sample without copying its payload (a duplicate to drop); its key,
    or None when there was none."""


def publish_serialized(publisher: _Entity, data: _Bytes, source_timestamp: int) -> None:
    """Write serialized CDR (any C-contiguous buffer, not copied in Python; do not mutate it
    during the call) on the DataWriter behind an rclpy publisher. ``source_timestamp`` is ns
    since the epoch (0 <= t < 2**31 s); takes report exactly it."""


def write_message(message: Any, source_timestamp: int, targets: Sequence[Any],
                  program: Optional[tuple] = None,
                  descriptor: Optional[Tuple[str, bytes]] = None) -> bool:
    """Write a ROS message to :class:`ChannelPublisher` objects and/or rclpy publishers (or
    their handles) of its type with ``source_timestamp``, converted once: its CDR written from
    its slots by the slot ``program`` where it can (``codec.encode``'s bytes), else to C as
    rclpy's ``publish`` does, serialized by rmw into each target's DDS payload. True.

    With ``descriptor`` (``(backend_type, descriptor bytes)``), its descriptor form
    (``codec.encode(message, descriptor)``'s bytes, ``program`` being
    ``codec.descriptor_program`` of its type) goes to ChannelPublisher targets only; written
    from the slots or not at all: False, nothing written, when the program cannot."""


def matched_subscription_gids(publisher: _Entity) -> List[bytes]:
    """GIDs of the subscriptions matched with the publisher (the set
    ``get_subscription_count()`` counts)."""


def exclude_from_next_write(publisher: _Entity, reader_gids: Sequence[bytes]) -> bool:
    """Keep the next sample written on the publisher's DataWriter from ``reader_gids``: Fast
    DDS sends them a GAP instead. Call right before the write; calling again before it
    replaces the set. False when this DataWriter cannot filter (nothing is excluded then)."""


def remove_write_exclusions(publisher: _Entity) -> None:
    """Take :func:`exclude_from_next_write`'s filter off the DataWriter again."""


def set_new_message_wakeup(subscription: _Entity, guard_condition: _Entity) -> None:
    """Trigger the guard condition on every new message of the subscription (right away when
    some are unread; later only on status changes: take until nothing is left). Replaces an
    earlier wakeup; pins both until :func:`clear_new_message_wakeup`."""


def clear_new_message_wakeup(subscription: _Entity) -> None:
    """Stop the wakeup and unpin (a barrier); a no-op when none is set."""


# discovery ----------------------------------------------------------------------------------

def install_discovery(node: _Entity) -> bool:
    """Install the discovery tap on the node's participant (right after creating the node);
    True if this call installed it."""


def uninstall_discovery(node: _Entity) -> bool:
    """Give rmw its own participant listener back."""


def drain_discovery_events(node: _Entity) -> List[_Event]:
    """Queued endpoint events of the node's participant (one consumer per participant)."""


def list_known_endpoints(node: _Entity) -> List[_Event]:
    """Alive endpoints seen since the tap was installed (status 'known')."""


def add_discovery_wakeup(node: _Entity, guard_condition: _Entity) -> bool:
    """Trigger the guard condition on every discovery event (pinned until removed); False if
    it was already registered."""


def remove_discovery_wakeup(guard_condition: _Entity) -> bool:
    """Stop triggering it and unpin it (a barrier)."""


def discovery_epoch() -> memoryview:
    """8 read-only bytes: the count of discovery callbacks this process's taps passed to rmw
    (``.cast('Q')[0]``); a matched count changes only shortly after one."""


def discovery_stats(node: _Entity) -> Dict[str, int]:
    """installed, queued, known, wakeups, dropped, recorded."""


def silence_discovery(node: _Entity) -> bool:
    """Stop the node's participant listening to discovery (rmw's listener and the tap), with
    bounded waits for running callbacks; True if this call did it. For shutdown and exit."""


def silence_discovery_if_last_node(node: _Entity) -> bool:
    """:func:`silence_discovery` when ``node`` is the only node of its context (rmw destroys
    the participant with it); False, nothing done, while other nodes share it."""


# channels -----------------------------------------------------------------------------------

class ChannelPublisher:
    """An rmw publisher below rcl on a full DDS topic name (volatile)."""

    gid: bytes
    topic_name: str
    valid: bool

    def __init__(self, node: _Entity, type_support: Any, topic_name: str,
                 reliability: int = 1, history: int = 1, depth: int = 10) -> None: ...
    def publish(self, data: _Bytes, source_timestamp: Optional[int] = None) -> None: ...
    def matched_count(self) -> int: ...
    def matched_gids(self) -> List[bytes]: ...
    def wait_for_all_acked(self, timeout_sec: float) -> bool: ...
    def destroy(self) -> None: ...


class ChannelSubscription:
    """An rmw subscription below rcl on a full DDS topic name; new data triggers
    ``guard_condition``."""

    gid: bytes
    topic_name: str
    valid: bool
    #: samples announced to the guard condition and not taken since (1 without one): 0 means
    #: every sample left will trigger it (again), so the channel need not be taken now
    pending: int
    on_udp: bool

    def __init__(self, node: _Entity, type_support: Any, topic_name: str,
                 reliability: int = 1, history: int = 1, depth: int = 10,
                 guard_condition: Optional[_Entity] = None) -> None: ...
    def take(self) -> Optional[Tuple[bytes, bytes, _Info]]: ...
    def take_message(self, msg_class: type,
                     max_size: int = -1) -> Optional[Tuple[Any, bytes, _Info]]: ...
    def take_described(self, msg_class: type, prefix_ops: tuple, suffix_size: int,
                       max_descriptor: int, program: Optional[tuple] = None
                       ) -> Optional[Tuple[bytes, bytes, _Info,
                                           Optional[Tuple[Any, str, bytes]]]]:
        """take(), and the descriptor message in the bytes decoded as ``decode_descriptor``
        decodes it (``codec.DescriptorReading.args``), or None for anything else."""
    def matched_count(self) -> int: ...
    def destroy(self) -> None: ...


# codec --------------------------------------------------------------------------------------

def encode_descriptor(msg: Any, slots: Any, payload_slot: Any, empty: Any, backend: bytes,
                      descriptor: bytes, suffix_size: int,
                      program: Optional[tuple] = None) -> Optional[bytearray]:
    """``codec.encode`` of the descriptor form for a compiled plan; None when it cannot.
    Written from the slots by ``program`` (``codec.plans.slot_program``) where it can, else
    from a payload-free clone by the type support: the same bytes."""


def decode_descriptor(raw: _Bytes, msg_class: type, prefix_ops: Any, suffix_size: int,
                      max_descriptor: int,
                      program: Optional[tuple] = None) -> Optional[Tuple[Any, str, bytes]]:
    """``codec.decode`` of descriptor-encoded CDR; None for anything else. The message is
    built from its slots by ``program`` where it can, else by the type support and the
    generated convert_to_py: the same message."""


def serialize(msg: Any, program: tuple) -> Optional[bytearray]:
    """The CDR of ``msg`` written from its slots by a slot program: ``codec.encode(msg)``'s
    bytes, or None where the program cannot write them exactly as the type support would."""


def deserialize(raw: _Bytes, program: tuple) -> Any:
    """CDR built into a message by a slot program (``codec.plans.slot_program``): the message
    ``deserialize_message`` gives, or None where the program cannot build it exactly so."""


# sockets ------------------------------------------------------------------------------------

def recv_records(fd: int, size: int) -> Tuple[bytes, bool]:
    """``(records, hung_up)``: the records of exactly ``size`` bytes queued on a SOCK_SEQPACKET
    socket, joined (others skipped), read without blocking and without raising when none is
    left; ``hung_up`` when the peer closed or the socket failed."""


class LedgerCore:
    """The rules of a demo backend endpoint ledger, run natively: the base of
    :class:`demo_buffer_backend.ledgers.EndpointLedger`, which supplies ``_share``."""

    token: str
    seq: int
    per_channel: bool
    depth: Optional[int]
    delivered: Optional[Callable[[], bool]]

    def __init__(self, token: str, depth: Optional[int], per_channel: bool,
                 delivered: Optional[Callable[[], bool]], limits: Any) -> None: ...
    @property
    def in_flight(self) -> int: ...
    def record(self, slot: Any) -> None: ...
    def settle(self, counters: Any) -> None: ...
    def full(self) -> bool: ...
    def _entries(self) -> List[Tuple[Any, int, int]]: ...


def describe_linked(accepted: int, pool: Any, pin: Any, ledger: Any) -> Optional[bytes]:
    """The pin's packed descriptor for the ledger's endpoint, recorded in flight, as
    :meth:`demo_buffer_backend.pool.Pool.describe` makes it for a current pin and an endpoint of
    another process that mapped the segment (its verdict ``accepted``) and has room; None,
    with nothing changed, for anything else."""


def describe_steady(accepted: int, pool: Any, ledger: Any, buffer: Any) -> Optional[bytes]:
    """:func:`describe_linked` for ``buffer``'s pin under ``pool.guard``, taken and let go as
    ``with pool.guard:`` does (a publisher's steady describer, see
    :meth:`demo_buffer_backend.pool.Pool.steady_describer`); None for a Buffer without a pin
    and for a closed pool."""


def open_mapped(prefix: bytes, read_lock: bytes, unlock: bytes, counters: Any, raw: Any,
                by_key: Dict[Any, Any], unacked: List[Any], now: float
                ) -> Optional[Tuple[memoryview, Any, int, bool]]:
    """The demo descriptor ``raw`` opened, ``(view, mapping, generation, acknowledged later)``,
    for a well-formed one (its first 8 bytes ``prefix``) of a current segment in ``by_key``,
    as :meth:`demo_buffer_backend.mappings.Mappings.open` opens it; None, with nothing
    changed, for anything else."""
