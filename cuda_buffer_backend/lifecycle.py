"""The process's pool of each GPU it uses: the demo backend's machinery
(:class:`demo_buffer_backend.lifecycle.Keeper`) over :class:`~.memory.CudaMedium`, one per
device, made on first use, closed at exit, forgotten in a forked child."""
import threading
from typing import Dict

from demo_buffer_backend.lifecycle import Keeper
from demo_buffer_backend.pool import Pool

from cuda_buffer_backend import driver as cuda
from cuda_buffer_backend.memory import CudaMedium

_keepers: Dict[int, Keeper] = {}
_lock = threading.Lock()


def keeper(device: int) -> Keeper:
    """The keeper of ``device``'s pool; ``RuntimeError`` naming why when CUDA is unusable here,
    ``ValueError`` for a device this process does not see."""
    found = _keepers.get(device)
    if found is not None:
        return found
    try:
        drv = cuda.load()
    except cuda.Unavailable as exc:
        raise RuntimeError(f'the cuda buffer backend is unavailable in this process: {exc}') \
            from None
    count = drv.device_count()
    if isinstance(device, bool) or not isinstance(device, int) or not 0 <= device < count:
        raise ValueError(f'device must be a CUDA device ordinal in [0, {count}), got {device!r}')
    with _lock:
        found = _keepers.get(device)
        if found is None:
            found = _keepers[device] = Keeper(CudaMedium(device))
        return found


def get_pool(device: int) -> Pool:
    return keeper(device).get_pool()


def pools() -> Dict[int, Pool]:
    """The pools made so far, by device."""
    return {device: k.get_pool() for device, k in list(_keepers.items())}


def shutdown() -> None:
    """Close every slot, link and listener of every device (also done at exit)."""
    for k in list(_keepers.values()):
        k.shutdown()
