"""Shared-memory segment files in /dev/shm: naming, header layout, creation, opening, liveness,
scavenging of segments left by dead processes, and the shm domain identity.

One segment holds one slot: a header page followed by the data area::

    file offset 0             HEADER_SIZE                         HEADER_SIZE + capacity
    | header (HEADER struct)  | data (the payload bytes)          |

Besides its contents, three byte offsets of the file carry OFD locks (see :mod:`.locks`):

- ``OWNER_BYTE``: exclusively locked by the creating process for the segment's whole life. No
  lock there means the owner is gone and the segment may be unlinked by anyone.
- ``HOLD_BYTE``: every process that holds views of the slot's current bytes has a shared lock; the
  owner may reuse the slot (bump the generation) only while it holds the exclusive lock.
- ``MUTEX_BYTE``: a short exclusive lock around the ``taken`` counter and the takers table,
  written by subscribers.

After the header struct, the header page holds a small *takers table*: per subscriber process
(identified by the 64-bit id of its presence token, see :mod:`.presence`) the number of
descriptors of the current generation it took. With it the owner can tell apart the takes of a
recipient that died from those of the live ones. It is reset with every generation.
"""
import errno
import mmap
import os
import re
import secrets
import stat
import struct
import time
from typing import Dict, Iterable, NamedTuple, Optional, Tuple

from demo_buffer_backend import locks

SHM_DIR = '/dev/shm'

#: Every segment name starts with this (the test suite checks /dev/shm for ``rbpy_``).
PREFIX = 'rbpy_demo_'

#: ``rbpy_demo_<owner pid>_<16 hex>``: only [A-Za-z0-9_], so never a path separator or ``..``.
NAME_PATTERN = re.compile(r'^rbpy_demo_([1-9][0-9]{0,9})_([0-9a-f]{16})$')

#: Size of the header page; the data area starts here (a multiple of the mmap granularity).
HEADER_SIZE = max(4096, mmap.ALLOCATIONGRANULARITY)

PAGE_SIZE = mmap.PAGESIZE

MAGIC = b'RBPYDMO1'
#: Magic of presence files (see :mod:`.presence`), which share the prefix, the owner byte and the
#: scavenging of segments.
PRESENCE_MAGIC = b'RBPYLIV1'

# magic, header_size, owner_pid, capacity, generation, offset, size, sent, taken, last_publish_ns
HEADER = struct.Struct('<8sIIQQQQQQQ')
_U64 = struct.Struct('<Q')
OFF_GENERATION = 24
OFF_OFFSET = 32
OFF_SIZE = 40
OFF_SENT = 48
OFF_TAKEN = 56
OFF_LAST_PUBLISH = 64

#: Takers table: entry count, overflow flag (more takers than entries: the table is incomplete
#: for this generation), then MAX_TAKERS entries of (taker id u64, descriptors taken u64).
OFF_TAKERS_COUNT = 112
OFF_TAKERS_OVERFLOW = 120
OFF_TAKERS = 128
_TAKER = struct.Struct('<QQ')
MAX_TAKERS = 64

OWNER_BYTE = 0
HOLD_BYTE = 1
MUTEX_BYTE = 2

#: A segment without an owner lock and without a magic (creator died while creating it) is
#: removed only once it is this old, so that a segment being created is never taken for garbage.
UNFINISHED_SEGMENT_AGE = 10.0

_OPEN_FLAGS = os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC


class HeaderFields(NamedTuple):
    magic: bytes
    header_size: int
    owner_pid: int
    capacity: int
    generation: int
    offset: int
    size: int
    sent: int
    taken: int
    last_publish_ns: int


def path_of(name: str) -> str:
    return os.path.join(SHM_DIR, name)


def new_name() -> str:
    return f'{PREFIX}{os.getpid()}_{secrets.token_hex(8)}'


def read_header(header: mmap.mmap) -> HeaderFields:
    return HeaderFields(*HEADER.unpack_from(header, 0))


def read_u64(header: mmap.mmap, offset: int) -> int:
    return _U64.unpack_from(header, offset)[0]


def write_u64(header: mmap.mmap, offset: int, value: int) -> None:
    _U64.pack_into(header, offset, value)


def record_taker(header: mmap.mmap, ident: int) -> None:
    """Count one take by ``ident`` in the takers table (caller holds the mutex byte)."""
    count = read_u64(header, OFF_TAKERS_COUNT)
    if count > MAX_TAKERS:  # garbage: make the table unusable rather than trust it
        write_u64(header, OFF_TAKERS_OVERFLOW, 1)
        return
    for i in range(count):
        offset = OFF_TAKERS + i * _TAKER.size
        if read_u64(header, offset) == ident:
            write_u64(header, offset + 8, read_u64(header, offset + 8) + 1)
            return
    if count == MAX_TAKERS:
        write_u64(header, OFF_TAKERS_OVERFLOW, 1)
        return
    _TAKER.pack_into(header, OFF_TAKERS + count * _TAKER.size, ident, 1)
    write_u64(header, OFF_TAKERS_COUNT, count + 1)


def reset_takers(header: mmap.mmap) -> None:
    """Empty the takers table (owner only, with no taker able to write: new generation)."""
    count = min(read_u64(header, OFF_TAKERS_COUNT), MAX_TAKERS)
    if count:
        header[OFF_TAKERS:OFF_TAKERS + count * _TAKER.size] = bytes(count * _TAKER.size)
    write_u64(header, OFF_TAKERS_COUNT, 0)
    write_u64(header, OFF_TAKERS_OVERFLOW, 0)


def taken_by(header: mmap.mmap, idents) -> Optional[int]:
    """Descriptors of this generation taken by the takers ``idents``; None when the table is
    incomplete (overflow), so that the caller cannot tell."""
    count = read_u64(header, OFF_TAKERS_COUNT)
    if read_u64(header, OFF_TAKERS_OVERFLOW) or count > MAX_TAKERS:
        return None
    total = 0
    for ident, taken in _TAKER.iter_unpack(header[OFF_TAKERS:OFF_TAKERS + count * _TAKER.size]):
        if ident in idents:
            total += taken
    return total


def takers(header: mmap.mmap) -> Optional[Dict[int, int]]:
    """The takers table, ``{taker id: descriptors taken}``; None when it is incomplete."""
    count = read_u64(header, OFF_TAKERS_COUNT)
    if read_u64(header, OFF_TAKERS_OVERFLOW) or count > MAX_TAKERS:
        return None
    table: Dict[int, int] = {}
    for ident, taken in _TAKER.iter_unpack(header[OFF_TAKERS:OFF_TAKERS + count * _TAKER.size]):
        table[ident] = table.get(ident, 0) + taken
    return table


def round_capacity(nbytes: int) -> int:
    """Data capacity for a payload of ``nbytes``: whole pages, at least one."""
    return max(PAGE_SIZE, -(-nbytes // PAGE_SIZE) * PAGE_SIZE)


def create(capacity: int) -> Tuple[str, int, mmap.mmap, mmap.mmap]:
    """Create a segment with ``capacity`` data bytes, mode 0600, owned (locked) by this process.

    The memory is reserved up front (``posix_fallocate``: a full /dev/shm fails here with
    ``OSError``, not later with SIGBUS) and pre-faulted (``MAP_POPULATE``). Returns
    ``(name, fd, header map, data map)``; the header is written with generation 0 and the magic
    last, after the owner lock is taken.
    """
    name = new_name()
    path = path_of(name)
    fd = os.open(path, _OPEN_FLAGS | os.O_CREAT | os.O_EXCL, FILE_MODE)
    header = data = None
    try:
        os.fchmod(fd, FILE_MODE)  # whatever the umask
        if not locks.try_lock(fd, OWNER_BYTE, exclusive=True):
            raise OSError(errno.EBUSY, f'cannot take the owner lock of new segment {name}')
        try:
            os.posix_fallocate(fd, 0, HEADER_SIZE + capacity)
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
                raise
            os.ftruncate(fd, HEADER_SIZE + capacity)
        flags = mmap.MAP_SHARED | getattr(mmap, 'MAP_POPULATE', 0)
        prot = mmap.PROT_READ | mmap.PROT_WRITE
        header = mmap.mmap(fd, HEADER_SIZE, flags=flags, prot=prot)
        data = mmap.mmap(fd, capacity, flags=flags, prot=prot, offset=HEADER_SIZE)
        HEADER.pack_into(header, 0, b'\0' * 8, HEADER_SIZE, os.getpid(), capacity,
                         0, 0, 0, 0, 0, 0)
        header[0:8] = MAGIC
        return name, fd, header, data
    except BaseException:
        for m in (data, header):
            if m is not None:
                m.close()
        unlink(name)
        os.close(fd)
        raise


def open_existing(name: str) -> Tuple[int, os.stat_result]:
    """Open a segment by (validated) name; ``OSError`` when it does not exist or is not ours."""
    fd = os.open(path_of(name), _OPEN_FLAGS)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise OSError(errno.EINVAL, f'{name} is not a regular file')
        return fd, st
    except BaseException:
        os.close(fd)
        raise


#: The mode every segment and presence file is created with (fchmod'ed, whatever the umask).
FILE_MODE = 0o600


def untrusted(st: os.stat_result) -> Optional[str]:
    """Why a file with status ``st`` (opened with O_NOFOLLOW) is not one this backend creates,
    or None: a regular file of our effective uid with mode exactly 0600."""
    if not stat.S_ISREG(st.st_mode):
        return 'not a regular file'
    if st.st_uid != os.geteuid():
        return f'owned by uid {st.st_uid}, not by us ({os.geteuid()})'
    if stat.S_IMODE(st.st_mode) != FILE_MODE:
        return f'mode {stat.S_IMODE(st.st_mode):04o}, not {FILE_MODE:04o}'
    return None


def map_header(fd: int) -> mmap.mmap:
    return mmap.mmap(fd, HEADER_SIZE, flags=mmap.MAP_SHARED,
                     prot=mmap.PROT_READ | mmap.PROT_WRITE)


def map_data_readonly(fd: int, capacity: int) -> mmap.mmap:
    return mmap.mmap(fd, capacity, flags=mmap.MAP_SHARED | getattr(mmap, 'MAP_POPULATE', 0),
                     prot=mmap.PROT_READ, offset=HEADER_SIZE)


def owner_alive(fd: int) -> bool:
    """True when some process (another open file description) holds the owner lock."""
    return locks.is_locked_by_other(fd, OWNER_BYTE)


def unlink(name: str) -> bool:
    try:
        os.unlink(path_of(name))
        return True
    except FileNotFoundError:
        return False


def scavenge(skip: Iterable[str] = ()) -> int:
    """Unlink every demo segment and presence file in /dev/shm whose owner process is gone;
    return how many.

    A file is garbage when nobody holds its owner lock and either its magic is written (the
    owner had taken the lock, so it is dead now) or it is older than UNFINISHED_SEGMENT_AGE (its
    creator died between creating the file and taking the lock). The magic is read *before* the
    lock is tested: a creator takes the lock before writing the magic, so a magic seen before an
    absent lock means the owner is really gone (not that it is just being created). Files that do
    not look like ours (:func:`untrusted`) are left alone.
    """
    skip = set(skip)
    removed = 0
    try:
        names = os.listdir(SHM_DIR)
    except OSError:
        return 0
    for name in names:
        if not name.startswith(PREFIX) or name in skip:
            continue
        try:
            fd, st = open_existing(name)
        except OSError:
            continue  # gone meanwhile, or not ours to open
        try:
            if untrusted(st):
                continue  # not created by this backend: not ours to judge
            finished = os.pread(fd, len(MAGIC), 0) in (MAGIC, PRESENCE_MAGIC)
            if owner_alive(fd):
                continue
            age = time.time() - max(st.st_mtime, st.st_ctime)
            if finished or age > UNFINISHED_SEGMENT_AGE:
                removed += unlink(name)
        except OSError:
            pass
        finally:
            os.close(fd)
    return removed


def _boot_id() -> str:
    try:
        with open('/proc/sys/kernel/random/boot_id') as f:
            return f.read().strip().replace('-', '').lower()
    except OSError:
        return 'noboot'


def domain_metadata() -> str:
    """Identity of the shared-memory domain this process reaches: processes whose metadata is
    equal open the same /dev/shm files (same boot, same /dev/shm mount, same user, who owns the
    0600 segments). Printable ASCII without ``;`` or ``=``."""
    try:
        st = os.stat(SHM_DIR)
        dev, ino = st.st_dev, st.st_ino
    except OSError:
        dev = ino = 0
    return f'shm1.{_boot_id()}.{dev:x}.{ino:x}.{os.geteuid():x}'
