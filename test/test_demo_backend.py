"""Tests of the ``demo`` shared-memory backend, in one process and across real processes.

Other processes are test/harness/demo_backend_peer.py, driven over JSON lines; every one is reaped.
Segments are memfds: what a process holds is read from its /proc/<pid>/maps and fd table, and
nothing of ours may ever appear in /dev/shm.
"""
import array
import errno
import gc
import hashlib
import os
import random
import resource
import threading
import time

import numpy
import pytest

import rosidl_buffer_py
from rosidl_buffer_py import Buffer, EndpointInfo, EndpointKind, MAX_DESCRIPTOR_SIZE
from rosidl_buffer_py.backend import EndpointGone

import demo_buffer_backend
from demo_buffer_backend import (DemoBackend, DemoBuffer, descriptor, diagnostics, handover,
                                 lifecycle, limits, memory)
from harness.demo_backend_peer import Peer

PEER_GID = bytes(range(16))  # what demo_backend_peer.py calls its peer


def _endpoint(gid=b'\x11' * 16, kind=EndpointKind.SUBSCRIPTION):
    return EndpointInfo(gid, '/demo_backend_test', kind)


def _shm_files():
    """Files of ours in /dev/shm: there must never be any (older versions of this backend, run
    by other test runs on this machine, name their pid: only this test's processes count)."""
    return {n for n in os.listdir('/dev/shm') if n.startswith('rbpy_')}


def _memfd_usage_of(pid):
    """Mappings and descriptors of memfds that process ``pid`` holds."""
    with open(f'/proc/{pid}/maps') as f:
        maps = sum(1 for line in f if '/memfd:' in line)
    fds = 0
    for name in os.listdir(f'/proc/{pid}/fd'):
        try:
            fds += os.readlink(f'/proc/{pid}/fd/{name}').startswith('/memfd:')
        except OSError:
            pass
    return {'maps': maps, 'fds': fds}


@pytest.fixture
def fresh():
    """A fresh process-wide pool with default limits; everything removed afterwards."""
    saved = dict(limits.current.as_dict())
    demo_buffer_backend.shutdown()
    yield
    gc.collect()
    demo_buffer_backend.shutdown()
    demo_buffer_backend.configure(**saved)
    assert not {n for n in _shm_files() if f'_{os.getpid()}_' in n}


@pytest.fixture
def backend(fresh):
    """A DemoBackend that knows PEER_GID (and the in-process endpoint) as compatible peers
    (both in this process until a peer process is started with it)."""
    be = DemoBackend()
    for gid in (PEER_GID, b'\x11' * 16):
        assert be.on_discovering_endpoint(
            _endpoint(gid), [], {'demo': be.get_backend_metadata(), 'cpu': ''}) == (True, [])
    return be


@pytest.fixture
def peers():
    started = []

    def start(backend=None):
        """A new peer process; with ``backend``, PEER_GID is re-discovered with the peer's
        metadata (its token: the process the segments are handed to)."""
        peer = Peer()
        started.append(peer)
        if backend is not None:
            assert backend.on_discovering_endpoint(
                _endpoint(PEER_GID), [], {'demo': peer.metadata}) == (True, [])
        return peer
    yield start
    for peer in started:
        peer.reap()
    assert not {n for n in _shm_files() if any(f'_{p.pid}_' in n for p in started)}


def _token(metadata):
    return metadata.rpartition('.')[2]


def _sha(data):
    import hashlib
    return hashlib.sha256(memoryview(data)).hexdigest()


# --- Buffer basics -------------------------------------------------------------------------------

@pytest.mark.parametrize('make', [
    lambda: b'hello demo backend',
    lambda: bytearray(b'\x00\x01\x02\xff' * 1000),
    lambda: memoryview(b'abcdefgh')[2:6],
    lambda: numpy.arange(12, dtype=numpy.float32).reshape(3, 4),
    lambda: numpy.arange(6, dtype='>i8'),
    lambda: numpy.array(['2024-01-01', '2025-06-30'], dtype='datetime64[D]'),
    lambda: numpy.zeros((0, 3), dtype=numpy.uint16),
])
def test_from_cpu_round_trips(fresh, make):
    data = make()
    raw = numpy.ascontiguousarray(data).tobytes() if isinstance(data, numpy.ndarray) \
        else bytes(data)
    buf = DemoBuffer.from_cpu(data)
    assert isinstance(buf, Buffer) and buf.backend_type == 'demo'
    assert buf.in_shm and buf.segment[0] == os.getpid()
    assert len(buf) == len(raw)
    assert buf.readonly
    assert buf.to_array() == array.array('B', raw)
    assert type(buf.to_array()) is array.array
    view = memoryview(buf)
    assert view.readonly and bytes(view) == raw
    assert numpy.asarray(buf).tobytes() == raw
    if raw:
        assert numpy.from_dlpack(buf).tobytes() == raw
    assert buf.to_bytes() == raw


def test_from_cpu_rejects_non_contiguous_and_non_bytes(fresh):
    with pytest.raises(ValueError, match='C-contiguous'):
        DemoBuffer.from_cpu(numpy.arange(10)[::2])
    with pytest.raises(TypeError):
        DemoBuffer.from_cpu('a str is not bytes')
    import ctypes
    for not_plain in (numpy.array([object()], dtype=object),
                      numpy.zeros(2, dtype=[('n', 'i4'), ('o', 'O')]),
                      memoryview(numpy.array([None], dtype=object)), (ctypes.c_void_p * 2)()):
        with pytest.raises(TypeError, match='plain numbers'):
            DemoBuffer.from_cpu(not_plain)
    with pytest.raises(ValueError):
        DemoBuffer.allocate(-1)


def test_allocate_is_writable_shared_memory_without_copies(fresh):
    buf = DemoBuffer.allocate(1 << 16)
    assert not buf.readonly and buf.in_shm and len(buf) == 1 << 16
    a = numpy.asarray(buf)
    a[:] = 7
    b = numpy.from_dlpack(buf)
    b[0] = 9  # the same memory
    assert memoryview(buf)[0] == 9 and memoryview(buf)[1] == 7
    # the bytes are the segment's: read them through its descriptor
    fd = lifecycle.get_pool().slots.by_id[buf.segment[1]].segment.fd
    assert os.pread(fd, 4, memory.HEADER_SIZE) == bytes([9, 7, 7, 7])


def test_segments_are_sealed_backed_memfds_and_small_descriptors(backend):
    import fcntl
    buf = DemoBuffer.from_cpu(b'x' * 5000)
    fd = lifecycle.get_pool().slots.by_id[buf.segment[1]].segment.fd
    assert os.readlink(f'/proc/self/fd/{fd}').startswith('/memfd:rbpy_demo')
    assert fcntl.fcntl(fd, fcntl.F_GET_SEALS) == memory.SEALS
    st = os.fstat(fd)
    assert st.st_size == memory.HEADER_SIZE + 8192 and st.st_blocks * 512 >= st.st_size
    for attack in (lambda: os.ftruncate(fd, 4096), lambda: os.ftruncate(fd, 1 << 20),
                   lambda: os.pwrite(fd, b'z', memory.HEADER_SIZE)):
        with pytest.raises(PermissionError):
            attack()
    assert bytes(memoryview(buf)) == b'x' * 5000
    assert not {n for n in _shm_files() if f'_{os.getpid()}_' in n}
    desc = backend.create_descriptor_with_endpoint(buf, _endpoint())
    assert isinstance(desc, bytes) and len(desc) == descriptor.SIZE < 64 < MAX_DESCRIPTOR_SIZE


# --- descriptors ---------------------------------------------------------------------------------

def test_descriptor_round_trip_in_process_is_zero_copy_and_read_only(backend):
    ep = _endpoint()
    buf = DemoBuffer.allocate(4096 * 3 + 5)
    numpy.asarray(buf)[:] = numpy.arange(len(buf)) % 251
    desc = backend.create_descriptor_with_endpoint(buf, ep)
    got = backend.from_descriptor_with_endpoint(desc, ep)
    assert isinstance(got, DemoBuffer) and got.readonly and got.in_shm
    assert got.segment == buf.segment and got.generation == buf.generation
    assert (buf.pin.slot.id, buf.hold, got.pin) == (buf.segment[1], None, None)
    assert got.hold.mapping.key.segment_id == buf.segment[1]  # what republishing cannot describe
    assert bytes(memoryview(got)) == bytes(memoryview(buf))
    # the receive path's unchecked constructor makes what the checked one would
    checked = DemoBuffer(memoryview(got), keepalive=got.hold)
    assert vars(checked) == vars(got)
    assert (len(checked), checked.readonly, repr(checked)) == (len(got), True, repr(got))
    del checked
    numpy.asarray(buf)[0] = 200  # the subscriber's view is the same memory
    assert numpy.asarray(got)[0] == 200
    with pytest.raises(ValueError):
        numpy.asarray(got)[0] = 1
    with pytest.raises(TypeError):
        memoryview(got)[0] = 1
    stats = demo_buffer_backend.stats()
    assert stats['descriptors_created'] == 1 and stats['taken'] == 1
    assert stats['views_held'] == 1
    del got
    assert demo_buffer_backend.stats()['views_held'] == 0


def test_descriptor_round_trip_in_other_process_is_zero_copy(backend, peers):
    peer = peers(backend)
    ours = backend.get_backend_metadata()
    # the same domain, another process's token
    assert peer.metadata.rpartition('.')[0] == ours.rpartition('.')[0]
    assert _token(peer.metadata) != _token(ours)
    assert handover.token_pid(_token(peer.metadata)) == peer.pid
    assert backend.parse_metadata(peer.metadata) == (True, _token(peer.metadata))
    buf = DemoBuffer.allocate(1 << 20)
    a = numpy.asarray(buf)
    a[:] = numpy.arange(len(buf)) % 253
    desc = backend.create_descriptor_with_endpoint(buf, _endpoint(PEER_GID))
    reply = peer('take', desc=desc.hex(), key='v')
    assert reply['ok'] and reply['n'] == 1 << 20
    assert reply['sha'] == _sha(buf)
    assert reply['readonly'] and reply['write_rejected']
    a[:] = 42  # still pinned by us: write through, the reader's view shows it (zero copy)
    assert peer('sha', key='v')['sha'] == _sha(buf)
    stats = peer('stats')
    assert stats['mappings_opened'] == stats['handovers_received'] == 1
    assert demo_buffer_backend.stats()['handovers_sent'] == 1
    # one segment, mapped once (CPython's mmap keeps a dup of the descriptor: 2 fds)
    assert peer('memory') == {'maps': 1, 'fds': 2}
    peer.exit()


def test_view_held_in_other_process_survives_100_more_frames(backend, peers):
    demo_buffer_backend.configure(max_inflight_per_peer=10)  # batches of 10 in flight
    peer = peers(backend)
    ep = _endpoint(PEER_GID)
    n = 64 * 1024
    first = DemoBuffer.allocate(n)
    numpy.asarray(first)[:] = 1
    reply = peer('take', desc=backend.create_descriptor_with_endpoint(first, ep).hex(), key='h')
    assert reply['ok']
    held_sha = reply['sha']
    held_segment = first.segment
    del first
    for batch in range(10):
        descs, shas = [], []
        for i in range(10):
            frame = DemoBuffer.allocate(n)
            numpy.asarray(frame)[:] = (batch * 10 + i + 2) % 256
            assert frame.in_shm
            assert frame.segment != held_segment  # never reused while held
            descs.append(backend.create_descriptor_with_endpoint(frame, ep).hex())
            shas.append(_sha(frame))
            del frame
        assert peer('take_drop', descs=descs)['digests'] == shas
        assert peer('sha', key='h')['sha'] == held_sha
    stats = demo_buffer_backend.stats()
    assert stats['fallbacks'] == 0 and stats['slots'] <= 12
    peer.exit()


# --- pool limits, fallback, holders ----------------------------------------------------------------

def test_pool_grows_to_cap_then_falls_back_and_recovers(backend):
    demo_buffer_backend.configure(max_slots=3, reclaim_timeout=3600)
    ep = _endpoint()
    held = []
    for i in range(3):
        buf = DemoBuffer.from_cpu(bytes([i]) * 10000)
        held.append(backend.from_descriptor_with_endpoint(
            backend.create_descriptor_with_endpoint(buf, ep), ep))
    assert demo_buffer_backend.stats()['slots'] == 3
    fallback = DemoBuffer.from_cpu(b'z' * 10000)  # every slot is held: private memory
    assert not fallback.in_shm and fallback.segment is None
    assert bytes(memoryview(fallback)) == b'z' * 10000
    assert backend.create_descriptor_with_endpoint(fallback, ep) is None
    writable = DemoBuffer.allocate(10)
    assert not writable.in_shm and not writable.readonly
    stats = demo_buffer_backend.stats()
    assert stats['fallbacks'] == 2 and stats['slots'] == 3
    assert stats['descriptors_declined'] >= 1
    del held[0]  # one hold released: that slot comes back
    again = DemoBuffer.from_cpu(b'y' * 10000)
    assert again.in_shm and demo_buffer_backend.stats()['fallbacks'] == 2


def test_publisher_buffer_pins_its_slot(backend):
    demo_buffer_backend.configure(max_slots=1)
    first = DemoBuffer.allocate(100)
    assert first.in_shm
    assert not DemoBuffer.allocate(100).in_shm
    view = memoryview(first)
    del first  # the view still pins it
    assert not DemoBuffer.allocate(100).in_shm
    del view
    assert DemoBuffer.allocate(100).in_shm


def test_untaken_descriptor_blocks_reuse_until_reclaim_timeout(backend):
    demo_buffer_backend.configure(max_slots=1, reclaim_timeout=3600)
    ep = _endpoint()
    buf = DemoBuffer.from_cpu(b'a' * 100)
    old = backend.create_descriptor_with_endpoint(buf, ep)
    del buf
    assert not DemoBuffer.allocate(100).in_shm  # in flight to a subscriber
    demo_buffer_backend.configure(reclaim_timeout=0)
    new = DemoBuffer.allocate(100)
    assert new.in_shm and new.generation == 2
    assert demo_buffer_backend.stats()['reclaimed'] == 1
    with pytest.raises(ValueError, match='stale'):
        backend.from_descriptor_with_endpoint(old, ep)  # the late taker
    assert demo_buffer_backend.stats()['stale'] == 1


def test_wrong_size_free_slots_are_evicted_at_the_cap(backend):
    demo_buffer_backend.configure(max_slots=2)
    for n in (100, 200_000):
        DemoBuffer.allocate(n)
    before = demo_buffer_backend.stats()
    assert DemoBuffer.allocate(3_000_000).in_shm
    after = demo_buffer_backend.stats()
    assert after['slots'] == 2 and after['segments_removed'] == before['segments_removed'] + 1


def test_killed_holder_releases_its_slot(backend, peers):
    demo_buffer_backend.configure(max_slots=1)
    peer = peers(backend)
    buf = DemoBuffer.from_cpu(b'k' * 3000)
    segment = buf.segment
    assert peer('take', desc=backend.create_descriptor_with_endpoint(
        buf, _endpoint(PEER_GID)).hex(), key='h')['ok']
    del buf
    assert not DemoBuffer.allocate(3000).in_shm  # held by the peer
    peer.kill9()
    reused = DemoBuffer.allocate(3000)
    assert reused.in_shm and reused.segment == segment and reused.generation == 2
    with pytest.raises(EndpointGone):  # its process is gone: nothing more is sent to it
        backend.create_descriptor_with_endpoint(reused, _endpoint(PEER_GID))
    assert demo_buffer_backend.stats()['peers_gone'] == 1


def test_killed_publisher_frames_in_flight_stay_readable_then_nothing_is_left(fresh, peers):
    """A publisher SIGKILLed with frames in flight: a slow subscriber that had not taken any of
    them yet still reads every one (their segments were handed over with the frames); once it
    drops them, it holds no memory of that publisher (its maps and fds), and nothing was ever
    in /dev/shm."""
    reader, publisher = peers(), peers()
    assert reader('orphan_seconds', value=0.5)['ok']
    assert publisher('discover', metadata=reader.metadata)['compatible']
    assert reader('expect_publisher', metadata=publisher.metadata, gid='ab' * 16)['compatible']
    sent = []
    for i, n in enumerate((10, 5000, 70000, 1 << 20, 5000)):  # the last one reuses no slot
        reply = publisher('publish', n=n, fill=i + 1, keep=str(i))
        assert reply['in_shm'] and reply['desc'] and not reply['gone'], reply
        sent.append((reply['desc'], hashlib.sha256(bytes([i + 1]) * n).hexdigest()))
    assert reader('stats')['taken'] == 0
    publisher.kill9()
    for i, (desc, sha) in enumerate(sent):
        reply = reader('take', desc=desc, key=str(i))
        assert reply['ok'] and reply['sha'] == sha, reply
    assert reader('memory') == {'maps': 5, 'fds': 10}  # (mmap keeps a dup of each fd)
    for i in range(len(sent)):
        assert reader('drop', key=str(i))['ok']
    time.sleep(0.6)
    assert reader('sweep')['ok']
    assert reader('memory') == {'maps': 0, 'fds': 0}
    assert _memfd_usage_of(reader.pid) == {'maps': 0, 'fds': 0}
    stats = reader('stats')
    assert stats['handovers_received'] == 5 and stats['mappings_closed'] == 5, stats
    assert not {n for n in _shm_files() if f'_{publisher.pid}_' in n or f'_{reader.pid}_' in n}
    reader.exit()


def test_held_views_outlive_their_publisher_until_dropped(fresh, peers):
    """A view held across the publisher's normal exit stays valid; the segment goes when the
    view does, not before (its publisher hung up: the grace period is for late descriptors)."""
    reader, publisher = peers(), peers()
    assert reader('orphan_seconds', value=0.0)['ok']
    publisher('discover', metadata=reader.metadata)
    reader('expect_publisher', metadata=publisher.metadata, gid='ab' * 16)
    reply = publisher('publish', n=4096, fill=5, keep='p')
    assert reader('take', desc=reply['desc'], key='r')['ok']
    sha = reader('sha', key='r')['sha']
    publisher.exit()
    assert reader('sweep')['ok']
    assert reader('sha', key='r')['sha'] == sha  # the view outlives its publisher
    assert reader('memory') == {'maps': 1, 'fds': 2}
    assert reader('drop', key='r')['ok'] and reader('sweep')['ok']
    assert reader('memory') == {'maps': 0, 'fds': 0}
    reader.exit()


def test_shutdown_closes_our_segments_and_fork_child_leaves_them(fresh):
    buf = DemoBuffer.from_cpu(b'f' * 100)
    segment = buf.segment
    pid = os.fork()
    if pid == 0:  # the child inherits the pool but must never touch the parent's segments
        code = 1
        try:
            # its at-fork hook forgot the parent's pool: the child's own, made anew
            pool = lifecycle.get_pool()
            code = 0 if pool.pid == os.getpid() and not pool.slots.by_id else 2
            demo_buffer_backend.shutdown()
        finally:
            os._exit(code)
    assert os.waitpid(pid, 0)[1] == 0
    assert segment[1] in lifecycle.get_pool().slots.by_id
    assert DemoBuffer.from_cpu(b'g' * 100).in_shm
    demo_buffer_backend.shutdown()
    assert demo_buffer_backend.stats()['slots'] == 0
    assert bytes(memoryview(buf)) == b'f' * 100  # a live Buffer keeps its mapping
    del buf
    gc.collect()
    assert _memfd_usage_of(os.getpid()) == {'maps': 0, 'fds': 0}


# --- malformed descriptors -----------------------------------------------------------------------

def _forge(good, **changes):
    d = descriptor.unpack(good)._replace(**changes)
    return descriptor.pack(d)


def _malformed(good: bytes) -> dict:
    """Malformed and forged forms of the descriptor ``good``, by label (some may still
    name its bytes: a bit flip in a field that does not matter)."""
    d = descriptor.unpack(good)
    bad = {
        'not bytes': 12345,
        'empty': b'',
        'bad magic': b'XXXX' + good[4:],
        'bad version': good[:4] + b'\x09' + good[5:],
        'reserved bits': good[:5] + b'\x01' + good[6:],
        'trailing byte': good + b'\x00',
        'other pid': _forge(good, pid=d.pid + 1),
        'pid zero': _forge(good, pid=0),
        'other nonce': _forge(good, nonce=d.nonce ^ 1),
        'segment never handed over': _forge(good, segment_id=d.segment_id + 1000),
        'offset outside': _forge(good, offset=1 << 30),
        'size outside': _forge(good, size=d.size + 10 ** 9),
        'wrong size': _forge(good, size=d.size - 1),
        'wrong offset': _forge(good, offset=16, size=d.size - 16),
        'stale generation': _forge(good, generation=d.generation + 1),
        'generation zero': _forge(good, generation=0),
        'huge size': _forge(good, size=1 << 62),
    }
    for length in range(len(good)):
        bad[f'truncated to {length}'] = good[:length]
    rng = random.Random(1234)
    for i in range(200):
        bad[f'random {i}'] = bytes(rng.randrange(256) for _ in range(rng.randrange(120)))
    for i in range(200):  # random corruptions of the valid descriptor
        corrupted = bytearray(good)
        corrupted[rng.randrange(len(good))] ^= 1 << rng.randrange(8)
        bad[f'bit flip {i}'] = bytes(corrupted)
    return bad


def test_malformed_descriptors_raise_value_error(backend):
    ep = _endpoint()
    buf = DemoBuffer.from_cpu(b'm' * 6000)
    good = backend.create_descriptor_with_endpoint(buf, ep)
    bad = _malformed(good)
    rejected = 0
    for label, raw in bad.items():
        if isinstance(raw, bytes) and raw == good:
            continue
        try:
            got = backend.from_descriptor_with_endpoint(raw, ep)
        except ValueError as exc:
            assert str(exc), label
            rejected += 1
            continue
        # A bit flip may only land in a field that still names exactly the same bytes.
        assert label.startswith('bit flip') and bytes(memoryview(got)) == b'm' * 6000, label
    stats = demo_buffer_backend.stats()
    assert stats['rejected'] == rejected > 300
    assert stats['views_held'] == 0  # no hold leaked by a rejection
    ok = backend.from_descriptor_with_endpoint(good, ep)  # still fine afterwards
    assert bytes(memoryview(ok)) == b'm' * 6000


def test_the_steady_opener_opens_what_the_general_open_opens_or_opens_nothing(backend):
    """``DemoBackend.steady_opener`` (a subscription's hot path) gives the DemoBuffer that
    ``from_descriptor_with_endpoint`` gives; for anything it does not open it returns None
    having opened, held and rejected nothing, and the general open then says why."""
    ep = _endpoint()
    opener = backend.steady_opener(ep)
    buf = DemoBuffer.from_cpu(b'm' * 6000)
    good = backend.create_descriptor_with_endpoint(buf, ep)
    general = backend.from_descriptor_with_endpoint(good, ep)
    taken = demo_buffer_backend.stats()['taken']
    steady = opener(good)
    assert isinstance(steady, DemoBuffer) and demo_buffer_backend.stats()['taken'] == taken + 1
    assert (steady.segment, steady.generation, steady.readonly, bytes(memoryview(steady))) == \
        (general.segment, general.generation, general.readonly, bytes(memoryview(general)))
    assert steady.hold.mapping is general.hold.mapping and steady.pin is None
    del steady, general
    declined = 0
    for label, raw in _malformed(good).items():
        before = demo_buffer_backend.stats()
        got = opener(raw)
        if got is not None:  # a bit flip that still names exactly the same bytes
            assert label.startswith('bit flip') and bytes(memoryview(got)) == b'm' * 6000, label
            del got
            continue
        declined += 1
        after = demo_buffer_backend.stats()
        assert {k: after[k] for k in ('taken', 'rejected', 'views_held', 'stale')} == \
            {k: before[k] for k in ('taken', 'rejected', 'views_held', 'stale')}, label
        if isinstance(raw, bytes):
            with pytest.raises(ValueError):
                backend.from_descriptor_with_endpoint(raw, ep)
    assert declined > 300


def test_stale_generation_after_reuse_is_rejected(backend):
    demo_buffer_backend.configure(max_slots=1)
    ep = _endpoint()
    buf = DemoBuffer.from_cpu(b'1' * 50)
    old = backend.create_descriptor_with_endpoint(buf, ep)
    backend.from_descriptor_with_endpoint(old, ep)  # taken and released at once
    del buf
    new_buf = DemoBuffer.from_cpu(b'2' * 50)
    assert new_buf.generation == 2
    with pytest.raises(ValueError, match='stale'):
        backend.from_descriptor_with_endpoint(old, ep)
    assert demo_buffer_backend.stats()['stale'] == 1


# --- backend contract ----------------------------------------------------------------------------

def test_metadata_and_compatibility(fresh):
    be = DemoBackend()
    meta = be.get_backend_metadata()
    assert be.get_backend_type() == 'demo'
    assert meta and ';' not in meta and '=' not in meta and meta.isprintable()
    boot = open('/proc/sys/kernel/random/boot_id').read().strip().replace('-', '')
    assert boot in meta
    buf = DemoBuffer.from_cpu(b'c' * 10)
    same, other, legacy, unknown = (_endpoint(bytes([i]) * 16) for i in (1, 2, 3, 4))
    assert be.on_discovering_endpoint(same, [], {'demo': meta}) == (True, [])
    assert be.on_discovering_endpoint(other, [], {'demo': meta + 'x'}) == (False, [])
    domain, _, token = meta.rpartition('.')
    assert handover.parse_token(token) == token and handover.token_pid(token) == os.getpid()
    assert meta.split('.')[:6] == domain.split('.') and domain.startswith('mfd1.')
    assert be.on_discovering_endpoint(legacy, [], {'cpu': ''}) == (False, [])
    assert be.create_descriptor_with_endpoint(buf, same) is not None
    assert be.create_descriptor_with_endpoint(buf, other) is None
    assert be.create_descriptor_with_endpoint(buf, legacy) is None
    assert be.create_descriptor_with_endpoint(buf, unknown) is None
    assert be.create_descriptor_with_endpoint(Buffer('cpu', b'abc'), same) is None
    be.on_removing_endpoint(same)
    assert be.create_descriptor_with_endpoint(buf, same) is None
    assert DemoBackend().get_backend_metadata() == meta
    assert isinstance(be.allocate(10), DemoBuffer)


def test_registry_finds_demo_through_the_entry_point():
    backends = rosidl_buffer_py.get_installed_backends(refresh=True)
    assert isinstance(backends['demo'], DemoBackend)
    assert rosidl_buffer_py.get_backend('demo').get_backend_type() == 'demo'


def test_limits_from_configure_and_constructor(fresh):
    assert DemoBackend(max_slots=5, max_pool_bytes=1 << 20).stats()['max_slots'] == 5
    assert demo_buffer_backend.configure()['max_pool_bytes'] == 1 << 20
    with pytest.raises(ValueError):
        demo_buffer_backend.configure(max_slots=-1)
    assert not DemoBuffer.allocate(2 << 20).in_shm  # bigger than the whole pool


def test_limits_from_environment(fresh, monkeypatch):
    monkeypatch.setenv(limits.ENV_MAX_SLOTS, '7')
    monkeypatch.setenv(limits.ENV_MAX_POOL_BYTES, '12345678')
    monkeypatch.setenv(limits.ENV_RECLAIM_TIMEOUT, '1.5')
    read = limits.Limits()
    assert (read.max_slots, read.max_pool_bytes, read.reclaim_timeout) == (7, 12345678, 1.5)


# --- steady state --------------------------------------------------------------------------------

def test_steady_state_creates_and_maps_nothing(backend, monkeypatch):
    ep = _endpoint()
    n = 1 << 20
    calls = {'create': 0, 'map': 0}

    def counting(key, func):
        def wrapper(*args, **kwargs):
            calls[key] += 1
            return func(*args, **kwargs)
        return wrapper

    def frame(i):
        buf = DemoBuffer.allocate(n)
        numpy.asarray(buf)[:] = i % 256
        got = backend.from_descriptor_with_endpoint(
            backend.create_descriptor_with_endpoint(buf, ep), ep)
        del buf
        assert numpy.asarray(got)[n - 1] == i % 256

    for i in range(3):  # warm-up
        frame(i)
    usage = _memfd_usage_of(os.getpid())
    for key, name in (('create', 'Segment'), ('map', 'open_received')):
        monkeypatch.setattr(memory, name, counting(key, getattr(memory, name)))
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for i in range(200):
        frame(i)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
    assert calls == {'create': 0, 'map': 0}
    assert _memfd_usage_of(os.getpid()) == usage
    # 200 MiB written and read: without pre-faulted, cached mappings that would be 51200 faults
    assert faults < 2000
    assert demo_buffer_backend.stats()['taken'] == 203


def test_threads_share_the_pool_safely(backend):
    ep = _endpoint()
    errors = []

    def worker(seed):
        try:
            for i in range(150):
                payload = bytes([seed]) * (1000 + seed)
                buf = DemoBuffer.from_cpu(payload)
                desc = backend.create_descriptor_with_endpoint(buf, ep)
                if desc is not None:
                    got = backend.from_descriptor_with_endpoint(desc, ep)
                    assert bytes(memoryview(got)) == payload
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(s,)) for s in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert demo_buffer_backend.stats()['views_held'] == 0


def test_compatibility_needs_the_domain_and_a_token(fresh):
    be = DemoBackend()
    meta = be.get_backend_metadata()
    domain, _, token = meta.rpartition('.')
    buf = DemoBuffer.from_cpu(b't' * 10)
    other = f'{os.getpid() + 1}_0123456789abcdef'  # another process of the same domain
    boot, net, mnt, pid_ns, uid = domain.split('.')[1:]
    cases = {
        f'{domain}.{other}': (True, other),  # compatible, but nobody listens: gone (below)
        meta: (True, token),
        domain: (False, None),  # no token: nowhere to hand segments to
        f'mfd1.{"0" * 32}.{net}.{mnt}.{pid_ns}.{uid}.{token}': (False, None),  # another boot
        f'mfd1.{boot}.1.{mnt}.{pid_ns}.{uid}.{token}': (False, None),  # another network ns
        f'mfd1.{boot}.{net}.1.{pid_ns}.{uid}.{token}': (False, None),  # another mount ns
        f'mfd1.{boot}.{net}.{mnt}.1.{uid}.{token}': (False, None),  # another pid ns
        f'mfd1.{boot}.{net}.{mnt}.{pid_ns}.{os.geteuid() + 1:x}.{token}': (False, None),
        f'shm1.{boot}.1.2.{uid}.{token}': (False, None),  # the /dev/shm design's metadata
        f'{domain}.{token}.extra': (False, None),
        f'{domain}.not_a_token': (False, None),
        f'{domain}.12_0123456789ABCDEF': (False, None),
        f'{domain}.0_0123456789abcdef': (False, None),
        f'{domain}../../etc_0123456789abcdef': (False, None),
        f'{domain}.': (False, None),
        '': (False, None),
    }
    for i, (metadata, expected) in enumerate(cases.items()):
        ep = _endpoint(bytes([i + 1]) * 16)
        assert be.parse_metadata(metadata) == expected, metadata
        assert be.on_discovering_endpoint(ep, [], {'demo': metadata}) == (expected[0], [])
        assert be.is_compatible(ep) == expected[0]
        assert be.peer_token(ep) == expected[1]
        if expected[1] == other:
            with pytest.raises(EndpointGone):
                be.create_descriptor_with_endpoint(buf, ep)
        else:
            assert (be.create_descriptor_with_endpoint(buf, ep) is not None) == expected[0]
    assert be.parse_metadata(None) == (False, None)


# --- dead recipients -----------------------------------------------------------------------------

def test_killed_recipient_stops_pinning_slots_live_ones_keep_theirs(backend, peers):
    """Descriptors for a SIGKILLed subscriber stop pinning slots at once (its link hangs up);
    a live subscriber's untaken descriptors and held views stay protected."""
    demo_buffer_backend.configure(max_slots=4, reclaim_timeout=3600,
                                  max_inflight_per_peer=4)  # each may pin every slot
    survivor, victim = peers(), peers()
    to_survivor, to_victim = _endpoint(b'\xa1' * 16), _endpoint(b'\xb2' * 16)
    for ep, peer in ((to_survivor, survivor), (to_victim, victim)):
        assert backend.on_discovering_endpoint(ep, [], {'demo': peer.metadata}) == (True, [])
    n = 50_000
    frames = []
    for i in range(4):
        buf = DemoBuffer.allocate(n)
        numpy.asarray(buf)[:] = 10 + i
        assert buf.in_shm
        frames.append(dict(segment=buf.segment, sha=_sha(buf),
                           a=backend.create_descriptor_with_endpoint(buf, to_survivor).hex(),
                           b=backend.create_descriptor_with_endpoint(buf, to_victim).hex()))
        del buf
    # The survivor holds frame 0 and took frames 1 and 2; frame 3 is still in flight to it.
    assert survivor('take', desc=frames[0]['a'], key='held')['sha'] == frames[0]['sha']
    assert survivor('take_drop', descs=[f['a'] for f in frames[1:3]])['digests'] == \
        [f['sha'] for f in frames[1:3]]
    # The victim took only frame 3 (then died): its take must not count as the survivor's.
    assert victim('take_drop', descs=[frames[3]['b']])['digests'] == [frames[3]['sha']]
    assert not DemoBuffer.allocate(n).in_shm  # all alive: the slow victim pins frames 0..2
    assert not DemoBuffer.allocate(n).in_shm

    victim.kill9()
    killed_at = time.monotonic()
    reused = []
    while True:
        buf = DemoBuffer.allocate(n)
        if buf.in_shm:
            break
        assert time.monotonic() - killed_at < 10.0, demo_buffer_backend.stats()
        time.sleep(0.01)
    latency = time.monotonic() - killed_at
    reused.append(buf)
    reused.append(DemoBuffer.allocate(n))
    stats = demo_buffer_backend.stats()
    # exactly frames 1 and 2 came back: 0 is held by the survivor, 3 is in flight to it
    assert {b.segment for b in reused} == {frames[1]['segment'], frames[2]['segment']}, stats
    assert all(b.in_shm and b.generation == 2 for b in reused)
    assert not DemoBuffer.allocate(n).in_shm
    assert stats['peers_gone'] == 1 and stats['reclaimed'] == 0, stats
    assert stats['slots'] == 4
    with pytest.raises(EndpointGone):
        backend.create_descriptor_with_endpoint(reused[0], to_victim)
    # the survivor's bytes are intact and its late take is not stale
    assert survivor('sha', key='held')['sha'] == frames[0]['sha']
    late = survivor('take', desc=frames[3]['a'], key='late')
    assert late['ok'] and late['sha'] == frames[3]['sha'], late
    survivor.exit()
    print(f'slots reusable {latency * 1000:.0f} ms after the SIGKILL')


def test_removed_endpoint_of_a_live_process_keeps_its_slot_until_the_process_exits(
        backend, peers):
    demo_buffer_backend.configure(max_slots=1, reclaim_timeout=3600)
    slow = peers()
    ep = _endpoint(b'\xc3' * 16)
    backend.on_discovering_endpoint(ep, [], {'demo': slow.metadata})
    buf = DemoBuffer.allocate(1000)
    backend.create_descriptor_with_endpoint(buf, ep)
    del buf
    for _ in range(300):
        assert not DemoBuffer.allocate(1000).in_shm  # a live, slow subscriber keeps its slot
    backend.on_removing_endpoint(ep)  # its endpoint went away but its process lives: kept
    assert not DemoBuffer.allocate(1000).in_shm
    slow.exit()  # now it is gone: its link hangs up, the slot comes back
    assert DemoBuffer.allocate(1000).in_shm
    assert demo_buffer_backend.stats()['peers_gone'] == 1


# --- fairness: per-peer ledgers ------------------------------------------------------------------

PUBLISHER_GID = b'\xee' * 16  # the local publisher the backend is called for


def _discovered(be, gid, depth=None, metadata=None):
    ep = EndpointInfo(gid, '/demo_backend_test', EndpointKind.SUBSCRIPTION, history_depth=depth,
                      local_gid=PUBLISHER_GID)
    assert be.on_discovering_endpoint(
        ep, [], {'demo': metadata or be.get_backend_metadata()}) == (True, [])
    return ep


def test_keep_last_window_stops_pinning_what_the_peer_can_no_longer_take(backend):
    """A KEEP_LAST 2 peer that never takes pins at most 2 slots: the pool of 4 never runs dry."""
    demo_buffer_backend.configure(max_slots=4, max_inflight_per_peer=4, reclaim_timeout=3600)
    ep = _discovered(backend, b'\x21' * 16, depth=2)
    for _ in range(40):
        buf = DemoBuffer.allocate(5000)
        assert buf.in_shm, demo_buffer_backend.stats()
        assert backend.create_descriptor_with_endpoint(buf, ep) is not None
        del buf
        assert backend.peer_ledgers()[f'{ep.gid_hex}/{PUBLISHER_GID.hex()}']['in_flight'] <= 2
    stats = demo_buffer_backend.stats()
    assert stats['released_window'] >= 38 and stats['fallbacks'] == 0, stats
    # without the publisher's GID the window would count other channels' messages: not applied
    unnamed = EndpointInfo(ep.gid, ep.topic_name, ep.endpoint_kind, history_depth=2)
    demo_buffer_backend.configure(max_slots=8)
    for _ in range(3):
        assert backend.create_descriptor_with_endpoint(DemoBuffer.allocate(5000), unnamed)
    assert backend.peer_ledgers()[ep.gid_hex] == dict(
        backend.peer_ledgers()[ep.gid_hex], depth=None, in_flight=3)


@pytest.mark.parametrize('history', [None, 0], ids=['unknown', 'keep_all'])
def test_share_caps_what_one_peer_pins_the_others_keep_zero_copy(backend, peers, history):
    """A peer (another live process) that never takes pins no more than its share; a peer that
    takes gets every frame zero-copy and the pool never falls back. When the stuck peer's
    history is not known, past its share its oldest are given up and it keeps getting
    descriptors; when it is known (KEEP_ALL here), nothing it can still take is given up: its
    next frames go as CPU bytes, and what it was sent stays valid."""
    demo_buffer_backend.configure(max_slots=4, max_inflight_per_peer=1, reclaim_timeout=3600)
    stuck_peer = peers()
    stuck = _discovered(backend, b'\x31' * 16, depth=history, metadata=stuck_peer.metadata)
    healthy = _discovered(backend, b'\x32' * 16, depth=0)
    to_stuck = []
    for i in range(30):
        buf = DemoBuffer.from_cpu(bytes([i]) * 3000)
        assert buf.in_shm, demo_buffer_backend.stats()
        to_stuck.append((buf.segment, buf.generation,
                         backend.create_descriptor_with_endpoint(buf, stuck)))
        desc = backend.create_descriptor_with_endpoint(buf, healthy)
        assert desc is not None
        del buf
        assert bytes(memoryview(backend.from_descriptor_with_endpoint(desc, healthy))) == \
            bytes([i]) * 3000
        assert backend.peer_ledgers()[f'{stuck.gid_hex}/{PUBLISHER_GID.hex()}'][
            'in_flight'] == 1
    stats = demo_buffer_backend.stats()
    assert stats['fallbacks'] == stats['reclaimed'] == 0, stats
    if history is None:
        assert stats['released_share'] == 29 and stats['descriptors_declined'] == 0, stats
        assert all(d is not None for _, _, d in to_stuck)
        kept, fill = to_stuck[-1], 29  # its share (the last frame) is protected
    else:
        assert stats['released_share'] == 0, stats
        assert stats['cpu_past_share'] == stats['descriptors_declined'] == 29, stats
        assert to_stuck[0][2] is not None and all(d is None for _, _, d in to_stuck[1:])
        kept, fill = to_stuck[0], 0  # what it was sent first, never given up
    # never reused, and it can still take it
    segment, generation, desc = kept
    assert lifecycle.get_pool().slots.by_id[segment[1]].generation == generation
    assert stuck_peer('take', desc=desc.hex(), key='kept')['sha'] == \
        hashlib.sha256(bytes([fill]) * 3000).hexdigest()


def test_a_dead_peer_with_its_share_in_flight_gets_nothing_not_cpu_bytes(backend, peers):
    """A peer whose history is known and whose share is in flight gets CPU bytes while it
    lives; once its process is gone, it gets nothing (EndpointGone), as any dead peer."""
    demo_buffer_backend.configure(max_slots=8, max_inflight_per_peer=1, reclaim_timeout=3600)
    peer = peers()
    ep = _discovered(backend, b'\x35' * 16, depth=0, metadata=peer.metadata)
    first = DemoBuffer.allocate(100)
    assert backend.create_descriptor_with_endpoint(first, ep) is not None
    assert backend.create_descriptor_with_endpoint(DemoBuffer.allocate(100), ep) is None
    peer.kill9()
    with pytest.raises(EndpointGone):
        backend.create_descriptor_with_endpoint(DemoBuffer.allocate(100), ep)
    assert demo_buffer_backend.stats()['cpu_past_share'] == 1


def test_in_order_takes_release_what_the_peer_skipped(backend):
    demo_buffer_backend.configure(max_slots=8, max_inflight_per_peer=3, reclaim_timeout=3600)
    ep = _discovered(backend, b'\x41' * 16, depth=0)
    bufs = [DemoBuffer.allocate(100) for _ in range(3)]
    descs = [backend.create_descriptor_with_endpoint(b, ep) for b in bufs]
    assert all(descs)
    key = f'{ep.gid_hex}/{PUBLISHER_GID.hex()}'
    assert backend.peer_ledgers()[key]['in_flight'] == 3
    held = backend.from_descriptor_with_endpoint(descs[2], ep)  # 0 and 1 were dropped (lossy)
    assert backend.create_descriptor_with_endpoint(bufs[0], ep) is not None
    assert demo_buffer_backend.stats()['released_skipped'] == 2
    assert backend.peer_ledgers()[key]['in_flight'] == 1
    del held
    # without the publisher's GID the ledger may mix channels, whose takes are not ordered
    unnamed = EndpointInfo(ep.gid, ep.topic_name, ep.endpoint_kind)
    bufs = [DemoBuffer.allocate(100) for _ in range(3)]
    descs = [backend.create_descriptor_with_endpoint(b, unnamed) for b in bufs]
    held = backend.from_descriptor_with_endpoint(descs[2], unnamed)
    assert backend.create_descriptor_with_endpoint(bufs[0], unnamed) is not None
    assert demo_buffer_backend.stats()['released_skipped'] == 2
    assert backend.peer_ledgers()[ep.gid_hex]['in_flight'] == 3
    del held


def test_slow_peer_keeps_getting_descriptors(backend):
    """Being slow is no reason for CPU bytes: a peer that took nothing for a while still gets
    descriptors (the "not taking for 2 s gets CPU bytes" rule is gone)."""
    demo_buffer_backend.configure(max_slots=16, max_inflight_per_peer=4, reclaim_timeout=3600)
    # its history unknown: past its share its oldest are given up (a known one would get CPU
    # bytes past its share, see test_share_caps_what_one_peer_pins_the_others_keep_zero_copy)
    ep = _discovered(backend, b'\x51' * 16)
    first = DemoBuffer.allocate(100)
    assert backend.create_descriptor_with_endpoint(first, ep) is not None
    time.sleep(0.3)
    bufs = [DemoBuffer.allocate(100) for _ in range(6)]
    descs = [backend.create_descriptor_with_endpoint(b, ep) for b in bufs]
    assert all(d is not None for d in descs)
    assert bytes(memoryview(backend.from_descriptor_with_endpoint(descs[-1], ep))) == \
        bytes(memoryview(bufs[-1]))
    stats = demo_buffer_backend.stats()
    assert stats['descriptors_declined'] == 0 and stats['released_share'] == 3, stats


def test_dead_or_foreign_peer_gets_nothing_or_cpu_and_pins_nothing(backend):
    """A peer whose listener is gone: EndpointGone (nothing sent). One whose listener is not
    the process its token names, or not of our uid: CPU bytes (None)."""
    domain = backend.get_backend_metadata().rpartition('.')[0]
    dead = _discovered(backend, b'\x61' * 16,
                       metadata=f'{domain}.{os.getpid() + 1}_00000000000000aa')
    with pytest.raises(EndpointGone):
        backend.create_descriptor_with_endpoint(DemoBuffer.allocate(10), dead)
    # a listener under a token that names another pid (a squatter of our uid), and one of
    # another uid under a token naming its own pid
    script = ('import os, socket, sys, time\n'
              'uid = int(sys.argv[2])\n'
              'if uid: os.setuid(uid)\n'
              'token = sys.argv[1] or f"{os.getpid()}_00000000000000cc"\n'
              's = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)\n'
              's.bind("\\0rbpy_demo/" + token); s.listen(8)\n'
              'print(token, flush=True); time.sleep(60)\n')
    import subprocess
    import sys
    squatter_token = f'{os.getpid() + 2}_00000000000000bb'
    procs = [subprocess.Popen([sys.executable, '-c', script, squatter_token, '0'],
                              stdout=subprocess.PIPE, text=True)]
    if os.geteuid() == 0:
        procs.append(subprocess.Popen([sys.executable, '-c', script, '', '65534'],
                                      stdout=subprocess.PIPE, text=True))
    try:
        for i, proc in enumerate(procs):
            token = proc.stdout.readline().strip()
            liar = _discovered(backend, bytes([0x62 + i]) * 16, metadata=f'{domain}.{token}')
            assert backend.create_descriptor_with_endpoint(DemoBuffer.allocate(10), liar) \
                is None
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
            proc.stdout.close()
    stats = demo_buffer_backend.stats()
    assert stats['cpu_foreign_peer'] == len(procs) and stats['handovers_sent'] == 0, stats
    assert stats['peers_gone'] == 1


def test_take_waits_a_bounded_time_for_a_held_lock(backend):
    """A process of our user that keeps a segment's hold byte locked exclusively (through its
    own description of the memfd) delays a take by a bounded time; the take is refused."""
    ep = _endpoint()
    buf = DemoBuffer.from_cpu(b'q' * 4096)
    desc = backend.create_descriptor_with_endpoint(buf, ep)
    own = lifecycle.get_pool().slots.by_id[buf.segment[1]].segment.fd
    fd = os.open(f'/proc/self/fd/{own}', os.O_RDWR)  # another description
    try:
        assert memory.try_lock(fd, exclusive=True)
        started = time.monotonic()
        with pytest.raises(ValueError, match='stale'):
            backend.from_descriptor_with_endpoint(desc, ep)
        waited = time.monotonic() - started
        assert waited < 1.0, waited  # generous: a loaded machine; the bound is about 0.1 s
        memory.unlock(fd)
        assert bytes(memoryview(backend.from_descriptor_with_endpoint(desc, ep))) == b'q' * 4096
    finally:
        os.close(fd)


def test_pool_exhausted_warning_names_the_cause(backend, monkeypatch):
    messages = []
    monkeypatch.setattr(diagnostics.logger, 'warning', lambda msg, **kw: messages.append(msg))
    demo_buffer_backend.configure(max_pool_bytes=1 << 16, max_slots=2)
    assert not DemoBuffer.allocate(1 << 20).in_shm
    assert 'larger than max_pool_bytes' in messages[-1]
    held = [DemoBuffer.allocate(100) for _ in range(2)]
    assert not DemoBuffer.allocate(100).in_shm
    assert '2 pinned by buffers this process still holds' in messages[-1]

    def enospc(capacity):
        raise OSError(errno.ENOSPC, 'No space left on device')
    monkeypatch.setattr(memory, 'Segment', enospc)
    demo_buffer_backend.configure(max_slots=4)
    assert not DemoBuffer.allocate(100).in_shm
    assert 'ENOSPC' in messages[-1]
    stats = demo_buffer_backend.stats()
    assert (stats['fallbacks_too_large'], stats['fallbacks_held'], stats['fallbacks_enospc']) \
        == (1, 1, 1), stats
    del held


def test_renew_waits_until_subscribers_are_done_then_gives_a_new_frame_in_the_same_memory(
        backend):
    """A camera that keeps its buffers: renew() returns once every descriptor of the published
    frame was taken and every view of it dropped; the same memory is then a new generation,
    and the old descriptor is refused as stale."""
    ep = _endpoint()  # this process's own endpoint (adopt_own): descriptors and views are real
    buf = DemoBuffer.allocate(1 << 16)
    segment, generation = buf.segment, buf.generation
    numpy.asarray(buf)[:] = 1
    first = backend.create_descriptor_with_endpoint(buf, ep)
    assert not buf.renew(timeout=0.05)  # sent, not taken yet
    got = backend.from_descriptor_with_endpoint(first, ep)
    assert not buf.renew(timeout=0.05)  # taken, but a view of it is held
    assert numpy.asarray(got)[0] == 1
    del got
    gc.collect()
    assert buf.renew(timeout=5.0)
    assert (buf.segment, buf.generation) == (segment, generation + 1)
    with pytest.raises(ValueError, match='stale'):
        backend.from_descriptor_with_endpoint(first, ep)
    numpy.asarray(buf)[:] = 2  # the new frame, in the same memory
    again = backend.from_descriptor_with_endpoint(
        backend.create_descriptor_with_endpoint(buf, ep), ep)
    assert numpy.asarray(again)[0] == 2 and again.segment == segment
    assert not again.renew()  # a received buffer is not the subscriber's to renew
    assert not DemoBuffer(bytearray(4)).renew()  # private memory: nothing to wait for


def test_wait_released_says_when_subscribers_are_done_and_leaves_the_frame_as_it_is(backend):
    """A publisher that only wants to know (pyzmq's MessageTracker): wait_released() is False
    while a descriptor is in flight or a view is held, True once both are gone, and the
    buffer stays the same frame (no new generation: its descriptor still opens)."""
    ep = _endpoint()
    buf = DemoBuffer.allocate(1 << 16)
    generation = buf.generation
    assert buf.released  # never described: nobody to wait for
    numpy.asarray(buf)[:] = 3
    first = backend.create_descriptor_with_endpoint(buf, ep)
    assert not buf.released and not buf.wait_released(timeout=0.05)  # in flight
    got = backend.from_descriptor_with_endpoint(first, ep)
    assert not buf.wait_released(timeout=0.05)  # taken, a view of it held
    del got
    gc.collect()
    start = time.monotonic()
    assert buf.wait_released(timeout=5.0) and buf.released
    assert time.monotonic() - start < 5.0
    assert buf.generation == generation  # not renewed
    again = backend.from_descriptor_with_endpoint(
        backend.create_descriptor_with_endpoint(buf, ep), ep)
    assert numpy.asarray(again)[0] == 3 and not buf.released
    assert not again.wait_released(0) and not again.released  # received: not ours to track
    assert DemoBuffer(bytearray(4)).released  # private memory is never shared
    with pytest.raises(ValueError, match='timeout'):
        buf.wait_released(timeout=-1)
