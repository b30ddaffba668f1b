"""Handing segments to subscriber processes: abstract-namespace Unix sockets and SCM_RIGHTS.

Every process that advertises the demo backend listens on ``\\0rbpy_demo/<token>`` (its token,
``<pid>_<16 hex>``, is in its backend metadata). A publisher connects once per subscriber
process (:class:`Link`) and pushes each segment's descriptor the first time it describes a
frame of that segment to that process, before the frame's descriptor leaves; the subscriber
drains its connections when it resolves a descriptor. Sockets are SOCK_SEQPACKET: one record
per message, its descriptor attached to it. Both sides check the other's credentials
(SO_PEERCRED: same uid; the pid of the token).

Descriptors queued in a socket outlive their sender: a SIGKILLed publisher's segments still
reach the subscriber. The other way, the subscriber acknowledges each take with a small record
(:data:`ACK`); a subscriber that died shows as a hang-up (EOF, EPIPE, ECONNRESET).
"""
import array
import errno
import os
import re
import secrets
import socket
import struct
from typing import List, NamedTuple, Optional, Tuple

TOKEN_PATTERN = re.compile(r'^([1-9][0-9]{0,9})_([0-9a-f]{16})$')
#: magic, publisher nonce, segment id, reserved (0), capacity; one descriptor attached.
HANDOVER = struct.Struct('<8sQIIQ')
HANDOVER_MAGIC = b'RBPYHND1'
#: The same record without a descriptor: the publisher removed that segment (capacity 0).
RETIRE_MAGIC = b'RBPYRET1'
#: segment id, reserved (0), generation: "one descriptor of this generation was taken".
ACK = struct.Struct('<IIQ')
_FD_SPACE = socket.CMSG_SPACE(4 * 4)  # room for a few descriptors: extra ones are counted
#: Records taken from one connection per drain (a sender cannot keep a drain going for ever).
MAX_RECORDS_PER_DRAIN = 256
_GONE = (errno.EPIPE, errno.ECONNRESET, errno.ECONNREFUSED, errno.ENOENT, errno.ENOTCONN)


class ProcessGone(Exception):
    """The process at the other end of a link is gone (or never listened)."""


class Credentials(NamedTuple):
    pid: int
    uid: int
    gid: int


class Handover(NamedTuple):
    """One segment a publisher process handed to us (``fd`` is ours to close), or, with
    ``fd`` -1, one it retired."""

    nonce: int
    segment_id: int
    capacity: int
    fd: int


def new_token() -> str:
    return f'{os.getpid()}_{secrets.token_hex(8)}'


def parse_token(text: str) -> Optional[str]:
    """``text`` when it is a well-formed token (it comes from the network), else None."""
    return text if isinstance(text, str) and TOKEN_PATTERN.match(text) else None


def token_pid(token: str) -> int:
    return int(token.partition('_')[0])


def _address(token: str) -> str:
    return f'\0rbpy_demo/{token}'


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

    def __init__(self, token: str) -> None:
        self.token = token
        self.sock = _new_socket()
        try:
            self.sock.bind(_address(token))
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


def receive(conn: socket.socket) -> Tuple[List[Handover], List[str], bool]:
    """Drain ``conn`` without blocking: ``(handovers, reasons for rejected records, hung up)``.
    Every descriptor received but not returned in a handover is closed here."""
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
            expected = {HANDOVER_MAGIC: 1, RETIRE_MAGIC: 0}.get(magic)
            if expected is None or reserved:
                problem = f'a record with magic {magic!r} / reserved {reserved}'
            elif len(fds) != expected:
                problem = f'a {magic!r} record with {len(fds)} descriptors, expected {expected}'
        if problem is None:
            handovers.append(Handover(nonce, segment_id, capacity, fds[0] if fds else -1))
        else:
            rejected.append(problem)
            for fd in fds:
                os.close(fd)
    return handovers, rejected, False  # the rest waits for the next drain


def send_ack(conn: socket.socket, segment_id: int, generation: int) -> bool:
    """Tell the publisher one descriptor was taken (never blocks; False when it could not)."""
    try:
        conn.send(ACK.pack(segment_id, 0, generation), socket.MSG_DONTWAIT | socket.MSG_NOSIGNAL)
        return True
    except OSError:
        return False


class Link:
    """The publisher side: a connection to one subscriber process."""

    __slots__ = ('token', 'sock', 'segments')

    def __init__(self, token: str) -> None:
        """Connect to ``token``'s listener without waiting. ``ProcessGone`` when nobody listens
        there; ``PermissionError`` when who listens is not that process of our user;
        ``BlockingIOError`` when its backlog is full (a stopped process: try again later)."""
        self.token = token
        self.segments: set = set()  #: ids of the segments handed over on this link
        self.sock = _new_socket()
        try:
            self.sock.setblocking(False)
            self.sock.connect(_address(token))
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

    def hand_over(self, nonce: int, segment_id: int, capacity: int, fd: int) -> None:
        """Push one segment's descriptor. ``ProcessGone`` when the subscriber hung up;
        ``BlockingIOError`` when its queue is full (try again with a later frame)."""
        record = HANDOVER.pack(HANDOVER_MAGIC, nonce, segment_id, 0, capacity)
        try:
            socket.send_fds(self.sock, [record], [fd], socket.MSG_DONTWAIT | socket.MSG_NOSIGNAL)
        except OSError as exc:
            if exc.errno in _GONE:
                raise ProcessGone(f'demo subscriber {self.token} hung up: {exc}') from None
            raise
        self.segments.add(segment_id)

    def retire(self, nonce: int, segment_id: int) -> None:
        """Tell the subscriber a segment it holds is removed (best effort, never blocks)."""
        if segment_id in self.segments:
            self.segments.discard(segment_id)
            try:
                self.sock.send(HANDOVER.pack(RETIRE_MAGIC, nonce, segment_id, 0, 0),
                               socket.MSG_DONTWAIT | socket.MSG_NOSIGNAL)
            except OSError:
                pass  # gone or full: it drops the segment when we hang up

    def acks(self) -> List[Tuple[int, int]]:
        """Takes acknowledged since the last call, ``(segment id, generation)`` each;
        ``ProcessGone`` when the subscriber hung up."""
        got = []
        while True:
            try:
                data = self.sock.recv(ACK.size + 1)
            except (BlockingIOError, InterruptedError):
                return got
            except OSError as exc:
                raise ProcessGone(f'demo subscriber {self.token} hung up: {exc}') from None
            if not data:
                raise ProcessGone(f'demo subscriber {self.token} hung up')
            if len(data) == ACK.size:
                segment_id, _, generation = ACK.unpack(data)
                got.append((segment_id, generation))

    def close(self) -> None:
        self.sock.close()
