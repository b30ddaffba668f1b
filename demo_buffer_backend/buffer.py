"""DemoBuffer: a Buffer whose bytes live in a demo shared-memory slot, a sealed memfd segment
(or, as a fallback when the pool is exhausted, in private memory: then it is sent as CPU
bytes)."""
import array
from typing import Any, Optional, Tuple

from rosidl_buffer_py.buffer import Buffer

from demo_buffer_backend import lifecycle
from demo_buffer_backend.mappings import Hold
from demo_buffer_backend.slots import Pin

BACKEND_TYPE = 'demo'


#: struct-module item formats of plain data (no pointers, no Python objects), any byte order.
_PLAIN_FORMATS = frozenset('cbB?hHiIlLqQnNefd')
_ACCEPTED = ('bytes, bytearray, a memoryview or another buffer of plain numbers, or a numpy '
             'array of a dtype without Python objects')


def _plain_format(fmt: str) -> bool:
    fmt = fmt.lstrip('@=<>!')
    return len(fmt) == 1 and fmt in _PLAIN_FORMATS


def _byte_view(data: Any) -> memoryview:
    """The raw bytes of ``data`` (bytes-like or C-contiguous array of plain data), no copy.

    Only plain data: the bytes of an object array are pointers into this process's heap, and
    publishing them would leak addresses and mean nothing to a subscriber.
    """
    dtype = getattr(data, 'dtype', None)
    if dtype is not None and getattr(dtype, 'hasobject', False):
        raise TypeError(f'DemoBuffer.from_cpu needs {_ACCEPTED}; got a numpy array of dtype '
                        f'{dtype} (it holds Python objects)')
    try:
        view = memoryview(data)
    except (TypeError, ValueError):
        # numpy dtypes the buffer protocol cannot express (datetime64, ...): view them as uint8.
        flags = getattr(data, 'flags', None)
        if flags is None or not hasattr(data, 'view') or dtype is None:
            raise TypeError(f'DemoBuffer.from_cpu needs {_ACCEPTED}; got '
                            f'{type(data).__name__}') from None
        if not flags.c_contiguous:
            raise ValueError('DemoBuffer.from_cpu needs C-contiguous data') from None
        import numpy
        view = memoryview(data.reshape(-1).view(numpy.uint8))
    # (numpy exports structured dtypes with long formats: plain data once objects are excluded)
    if dtype is None and not _plain_format(view.format):
        raise TypeError(f'DemoBuffer.from_cpu needs {_ACCEPTED}; got a {type(data).__name__} '
                        f'buffer of item format {view.format!r}')
    if not view.c_contiguous:
        raise ValueError('DemoBuffer.from_cpu needs C-contiguous data (use '
                         'numpy.ascontiguousarray first)')
    if view.nbytes == 0:
        return memoryview(b'')
    if view.ndim != 1 or view.format != 'B':
        view = view.cast('B')
    return view


class DemoBuffer(Buffer):
    """A ``demo`` Buffer. Make one with :meth:`from_cpu` (one copy into shared memory) or
    :meth:`allocate` (a writable slot to fill in place); a subscriber gets a read-only one from
    ``DemoBackend.from_descriptor_with_endpoint``.

    ``memoryview(buf)``, ``numpy.asarray(buf)`` and ``numpy.from_dlpack(buf)`` see the shared
    memory itself, without a copy. The slot stays reserved as long as the Buffer or any of those
    views lives. Do not write into a published Buffer: subscribers may be reading it.
    """

    def __init__(self, host: Any, *, keepalive: Optional[Any] = None) -> None:
        """Internal: wrap ``host`` memory; ``keepalive`` is the pool's pin or hold (``None`` for
        private memory). Use :meth:`from_cpu` or :meth:`allocate`."""
        super().__init__(BACKEND_TYPE, host, keepalive=keepalive)
        self._pin = keepalive if isinstance(keepalive, Pin) else None
        self._hold = keepalive if isinstance(keepalive, Hold) else None
        self._claim = self._pin or self._hold

    @classmethod
    def received(cls, view: memoryview, hold: Hold) -> 'DemoBuffer':
        """A subscriber's DemoBuffer over the read-only ``view`` of a segment the pool mapped,
        which ``hold`` keeps (``cls(view, keepalive=hold)``, without the checks that a view of
        the pool's own need not pass: it runs for every message received)."""
        return cls.over_view(BACKEND_TYPE, view, hold, _pin=None, _hold=hold, _claim=hold)

    @classmethod
    def allocate(cls, nbytes: int) -> 'DemoBuffer':
        """A writable DemoBuffer of ``nbytes`` (contents unspecified) to fill in place."""
        if isinstance(nbytes, bool) or not isinstance(nbytes, int):
            raise TypeError(f'nbytes must be an int, got {type(nbytes).__name__}')
        if nbytes < 0:
            raise ValueError(f'nbytes must be >= 0, got {nbytes}')
        got = lifecycle.get_pool().allocate(nbytes)
        if got is None:
            return cls(bytearray(nbytes))
        view, pin = got
        return cls(view, keepalive=pin)

    @classmethod
    def from_cpu(cls, data: Any) -> 'DemoBuffer':
        """A read-only DemoBuffer holding a copy of ``data``'s raw bytes (one memcpy)."""
        source = _byte_view(data)
        got = lifecycle.get_pool().allocate(source.nbytes)
        if got is None:
            return cls(bytes(source))
        view, pin = got
        view[:] = source
        return cls(view.toreadonly(), keepalive=pin)

    def renew(self, timeout: Optional[float] = None) -> bool:
        """Wait until every subscriber is done with this published buffer (its descriptors
        taken, or given up by their ledgers at a later publish, and their views gone), then
        make it a new frame in the same memory: write into it again and publish it. False
        when ``timeout`` seconds passed first (allocate a new buffer then), for a received
        buffer, or for private memory (nothing to wait for: write into it freely)."""
        if self._pin is None:
            return False
        return lifecycle.get_pool().renew(self._pin, timeout)

    def wait_released(self, timeout: Optional[float] = None) -> bool:
        """Wait until every subscriber is done with this published buffer, as :meth:`renew`
        does, without making it a new frame: True once they are (free it, or hand it back to
        a pool of your own), False when ``timeout`` seconds passed first (0: only checks).
        Private memory is never shared: True at once. A received buffer: False (it is not
        this process's to track)."""
        if self._pin is None:
            return self._hold is None
        return lifecycle.get_pool().released(self._pin, timeout)

    @property
    def released(self) -> bool:
        """Whether every subscriber is done with this published buffer now
        (``wait_released(0)``), as pyzmq's ``MessageTracker.done``."""
        return self.wait_released(0)

    @property
    def in_shm(self) -> bool:
        """True when the bytes live in a shared-memory slot (False: private fallback memory,
        which is sent as CPU bytes)."""
        return self._claim is not None

    @property
    def pin(self) -> Optional[Pin]:
        """The publisher's pin on the slot holding the bytes (what ``DemoBackend`` describes);
        ``None`` for a received buffer or private memory."""
        return self._pin

    @property
    def hold(self) -> Optional[Hold]:
        """This subscriber's hold on the received segment holding the bytes; ``None`` for a
        buffer made here (published from) or private memory."""
        return self._hold

    @property
    def segment(self) -> Optional[Tuple[int, int]]:
        """``(publisher pid, segment id)`` of the shared segment holding the bytes (``None`` for
        private memory)."""
        return self._claim.segment if self._claim is not None else None

    @property
    def generation(self) -> Optional[int]:
        """Generation of the slot these bytes belong to (``None`` for private memory)."""
        return self._claim.generation if self._claim is not None else None

    def to_array(self) -> array.array:
        """A copy of the bytes as ``array.array('B')`` (what stock rclpy hands out)."""
        result = array.array('B')
        result.frombytes(memoryview(self))
        return result
