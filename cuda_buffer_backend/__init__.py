"""cuda_buffer_backend: the ``cuda`` buffer backend, payloads in GPU memory.

A publisher fills a :class:`CudaBuffer` on its GPU (``torch.from_dlpack(buf)``,
``cupy.from_dlpack(buf)``) and publishes it; a subscriber in another process on the same GPU gets
a read-only CudaBuffer over the same memory, zero-copy, as a torch or CuPy tensor through DLPack
or ``__cuda_array_interface__``, its stream waiting for the publisher's writes. Peers that cannot
map the memory get CPU bytes, identical to a stock ``uint8[]``.

- :mod:`.driver`: the CUDA driver API through ctypes (no toolkit or extra package needed);
- :mod:`.memory`: GPU memory as a medium of the demo backend's machinery (slots, ledgers, links,
  inbox, mappings): a VMM allocation exported as a POSIX file descriptor and a sealed control
  segment per slot, an interprocess event per slot, fences for reads;
- :mod:`.buffer`: :class:`CudaBuffer` (``allocate``, ``from_dlpack``, ``__dlpack__``,
  ``__cuda_array_interface__``, ``to_bytes``);
- :mod:`.backend`: :class:`CudaBackend`, the plugin; :mod:`.lifecycle`: one pool per device.

Backend metadata: ``cuda1.<demo domain>/<device uuid hex>:<token>/...``.
Pool limits are the demo backend's (``demo_buffer_backend.configure``), per device.
"""
from cuda_buffer_backend.backend import CudaBackend
from cuda_buffer_backend.buffer import BACKEND_TYPE, CudaBuffer
from cuda_buffer_backend.driver import CudaError
from cuda_buffer_backend.lifecycle import shutdown


def available() -> bool:
    """Whether this process can use CUDA (a driver and a device)."""
    from cuda_buffer_backend import driver
    try:
        driver.load()
        return True
    except driver.Unavailable:
        return False


def unavailable_reason() -> str:
    """Why this process cannot use CUDA ('' when it can)."""
    from cuda_buffer_backend import driver
    try:
        driver.load()
        return ''
    except driver.Unavailable as exc:
        return str(exc)


__all__ = ['BACKEND_TYPE', 'CudaBackend', 'CudaBuffer', 'CudaError', 'available', 'shutdown',
           'unavailable_reason']
