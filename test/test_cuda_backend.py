"""The cuda backend's parts that need no GPU: its metadata, its absence where there is no driver,
the shared machinery's media (two descriptors per handover, a reader's fence), the descriptor
magic, the DLPack and stream arguments. test/test_cuda_gpu.py runs the rest on a GPU."""
import gc
import os

import numpy
import pytest

import cuda_buffer_backend
import demo_buffer_backend
from cuda_buffer_backend import backend as cuda_backend
from cuda_buffer_backend import buffer as cuda_buffer
from demo_buffer_backend import descriptor, handover, memory
from demo_buffer_backend.pool import Pool
from rosidl_buffer_py import registry
from rosidl_buffer_py.backend import BackendUnavailable

NO_GPU = bool(cuda_buffer_backend.unavailable_reason())
DOMAIN = 'cuda1.' + handover.domain()
UUID = bytes(range(16))
TOKEN = '1234_0123456789abcdef'


# --- metadata ------------------------------------------------------------------------------------

def test_metadata_names_each_device_by_uuid_with_its_listener_token():
    meta = f'{DOMAIN}/{UUID.hex()}:{TOKEN}/{"ff" * 16}:4321_fedcba9876543210'
    assert cuda_backend.parse_metadata(meta, DOMAIN) == {
        UUID: TOKEN, b'\xff' * 16: '4321_fedcba9876543210'}


@pytest.mark.parametrize('meta', [
    None, '', 'demo', DOMAIN, f'other.{DOMAIN}/{UUID.hex()}:{TOKEN}',
    f'{DOMAIN}/{UUID.hex()}', f'{DOMAIN}/{UUID.hex()}:0_0123456789abcdef',
    f'{DOMAIN}/{UUID.hex()[:-1]}:{TOKEN}', f'{DOMAIN}/{UUID.hex().upper()}:{TOKEN}',
    f'{DOMAIN}/{UUID.hex()}:{TOKEN}/junk',
    DOMAIN + f'/{UUID.hex()}:{TOKEN}' * (cuda_backend.MAX_DEVICES + 1),
])
def test_malformed_or_foreign_metadata_serves_nothing(meta):
    assert cuda_backend.parse_metadata(meta, DOMAIN) == {}


# --- where there is no GPU ---------------------------------------------------------------------

@pytest.mark.skipif(not NO_GPU, reason='this machine has a CUDA device')
def test_without_a_driver_the_backend_is_left_out_and_says_why_to_who_asks(caplog):
    with pytest.raises(BackendUnavailable, match='CUDA'):
        cuda_backend.CudaBackend()
    backends = registry.get_installed_backends(refresh=True)
    assert 'cuda' not in backends and 'demo' in backends
    why = registry.unavailable_backends()['cuda']
    assert 'CUDA' in why
    with pytest.raises(KeyError, match='unavailable here'):
        registry.get_backend('cuda')
    from rosidl_buffer_py.image import allocate_image_msg
    with pytest.raises(ValueError, match='cuda'):
        allocate_image_msg(4, 4, 'rgb8', backend='cuda')
    with pytest.raises(RuntimeError, match='unavailable in this process'):
        cuda_buffer_backend.CudaBuffer.allocate(16)
    # a subscription that asks for it gets CPU bytes, and is told why
    assert registry.parse_acceptable_buffer_backends('cuda,demo') == {'cpu', 'demo'}


def test_the_cuda_benchmark_says_it_needs_a_gpu(capsys):
    if not NO_GPU:
        pytest.skip('this machine has a CUDA device: ./dev bench cuda runs for real')
    from launch_free_demos.bench import cuda as bench
    assert bench.main([]) == 2
    assert 'needs a CUDA GPU' in capsys.readouterr().err


# --- the DLPack and stream arguments ----------------------------------------------------------

def test_stream_arguments_follow_dlpack():
    assert cuda_buffer._stream_of(None) == 1  # the legacy default stream
    assert cuda_buffer._stream_of(2) == 2 and cuda_buffer._stream_of(-1) == -1
    assert cuda_buffer._stream_of(0x7f0012345678) == 0x7f0012345678

    class TorchLike:
        cuda_stream = 0x5000

    class CupyLike:
        ptr = 0x6000

    assert cuda_buffer._stream_of(TorchLike()) == 0x5000
    assert cuda_buffer._stream_of(CupyLike()) == 0x6000
    with pytest.raises(BufferError, match='ambiguous'):
        cuda_buffer._stream_of(0)
    with pytest.raises(ValueError, match='-1, 1, 2'):
        cuda_buffer._stream_of(-7)
    with pytest.raises(TypeError, match='stream must be'):
        cuda_buffer._stream_of('s')


def test_from_dlpack_refuses_host_tensors_and_non_producers():
    with pytest.raises(ValueError, match='CUDA tensor'):
        cuda_buffer_backend.CudaBuffer.from_dlpack(numpy.zeros(4, numpy.uint8))
    with pytest.raises(TypeError, match='DLPack producer'):
        cuda_buffer_backend.CudaBuffer.from_dlpack(b'bytes')


def test_a_producers_capsule_is_read_and_released_as_a_consumer_would():
    import sys
    a = numpy.arange(24, dtype=numpy.int16).reshape(4, 6)
    refs = sys.getrefcount(a)
    capsule = a.__dlpack__()
    address, nbytes = cuda_buffer._read_capsule(capsule)
    assert (address, nbytes) == (a.ctypes.data, 48)
    cuda_buffer._release_capsule(capsule)
    del capsule
    gc.collect()
    assert sys.getrefcount(a) == refs  # its deleter ran once
    strided = a[:, ::2].__dlpack__()
    with pytest.raises(ValueError, match='C-contiguous'):
        cuda_buffer._read_capsule(strided)
    cuda_buffer._release_capsule(strided)


# --- the shared machinery with another medium ----------------------------------------------------

class _Fence:
    def __init__(self):
        self.complete = False

    def done(self):
        return self.complete


class _TwoFdMemory(memory.SharedMemory):
    """Shared memory handed over as two descriptors (as the GPU medium's control segment and
    allocation), whose reads complete only when the test says so."""

    name = 'twofd'
    descriptor_magic = b'RBTF'
    fds_per_segment = 2
    fences = []

    @staticmethod
    def create(capacity):
        return _TwoFdSegment(capacity)

    @staticmethod
    def open_received(fds, capacity):
        os.close(fds[1])  # the second one is ours once mapped, as the GPU medium's
        return memory.open_received(fds[0], capacity)

    @classmethod
    def fence(cls, readers):
        fence = _Fence()
        cls.fences.append((set(readers), fence))
        return fence


class _TwoFdSegment(memory.Segment):
    __slots__ = ()

    def reader_fds(self):
        return [self.reader_fd(), os.dup(self.fd)]


@pytest.fixture
def two_pools():
    publisher = Pool(handover.new_token(), _TwoFdMemory)
    subscriber = Pool(handover.new_token(), _TwoFdMemory)
    yield publisher, subscriber
    gc.collect()
    publisher.shutdown()
    subscriber.shutdown()


def test_a_medium_with_two_descriptors_per_segment_and_fenced_reads(two_pools):
    from demo_buffer_backend.ledgers import EndpointLedger
    publisher, subscriber = two_pools
    assert subscriber.advertise() == subscriber.token
    subscriber.expect(b'\x01' * 16, os.getpid())
    view, pin = publisher.allocate(10000)
    view[:5] = b'hello'
    raw = publisher.describe(pin, EndpointLedger(subscriber.token, 10, per_channel=True))
    assert raw[:4] == b'RBTF'
    with pytest.raises(ValueError, match='magic'):
        descriptor.unpack(raw)  # not a demo descriptor
    got, hold = subscriber.open_descriptor(raw)
    assert bytes(got[:5]) == b'hello'
    mapping = hold.mapping
    # the reader exported it to stream 7 of device 0: dropping it waits for those reads
    hold.readers = {(0, 7)}
    del got, hold
    gc.collect()
    subscriber.sweep()
    assert mapping.refs == 1 and _TwoFdMemory.fences[-1][0] == {(0, 7)}
    _TwoFdMemory.fences[-1][1].complete = True
    subscriber.sweep()
    assert mapping.refs == 0  # released: its publisher may reuse the slot
    del pin, view
    gc.collect()
    assert publisher.allocate(10000) is not None


def test_a_handover_with_the_wrong_number_of_descriptors_is_refused(two_pools):
    import socket
    _, subscriber = two_pools
    subscriber.advertise()
    subscriber.expect(b'\x01' * 16, os.getpid())
    link = handover.Link(subscriber.token, 'twofd')
    try:
        fd = os.memfd_create('x')
        socket.send_fds(link.sock, [handover.HANDOVER.pack(handover.HANDOVER_MAGIC, 1, 1, 0,
                                                           4096)], [fd])
        os.close(fd)
        subscriber.sweep()
        assert subscriber.stats()['handovers_rejected'] == 1
    finally:
        link.close()


def test_demo_and_other_media_keep_their_own_listeners(two_pools):
    _, subscriber = two_pools
    subscriber.advertise()
    with pytest.raises(handover.ProcessGone):
        handover.Link(subscriber.token)  # the demo medium's address: nobody listens there
    demo_buffer_backend.shutdown()
