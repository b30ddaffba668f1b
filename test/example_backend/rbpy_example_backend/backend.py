"""FileStoreBackend: payloads in files of a shared directory, ~50-byte descriptors."""
import collections
import hashlib
import itertools
import mmap
import os
import re
import secrets
import stat
import struct
import threading
import weakref
import zlib
from typing import Deque, List, Mapping, Optional, Sequence, Set, Tuple

from rosidl_buffer_py import Buffer, BufferBackend
from rosidl_buffer_py.backend import EndpointInfo

BACKEND_TYPE = 'filestore'
#: Directory that holds the payload files; processes sharing it share payloads. Required.
STORE_DIR_ENV = 'RBPY_EXAMPLE_STORE_DIR'
#: How many files sent as descriptors a publisher process keeps for late readers (default 64).
RETAIN_ENV = 'RBPY_EXAMPLE_RETAIN'

_MAGIC = b'FSB1'
_HEADER = struct.Struct('<4sQI')  # magic, size, crc32; then the file name (ASCII)
_NAME = re.compile(r'^[0-9]{1,10}-[0-9]{1,20}-[0-9a-f]{16}\.buf$')
_sequence = itertools.count()


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


class _StoredFile:
    """One payload file created by this process, mapped read-write; unlinked when collected
    (or at interpreter exit)."""

    def __init__(self, directory: str, nbytes: int) -> None:
        self.name = f'{os.getpid()}-{next(_sequence)}-{secrets.token_hex(8)}.buf'
        self.path = os.path.join(directory, self.name)
        self.size = nbytes
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
        self._finalizer = weakref.finalize(self, _unlink, self.path)
        try:
            os.ftruncate(fd, nbytes)
            self.map = mmap.mmap(fd, nbytes, flags=mmap.MAP_SHARED,
                                 prot=mmap.PROT_READ | mmap.PROT_WRITE) if nbytes else bytearray()
        except BaseException:
            self._finalizer()
            raise
        finally:
            os.close(fd)


class FileStoreBuffer(Buffer):
    """A Buffer over a mapped store file: writable when allocated here, read-only when received.

    ``stored`` is the file this process created (None for a received buffer).
    """

    def __init__(self, host, stored: Optional[_StoredFile] = None, keepalive=None) -> None:
        super().__init__(BACKEND_TYPE, host, keepalive=keepalive if keepalive is not None
                         else stored)
        self.stored = stored


def _advertisable(text: str) -> bool:
    return all(0x20 <= ord(c) <= 0x7e for c in text) and ';' not in text and '=' not in text


class FileStoreBackend(BufferBackend):
    """The ``filestore`` backend (entry point
    ``filestore = rbpy_example_backend:FileStoreBackend``).

    :param directory: The store directory (default: ``$RBPY_EXAMPLE_STORE_DIR``).
    :param retain: Files sent as descriptors kept for late readers (default:
        ``$RBPY_EXAMPLE_RETAIN`` or 64).
    """

    def __init__(self, directory: Optional[str] = None, retain: Optional[int] = None) -> None:
        directory = directory or os.environ.get(STORE_DIR_ENV)
        if not directory:
            raise RuntimeError(f'set {STORE_DIR_ENV} to the directory that peers share')
        if not os.path.isdir(directory):
            raise RuntimeError(f'{STORE_DIR_ENV}={directory!r} is not a directory')
        self.directory = os.path.realpath(directory)
        # Metadata: the directory itself, so a peer is compatible only if it shares it.
        self._metadata = self.directory if _advertisable(self.directory) else \
            'sha256-' + hashlib.sha256(self.directory.encode()).hexdigest()
        retain = int(os.environ.get(RETAIN_ENV, '64')) if retain is None else retain
        if retain < 1:
            raise ValueError(f'retain must be >= 1, got {retain}')
        self._lock = threading.Lock()
        self._retained: Deque[_StoredFile] = collections.deque(maxlen=retain)
        self._peers: Set[bytes] = set()

    # identity ---------------------------------------------------------------------------------

    def get_backend_type(self) -> str:
        return BACKEND_TYPE

    def get_backend_metadata(self) -> str:
        return self._metadata

    # endpoints ----------------------------------------------------------------------------------

    def on_discovering_endpoint(
            self, endpoint_info: EndpointInfo, existing_endpoints: Sequence[EndpointInfo],
            endpoint_supported_backends: Mapping[str, str]) -> Tuple[bool, List[Set[int]]]:
        """Compatible iff the peer advertises the same store directory."""
        compatible = endpoint_supported_backends.get(BACKEND_TYPE) == self._metadata
        with self._lock:
            if compatible:
                self._peers.add(endpoint_info.gid)
            else:
                self._peers.discard(endpoint_info.gid)
        return compatible, []

    def on_removing_endpoint(self, endpoint_info: EndpointInfo) -> None:
        with self._lock:
            self._peers.discard(endpoint_info.gid)

    # memory -------------------------------------------------------------------------------------

    def allocate(self, nbytes: int) -> FileStoreBuffer:
        if not isinstance(nbytes, int) or nbytes < 0:
            raise ValueError(f'nbytes must be an int >= 0, got {nbytes!r}')
        stored = _StoredFile(self.directory, nbytes)
        return FileStoreBuffer(stored.map, stored)

    def create_descriptor_with_endpoint(self, buffer: Buffer,
                                        endpoint_info: EndpointInfo) -> Optional[bytes]:
        """Name the buffer's file, or None (CPU bytes) for an unknown or incompatible peer and
        for buffers this process did not allocate (received ones, or foreign memory)."""
        with self._lock:
            known = endpoint_info.gid in self._peers
        stored = getattr(buffer, 'stored', None)
        if not known or not isinstance(buffer, FileStoreBuffer) or stored is None:
            return None
        crc = zlib.crc32(memoryview(buffer)) if len(buffer) else 0
        with self._lock:
            if not self._retained or self._retained[-1] is not stored:
                self._retained.append(stored)  # the oldest retained file may now be unlinked
        return _HEADER.pack(_MAGIC, stored.size, crc) + stored.name.encode('ascii')

    def from_descriptor_with_endpoint(self, descriptor: bytes,
                                      endpoint_info: EndpointInfo) -> FileStoreBuffer:
        descriptor = bytes(descriptor)
        if len(descriptor) <= _HEADER.size or len(descriptor) > _HEADER.size + 64:
            raise ValueError(f'filestore descriptor of {len(descriptor)} bytes')
        magic, size, crc = _HEADER.unpack_from(descriptor)
        name = descriptor[_HEADER.size:].decode('ascii', errors='replace')
        if magic != _MAGIC or not _NAME.match(name):
            raise ValueError(f'malformed filestore descriptor {descriptor[:80]!r}')
        try:
            fd = os.open(os.path.join(self.directory, name),
                         os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        except FileNotFoundError:
            raise ValueError(f'filestore file {name} is gone (dropped by its publisher, or '
                             'another store directory)') from None
        except OSError as exc:
            raise ValueError(f'filestore file {name}: {exc}') from None
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode) or st.st_size != size:
                raise ValueError(f'filestore file {name} has {st.st_size} bytes, the descriptor '
                                 f'says {size}')
            view = mmap.mmap(fd, size, flags=mmap.MAP_SHARED, prot=mmap.PROT_READ) if size \
                else b''
        finally:
            os.close(fd)
        if (zlib.crc32(view) if size else 0) != crc:
            if size:
                view.close()
            raise ValueError(f'filestore file {name}: CRC mismatch (written after publish?)')
        return FileStoreBuffer(view, keepalive=view)

    # diagnostics --------------------------------------------------------------------------------

    def retained_count(self) -> int:
        """Files kept for late readers."""
        with self._lock:
            return len(self._retained)

    def close(self) -> None:
        """Drop the retained files (unlinked unless a Buffer of this process still uses them)."""
        with self._lock:
            self._retained.clear()
