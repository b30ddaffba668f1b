"""Handing segments to subscriber processes: abstract-namespace Unix sockets and SCM_RIGHTS.

Every process that advertises the demo backend listens on ``\\0rbpy_demo/<token>`` (its token,
``<pid>_<16 hex>``, is in its backend metadata). A publisher connects once per subscriber
process (:class:`Link`) and pushes each segment's descriptor the first time it describes a
frame of that segment to that process, before the frame's descriptor leaves, and waits a
moment for the subscriber's verdict on it; the subscriber screens and drains its connections
from a thread of its own (:mod:`.porter`). Sockets are SOCK_SEQPACKET: one record per message,
its descriptor attached to it. Both sides check the other's credentials (SO_PEERCRED: same
uid; the pid of the token).

Descriptors queued in a socket outlive their sender: a SIGKILLed publisher's segments still
reach the subscriber. The other way, the subscriber answers with small :data:`REPLY` records:
each segment accepted or refused (with the reason, so that the publisher sends CPU bytes
instead of descriptors the subscriber would reject), each take acknowledged, and a connection it
will not serve refused before it is closed. A subscriber that died shows as a hang-up (EOF,
EPIPE, ECONNRESET).
"""
import array
import enum
import errno
import os
import re
import secrets
import select
import socket
import struct
from typing import List, NamedTuple, Optional, Tuple

from rosidl_buffer_py._native import recv_records

TOKEN_PATTERN = re.compile(r'^([1-9][0-9]{0,9})_([0-9a-f]{16})$')
#: magic, publisher nonce, segment id, reserved (0), capacity; one descriptor attached.
HANDOVER = struct.Struct('<8sQIIQ')
HANDOVER_MAGIC = b'RBPYHND1'
#: The same record without a descriptor: the publisher removed that segment (capacity 0).
RETIRE_MAGIC = b'RBPYRET1'
#: segment id, kind (:class:`ReplyKind`), value (a generation or a :class:`Refusal`).
REPLY = struct.Struct('<IIQ')
#: Flags of every send: never block, never SIGPIPE (an int: socket's flags are an IntFlag, whose
#: ``|`` runs Python-level enum code on every call)
_SEND_FLAGS = int(socket.MSG_DONTWAIT | socket.MSG_NOSIGNAL)
_FD_SPACE = socket.CMSG_SPACE(4 * 4)  # room for a few descriptors: extra ones are counted
#: Records taken from one connection per drain: a genuine publisher sends one per new segment,
#: so a flood waits for later drains and costs only its own connection's turn.
MAX_RECORDS_PER_DRAIN = 16


class ReplyKind(enum.IntEnum):
    """What a :data:`REPLY` record from a subscriber process says."""

    TAKEN = 0     #: one descriptor of generation ``value`` of the segment was taken
    ACCEPTED = 1  #: the segment is mapped: descriptors of it will be opened
    REFUSED = 2   #: the segment is not mapped (``value``: the :class:`Refusal`)
    UNWANTED = 3  #: this connection is refused as a whole (``value``: why); it closes next


class Refusal(enum.IntEnum):
    """Why a subscriber process refused a segment or a connection."""

    PROCESS_LIMIT = 1  #: the sender has as many segments mapped as one process may
    TOTAL_LIMIT = 2    #: this process has as many segments mapped as it may, or cannot map more
    INVALID = 3        #: not a segment as the demo backend makes them
    UNMATCHED = 4      #: the sender is not a buffer-aware publisher this process discovered

    def describe(self) -> str:
        return _REFUSAL_TEXT.get(self, f'refusal {int(self)}')


_REFUSAL_TEXT = {
    Refusal.PROCESS_LIMIT: 'it maps at most limits.MAX_MAPPINGS_PER_PROCESS segments of one '
                           'publisher process',
    Refusal.TOTAL_LIMIT: 'it has no room for more segments (limits.MAX_MAPPINGS in all, or '
                         'its memory or descriptors ran out)',
    Refusal.INVALID: 'the segment is not one the demo backend makes',
    Refusal.UNMATCHED: 'discovery did not show this process as a buffer-aware publisher '
                       'matched to it',
}


class Reply(NamedTuple):
    """One :data:`REPLY` record (its fields in wire order)."""

    segment_id: int
    kind: int  #: a :class:`ReplyKind` (an unknown kind is ignored)
    value: int
_GONE = (errno.EPIPE, errno.ECONNRESET, errno.ECONNREFUSED, errno.ENOENT, errno.ENOTCONN)


class ProcessGone(Exception):
    """The process at the other end of a link is gone (or never listened)."""


class Credentials(NamedTuple):
    pid: int
    uid: int
    gid: int


class Handover(NamedTuple):
    """One segment a publisher process handed to us (``fds`` are ours to close: as many as
    its medium hands over per segment), or, with no ``fds``, one it retired."""

    nonce: int
    segment_id: int
    capacity: int
    fds: Tuple[int, ...]


def new_token() -> str:
    return f'{os.getpid()}_{secrets.token_hex(8)}'


def parse_token(text: str) -> Optional[str]:
    """``text`` when it is a well-formed token (it comes from the network), else None."""
    return text if isinstance(text, str) and TOKEN_PATTERN.match(text) else None


def token_pid(token: str) -> int:
    return int(token.partition('_')[0])


#: The medium name of the demo backend's listeners (``\\0rbpy_demo/<token>``).
DEMO = 'demo'


def _address(token: str, medium: str) -> str:
    return f'\0rbpy_{medium}/{token}'


def domain() -> str:
    """Who can reach our listeners and check our credentials: the same boot, network, mount
    and pid namespaces and effective uid (hex; printable ASCII without ``;`` or ``=``)."""
    try:
        with open('/proc/sys/kernel/random/boot_id') as f:
            boot = f.read().strip().replace('-', '').lower()
    except OSError:
        boot = 'noboot'
    inodes = []
    for ns in ('net', 'mnt', 'pid'):
        try:
            inodes.append(f'{os.stat(f"/proc/self/ns/{ns}").st_ino:x}')
        except OSError:
            inodes.append('0')
    return f'mfd1.{boot}.{".".join(inodes)}.{os.geteuid():x}'


def credentials(sock: socket.socket) -> Credentials:
    raw = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize('3i'))
    return Credentials(*struct.unpack('3i', raw))


def _new_socket() -> socket.socket:
    return socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)


class Listener:
    """The subscriber side: this process's listening socket and the links accepted on it."""

    def __init__(self, token: str, medium: str = DEMO) -> None:
        self.token = token
        self.sock = _new_socket()
        try:
            self.sock.bind(_address(token, medium))
            self.sock.listen(64)
            self.sock.setblocking(False)
        except BaseException:
            self.sock.close()
            raise

    def accept(self) -> List[Tuple[socket.socket, Credentials]]:
        """Every pending connection with its peer's credentials (non-blocking)."""
        accepted = []
        while True:
            try:
                conn, _ = self.sock.accept()
            except (BlockingIOError, InterruptedError):
                return accepted
            except OSError:  # ECONNABORTED and the like: that one is gone
                continue
            conn.setblocking(False)
            accepted.append((conn, credentials(conn)))

    def close(self) -> None:
        self.sock.close()


def receive(conn: socket.socket,
            fds_per_segment: int = 1) -> Tuple[List[Handover], List[str], bool]:
    """Drain ``conn`` without blocking: ``(handovers, reasons for rejected records, hung up)``;
    a handover carries ``fds_per_segment`` descriptors (its medium's).
    Stops at the first malformed record (a genuine publisher sends none: the caller closes the
    connection). Every descriptor received but not returned in a handover is closed here."""
    handovers: List[Handover] = []
    rejected: List[str] = []
    for _ in range(MAX_RECORDS_PER_DRAIN):
        try:
            data, ancdata, flags, _ = conn.recvmsg(HANDOVER.size + 1, _FD_SPACE)
        except (BlockingIOError, InterruptedError):
            return handovers, rejected, False
        except OSError:
            return handovers, rejected, True
        fds = array.array('i')
        for level, kind, payload in ancdata:
            if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
                fds.frombytes(payload[:len(payload) - len(payload) % fds.itemsize])
        if not data and not fds:
            return handovers, rejected, True  # EOF: SEQPACKET never carries empty records
        problem = None
        if flags & (socket.MSG_TRUNC | socket.MSG_CTRUNC):
            problem = f'a truncated record ({len(data)} bytes, flags {flags:#x})'
        elif len(data) != HANDOVER.size:
            problem = f'a record of {len(data)} bytes, expected {HANDOVER.size}'
        else:
            magic, nonce, segment_id, reserved, capacity = HANDOVER.unpack(data)
            expected = {HANDOVER_MAGIC: fds_per_segment, RETIRE_MAGIC: 0}.get(magic)
            if expected is None or reserved:
                problem = f'a record with magic {magic!r} / reserved {reserved}'
            elif len(fds) != expected:
                problem = f'a {magic!r} record with {len(fds)} descriptors, expected {expected}'
        if problem is None:
            handovers.append(Handover(nonce, segment_id, capacity, tuple(fds)))
        else:
            rejected.append(problem)
            for fd in fds:
                os.close(fd)
            return handovers, rejected, False
    return handovers, rejected, False  # the rest waits for the next drain


def send_reply(conn: socket.socket, kind: ReplyKind, segment_id: int = 0, value: int = 0) -> bool:
    """Answer the publisher at the other end of ``conn`` (never blocks; False when it could
    not: its queue is full or it hung up)."""
    try:
        conn.send(REPLY.pack(segment_id, kind, value), _SEND_FLAGS)
        return True
    except OSError:
        return False


class Link:
    """The publisher side: a connection to one subscriber process."""

    __slots__ = ('token', 'sock', 'segments', 'verdicts', 'responsive')

    def __init__(self, token: str, medium: str = DEMO) -> None:
        """Connect to ``token``'s listener of ``medium`` without waiting. ``ProcessGone`` when
        nobody listens there; ``PermissionError`` when who listens is not that process of our
        user; ``BlockingIOError`` when its backlog is full (a stopped process: try again
        later)."""
        self.token = token
        self.segments: set = set()  #: ids of the segments handed over on this link
        #: segment id -> the subscriber's verdict on it (ACCEPTED or REFUSED, and the refusal)
        self.verdicts: dict = {}
        #: whether a publisher waits for verdicts: False once one was late (until one comes)
        self.responsive = True
        self.sock = _new_socket()
        try:
            self.sock.setblocking(False)
            self.sock.connect(_address(token, medium))
            cred = credentials(self.sock)
            if cred.uid != os.geteuid() or cred.pid != token_pid(token):
                raise PermissionError(
                    f'the listener of demo token {token} is pid {cred.pid} uid {cred.uid}, '
                    f'expected pid {token_pid(token)} uid {os.geteuid()}')
        except OSError as exc:
            self.sock.close()
            if exc.errno in _GONE:
                raise ProcessGone(f'nobody listens for demo token {token}: {exc}') from None
            raise

    def hand_over(self, nonce: int, segment_id: int, capacity: int, fds: List[int]) -> None:
        """Push one segment's descriptors. ``ProcessGone`` when the subscriber hung up;
        ``BlockingIOError`` when its queue is full (try again with a later frame)."""
        record = HANDOVER.pack(HANDOVER_MAGIC, nonce, segment_id, 0, capacity)
        try:
            socket.send_fds(self.sock, [record], fds, _SEND_FLAGS)
        except OSError as exc:
            if exc.errno in _GONE:
                raise ProcessGone(f'demo subscriber {self.token} hung up: {exc}') from None
            raise
        self.segments.add(segment_id)

    def retire(self, nonce: int, segment_id: int) -> None:
        """Tell the subscriber a segment it holds is removed (best effort, never blocks)."""
        if segment_id in self.segments:
            self.segments.discard(segment_id)
            self.verdicts.pop(segment_id, None)
            try:
                self.sock.send(HANDOVER.pack(RETIRE_MAGIC, nonce, segment_id, 0, 0),
                               _SEND_FLAGS)
            except OSError:
                pass  # gone or full: it drops the segment when we hang up

    def accepted(self, segment_id: int) -> bool:
        """Whether the subscriber process said it mapped the segment."""
        verdict = self.verdicts.get(segment_id)
        return verdict is not None and verdict.kind == ReplyKind.ACCEPTED

    def replies(self) -> Tuple[List[Reply], bool]:
        """``(replies received since the last call, hung up)``: what the subscriber said before
        it hung up is returned too (a refusal comes just before its subscriber closes). Read in
        C (:func:`rosidl_buffer_py._native.recv_records`): a drain that finds nothing raises
        nothing, which matters on the publish path, where most drains find one ack or none."""
        data, hung_up = recv_records(self.sock.fileno(), REPLY.size)
        return [Reply(*fields) for fields in REPLY.iter_unpack(data)], hung_up

    def wait_readable(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for a reply or a hang-up (call it without the pool's
        lock held); True when there is one."""
        poller = select.poll()
        poller.register(self.sock, select.POLLIN)
        return bool(poller.poll(max(0, int(timeout * 1000))))

    def close(self) -> None:
        self.sock.close()
