"""Sealed anonymous segments: the memory a demo slot lives in, and the checks that a segment
received from another process is one of them.

A segment is a memfd (no name in any filesystem: the kernel frees it with its last descriptor
or mapping, SIGKILL included) laid out as a header page followed by the data::

    offset 0                 HEADER_SIZE                          HEADER_SIZE + capacity
    | header (HEADER struct) | data (the payload bytes)           |

Its pages are allocated when it is created (``posix_fallocate``: a full memory fails then, with
``OSError``, never later with SIGBUS), then it is sealed (``SEALS``) before any other process
sees it: it can never shrink or grow, and nobody can write it except through the creator's
mapping made before the seal (no ``write``, no writable ``mmap``, no hole punching). A reader
therefore never touches a page that is not there.

The creator writes the header; readers map everything read-only. Byte ``HOLD_BYTE`` of the file
carries OFD locks (per open file description, dropped by the kernel when the description is
closed, which includes the death of its process): each reader holds a shared lock on its own
description while it holds views; the creator reuses the slot only under an exclusive lock.
"""
import errno
import fcntl
import mmap
import os
import struct
from typing import Sequence

HEADER_SIZE = max(4096, mmap.ALLOCATIONGRANULARITY)
PAGE_SIZE = mmap.PAGESIZE
MAGIC = b'RBPYMFD1'
#: magic, capacity, generation, offset, size
HEADER = struct.Struct('<8sQQQQ')

_F_SEAL_FUTURE_WRITE = getattr(fcntl, 'F_SEAL_FUTURE_WRITE', 0x0010)
#: Seals every segment carries: no shrinking, no growing, no write but the creator's mapping,
#: no more seals to add or remove.
SEALS = fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | _F_SEAL_FUTURE_WRITE | fcntl.F_SEAL_SEAL

HOLD_BYTE = 0
_FLOCK = struct.Struct('hhqqi4x')  # struct flock (l_pid must be 0 for OFD locks)
_F_OFD_SETLK = getattr(fcntl, 'F_OFD_SETLK', 37)
#: The three requests on the hold byte, packed once (every message locks and unlocks it)
_WRLCK, _RDLCK, _UNLCK = (_FLOCK.pack(kind, os.SEEK_SET, HOLD_BYTE, 1, 0)
                          for kind in (fcntl.F_WRLCK, fcntl.F_RDLCK, fcntl.F_UNLCK))
#: The shared lock and the unlock of the hold byte as packed requests, for the native open
#: (``rosidl_buffer_py._native.open_mapped``), which takes a subscriber's hold as
#: :func:`try_lock` does.
SHARED_LOCK_REQUEST, UNLOCK_REQUEST = _RDLCK, _UNLCK


def _close(data, mapped: mmap.mmap, fd: int) -> None:
    """Close a segment's view, mapping and descriptor (the mapping stays while a view of it is
    exported: the kernel drops it with that view)."""
    try:
        if data is not None:
            data.release()
        mapped.close()
    except BufferError:
        pass  # a view is still exported: the mapping goes when it does
    os.close(fd)


def round_capacity(nbytes: int) -> int:
    """Data capacity for a payload of ``nbytes``: whole pages, at least one."""
    return max(PAGE_SIZE, -(-nbytes // PAGE_SIZE) * PAGE_SIZE)


def try_lock(fd: int, *, exclusive: bool) -> bool:
    """Lock ``HOLD_BYTE`` on ``fd``'s open file description without waiting; False when another
    description holds a conflicting lock."""
    try:
        fcntl.fcntl(fd, _F_OFD_SETLK, _WRLCK if exclusive else _RDLCK)
    except OSError as exc:
        if exc.errno in (errno.EAGAIN, errno.EACCES):
            return False
        raise
    return True


def unlock(fd: int) -> None:
    fcntl.fcntl(fd, _F_OFD_SETLK, _UNLCK)


class Segment:
    """A segment this process created: its descriptor and a writable mapping of all of it.

    With ``with_data=False`` it is a header alone (the *control* segment of memory that lives
    elsewhere, a GPU's for example): its header records ``capacity`` and the generation, and
    its hold byte carries the locks, while ``data`` is left ``None`` for the medium to set.
    """

    __slots__ = ('fd', 'map', 'capacity', 'data')

    def __init__(self, capacity: int, *, with_data: bool = True) -> None:
        """Create, back and seal a segment of ``capacity`` data bytes (a multiple of the page
        size); ``OSError`` (ENOSPC, ENOMEM, EFBIG, ...) when the memory cannot be had."""
        if capacity <= 0 or capacity % PAGE_SIZE:
            raise ValueError(f'capacity must be a positive multiple of {PAGE_SIZE}, got '
                             f'{capacity}')
        fd = os.memfd_create('rbpy_demo', os.MFD_ALLOW_SEALING | os.MFD_CLOEXEC)
        mapped = None
        length = HEADER_SIZE + (capacity if with_data else 0)
        try:
            os.posix_fallocate(fd, 0, length)
            mapped = mmap.mmap(fd, length,
                               flags=mmap.MAP_SHARED | getattr(mmap, 'MAP_POPULATE', 0))
            fcntl.fcntl(fd, fcntl.F_ADD_SEALS, SEALS)  # after the writable mapping, see above
        except BaseException:
            if mapped is not None:
                mapped.close()
            os.close(fd)
            raise
        self.map = mapped
        self.fd = fd
        self.capacity = capacity
        HEADER.pack_into(self.map, 0, MAGIC, capacity, 0, 0, 0)
        self.data = memoryview(self.map)[HEADER_SIZE:] if with_data else None

    def set_generation(self, generation: int, size: int) -> None:
        """Record the bytes of a new generation (the caller holds the exclusive lock)."""
        HEADER.pack_into(self.map, 0, MAGIC, self.capacity, generation, 0, size)

    def reader_fd(self) -> int:
        """A new read-only open file description of this segment, for one reader (its locks
        are its own). The caller closes it (after handing it over)."""
        return os.open(f'/proc/self/fd/{self.fd}', os.O_RDONLY | os.O_CLOEXEC)

    def reader_fds(self) -> list:
        """What a reader process is handed: one new read-only description (see
        :meth:`reader_fd`)."""
        return [self.reader_fd()]

    def close(self) -> None:
        _close(self.data, self.map, self.fd)


class Received:
    """A segment of another process (or ours, through a reader description), mapped
    read-only: ``fd`` carries the locks, ``map`` the header, ``data`` the payload view (None
    for a control segment, whose medium sets it)."""

    __slots__ = ('fd', 'map', 'capacity', 'data')

    def __init__(self, fd: int, mapped: mmap.mmap, capacity: int, with_data: bool) -> None:
        self.fd = fd
        self.map = mapped
        self.capacity = capacity
        self.data = memoryview(mapped).toreadonly()[HEADER_SIZE:] if with_data else None

    def close(self) -> None:
        _close(self.data, self.map, self.fd)


def open_received(fd: int, capacity: int, *, with_data: bool = True) -> Received:
    """Map a received segment descriptor after checking that it is one as :class:`Segment`
    creates them: a sealed memfd of ``HEADER_SIZE + capacity`` bytes (``HEADER_SIZE`` alone
    when not ``with_data``), all backed, with our header. ``ValueError`` naming what is wrong
    otherwise; ``OSError`` when this process lacks the memory or descriptors to map it; ``fd``
    stays the caller's to close on error."""
    try:
        seals = fcntl.fcntl(fd, fcntl.F_GET_SEALS)
    except OSError:
        raise ValueError('not a sealable memfd (F_GET_SEALS failed)') from None
    if seals & SEALS != SEALS:
        raise ValueError(f'seals {seals:#x} lack some of {SEALS:#x} (shrink, grow, future '
                         'write, seal)')
    st = os.fstat(fd)
    if not 0 < capacity <= 1 << 40 or capacity % PAGE_SIZE:
        raise ValueError(f'capacity {capacity} is not a multiple of {PAGE_SIZE} in (0, 1 TiB]')
    length = HEADER_SIZE + (capacity if with_data else 0)
    if st.st_size != length:
        raise ValueError(f'size {st.st_size} is not {length} (header'
                         + (f' + capacity {capacity})' if with_data else ' alone)'))
    if st.st_blocks * 512 < st.st_size:
        raise ValueError(f'only {st.st_blocks * 512} of its {st.st_size} bytes are backed '
                         '(a sparse segment could fault)')
    try:
        mapped = mmap.mmap(fd, st.st_size, prot=mmap.PROT_READ,  # page tables filled now
                           flags=mmap.MAP_SHARED | getattr(mmap, 'MAP_POPULATE', 0))
    except OSError as exc:
        if exc.errno in (errno.ENOMEM, errno.EAGAIN, errno.EMFILE, errno.ENFILE):
            raise  # this process lacks the memory or descriptors, not the segment's fault
        raise ValueError(f'cannot map it: {exc}') from None
    magic, recorded, _, _, _ = HEADER.unpack_from(mapped, 0)
    if (magic, recorded) != (MAGIC, capacity):
        mapped.close()
        raise ValueError(f'header ({magic!r}, capacity {recorded}) is not ({MAGIC!r}, '
                         f'{capacity})')
    return Received(fd, mapped, capacity, with_data)


class SharedMemory:
    """The demo backend's medium: payloads in the sealed segments themselves.

    A *medium* is what a :class:`~.pool.Pool` is made of; the pool's machinery (slots,
    ledgers, links, inbox, mappings) is the same for every medium. A medium has:

    - ``name``: names its listeners (``\\0rbpy_<name>/<token>``) and its messages;
    - ``descriptor_magic``: the 4 bytes that open its descriptors;
    - ``fds_per_segment``: the descriptors a handover carries (the first is the segment whose
      header and hold byte the machinery uses);
    - ``round_capacity(nbytes)`` and ``fits(capacity, nbytes)``: slot sizes;
    - ``create(capacity)``: a segment (``fd``, ``map``, ``capacity``, ``data`` sliceable,
      ``set_generation``, ``reader_fds()``, ``close()``), ``OSError`` when the memory cannot
      be had;
    - ``open_received(fds, capacity)``: a :class:`Received`-like mapping (``fd``, ``map``,
      ``capacity``, ``data``, ``close()``), which owns ``fds`` on success; ``ValueError`` for
      a segment it does not make, ``OSError`` for what this process lacks;
    - ``fence(readers)``: for memory that other engines read asynchronously (a GPU's streams),
      an object whose ``done()`` says when the reads queued so far are complete; None when
      nothing is pending (host memory: a view dropped is a read complete).
    """

    name = 'demo'
    descriptor_magic = b'RBDM'
    fds_per_segment = 1

    @staticmethod
    def round_capacity(nbytes: int) -> int:
        return round_capacity(nbytes)

    @staticmethod
    def fits(capacity: int, nbytes: int) -> bool:
        """A slot of ``capacity`` serves ``nbytes`` without wasting more than half of it."""
        return nbytes <= capacity <= 2 * max(nbytes, PAGE_SIZE)

    @staticmethod
    def create(capacity: int) -> Segment:
        return Segment(capacity)

    @staticmethod
    def open_received(fds: Sequence[int], capacity: int) -> Received:
        return open_received(fds[0], capacity)

    @staticmethod
    def fence(readers) -> None:
        return None
