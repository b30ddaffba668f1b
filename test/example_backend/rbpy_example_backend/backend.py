"""FileStoreBackend: payloads in files of a shared directory, ~60-byte descriptors.

Memory is released without guessing how long receivers need it: each descriptor names a hard
link made for that one subscriber, which the receiver unlinks as soon as it has mapped the file.
The publisher's own name for the file goes with its Buffer; links a subscriber never took are
removed when that subscriber leaves (``on_removing_endpoint``) and at process exit. The kernel
frees the pages with the last mapping.
"""
import atexit
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
from typing import Dict, List, Mapping, Optional, Sequence, Set, Tuple

from rosidl_buffer_py import Buffer, BufferBackend
from rosidl_buffer_py.backend import EndpointInfo

BACKEND_TYPE = 'filestore'
#: Directory that holds the payload files; processes sharing it share payloads. Required.
STORE_DIR_ENV = 'RBPY_EXAMPLE_STORE_DIR'

_MAGIC = b'FSB1'
_HEADER = struct.Struct('<4sQI')  # magic, size, crc32; then the file name (ASCII)
#: A descriptor names a per-subscriber link: <pid>-<sequence>-<16 hex>.buf.<8 hex>
_LINK = re.compile(r'^[0-9]{1,10}-[0-9]{1,20}-[0-9a-f]{16}\.buf\.[0-9a-f]{8}$')
#: Links per subscriber after which those already consumed are forgotten.
_PRUNE_AT = 64
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
    """

    def __init__(self, directory: Optional[str] = None) -> None:
        directory = directory or os.environ.get(STORE_DIR_ENV)
        if not directory:
            raise RuntimeError(f'set {STORE_DIR_ENV} to the directory that peers share')
        if not os.path.isdir(directory):
            raise RuntimeError(f'{STORE_DIR_ENV}={directory!r} is not a directory')
        self.directory = os.path.realpath(directory)
        # Metadata: the directory itself, so a peer is compatible only if it shares it.
        self._metadata = self.directory if _advertisable(self.directory) else \
            'sha256-' + hashlib.sha256(self.directory.encode()).hexdigest()
        self._lock = threading.Lock()
        self._peers: Set[bytes] = set()
        #: subscriber GID -> links made for it that it may not have consumed yet
        self._links: Dict[bytes, Set[str]] = {}
        atexit.register(self.close)

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
        """A peer left: forget it and remove the links it did not take."""
        with self._lock:
            self._peers.discard(endpoint_info.gid)
            links = self._links.pop(endpoint_info.gid, set())
        for link in links:
            _unlink(link)

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
        link = f'{stored.path}.{secrets.token_hex(4)}'
        os.link(stored.path, link)  # this subscriber's own name for the payload
        with self._lock:
            links = self._links.setdefault(endpoint_info.gid, set())
            links.add(link)
            if len(links) > _PRUNE_AT:  # forget the links their receivers consumed
                links.difference_update([x for x in links if not os.path.exists(x)])
        return _HEADER.pack(_MAGIC, stored.size, crc) + os.path.basename(link).encode('ascii')

    def from_descriptor_with_endpoint(self, descriptor: bytes,
                                      endpoint_info: EndpointInfo) -> FileStoreBuffer:
        descriptor = bytes(descriptor)
        if len(descriptor) <= _HEADER.size or len(descriptor) > _HEADER.size + 64:
            raise ValueError(f'filestore descriptor of {len(descriptor)} bytes')
        magic, size, crc = _HEADER.unpack_from(descriptor)
        name = descriptor[_HEADER.size:].decode('ascii', errors='replace')
        if magic != _MAGIC or not _LINK.match(name):
            raise ValueError(f'malformed filestore descriptor {descriptor[:80]!r}')
        try:
            fd = os.open(os.path.join(self.directory, name),
                         os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        except FileNotFoundError:
            raise ValueError(f'filestore link {name} is gone (taken already, dropped by its '
                             'publisher, or another store directory)') from None
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
        # Taken: the link is this receiver's alone. Its mapping keeps the pages; the kernel
        # frees them once the publisher's Buffer and every mapping are gone.
        _unlink(os.path.join(self.directory, name))
        if (zlib.crc32(view) if size else 0) != crc:
            if size:
                view.close()
            raise ValueError(f'filestore file {name}: CRC mismatch (written after publish?)')
        return FileStoreBuffer(view, keepalive=view)

    # diagnostics --------------------------------------------------------------------------------

    def pending_links(self) -> int:
        """Links made for subscribers that they have not taken yet."""
        with self._lock:
            return sum(1 for links in self._links.values() for x in links if os.path.exists(x))

    def close(self) -> None:
        """Remove every link not taken yet (also run at interpreter exit)."""
        with self._lock:
            links = [link for peer_links in self._links.values() for link in peer_links]
            self._links.clear()
        for link in links:
            _unlink(link)
