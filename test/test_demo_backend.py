"""Tests of the ``demo`` shared-memory backend, in one process and across real processes.

Other processes are test/demo_backend_peer.py, driven over JSON lines; every one is reaped. Only
segments of the processes of this test are looked at in /dev/shm (other test runs may share it).
"""
import array
import errno
import gc
import os
import random
import resource
import threading
import time

import numpy
import pytest

import rosidl_buffer_py
from rosidl_buffer_py import Buffer, EndpointInfo, EndpointKind, MAX_DESCRIPTOR_SIZE

import demo_buffer_backend
from demo_backend_peer import Peer
from demo_buffer_backend import DemoBackend, DemoBuffer, descriptor, pool, presence, shm

PEER_GID = bytes(range(16))  # what demo_backend_peer.py calls its peer


def _endpoint(gid=b'\x11' * 16, kind=EndpointKind.SUBSCRIPTION):
    return EndpointInfo(gid, '/demo_backend_test', kind)


def _segments_of(pid):
    prefix = f'{shm.PREFIX}{pid}_'
    return {n for n in os.listdir(shm.SHM_DIR) if n.startswith(prefix)}


@pytest.fixture
def fresh():
    """A fresh process-wide pool with default limits; everything removed afterwards."""
    saved = dict(pool._limits.as_dict())
    demo_buffer_backend.shutdown()
    yield
    gc.collect()
    demo_buffer_backend.shutdown()
    demo_buffer_backend.configure(**saved)
    assert not _segments_of(os.getpid())


@pytest.fixture
def backend(fresh):
    """A DemoBackend that knows PEER_GID (and the in-process endpoint) as compatible peers."""
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
        metadata (its presence token: the process whose takes count for that endpoint)."""
        peer = Peer()
        started.append(peer)
        if backend is not None:
            assert backend.on_discovering_endpoint(
                _endpoint(PEER_GID), [], {'demo': peer.metadata}) == (True, [])
        return peer
    yield start
    for peer in started:
        peer.reap()
    if started:  # presence files of peers killed above (a normal exit removes its own)
        demo_buffer_backend.scavenge()
        for peer in started:
            assert not _presence_of(peer.pid)


def _presence_of(pid):
    prefix = f'{presence.PREFIX}{pid}_'
    return {n for n in os.listdir(shm.SHM_DIR) if n.startswith(prefix)}


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
    assert buf.in_shm and buf.segment_name.startswith('rbpy_demo_')
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
    # the bytes are the segment's: read them through the file itself
    with open(os.path.join(shm.SHM_DIR, buf.segment_name), 'rb') as f:
        f.seek(shm.HEADER_SIZE)
        assert f.read(4) == bytes([9, 7, 7, 7])


def test_segments_are_mode_0600_and_small_descriptors(backend):
    buf = DemoBuffer.from_cpu(b'x' * 5000)
    st = os.stat(os.path.join(shm.SHM_DIR, buf.segment_name))
    assert st.st_mode & 0o777 == 0o600
    desc = backend.create_descriptor_with_endpoint(buf, _endpoint())
    assert isinstance(desc, bytes) and len(desc) < 128 < MAX_DESCRIPTOR_SIZE


# --- descriptors ---------------------------------------------------------------------------------

def test_descriptor_round_trip_in_process_is_zero_copy_and_read_only(backend):
    ep = _endpoint()
    buf = DemoBuffer.allocate(4096 * 3 + 5)
    numpy.asarray(buf)[:] = numpy.arange(len(buf)) % 251
    desc = backend.create_descriptor_with_endpoint(buf, ep)
    got = backend.from_descriptor_with_endpoint(desc, ep)
    assert isinstance(got, DemoBuffer) and got.readonly and got.in_shm
    assert got.segment_name == buf.segment_name and got.generation == buf.generation
    assert bytes(memoryview(got)) == bytes(memoryview(buf))
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
    # the same shm domain, another process's presence token
    assert peer.metadata.rpartition('.')[0] == ours.rpartition('.')[0]
    assert _token(peer.metadata) != _token(ours)
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
    assert peer('stats')['mappings_opened'] == 1
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
    held_segment = first.segment_name
    del first
    for batch in range(10):
        descs, shas = [], []
        for i in range(10):
            frame = DemoBuffer.allocate(n)
            numpy.asarray(frame)[:] = (batch * 10 + i + 2) % 256
            assert frame.in_shm
            assert frame.segment_name != held_segment  # never reused while held
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
    assert not fallback.in_shm and fallback.segment_name is None
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
    name = buf.segment_name
    assert peer('take', desc=backend.create_descriptor_with_endpoint(
        buf, _endpoint(PEER_GID)).hex(), key='h')['ok']
    del buf
    assert not DemoBuffer.allocate(3000).in_shm  # held by the peer
    peer.kill9()
    reused = DemoBuffer.allocate(3000)
    assert reused.in_shm and reused.segment_name == name and reused.generation == 2


def test_killed_publisher_segments_are_removed_by_the_next_user(fresh, peers):
    publisher = peers()
    names = {publisher('publish', n=n, fill=3, keep=str(n))['name'] for n in (10, 5000, 70000)}
    assert names == _segments_of(publisher.pid) and len(names) == 3
    publisher.kill9()
    # The next process that uses the backend scavenges on start (unless the housekeeping of
    # another user of the backend on this machine was quicker).
    peers().exit()
    assert not _segments_of(publisher.pid)


def test_killed_publisher_segment_is_removed_while_mapped_views_stay_valid(backend, peers):
    publisher, reader = peers(), peers()
    reply = publisher('publish', n=4096, fill=5, keep='p')
    assert reader('take', desc=reply['desc'], key='r')['ok']
    sha = reader('sha', key='r')['sha']
    publisher.kill9()
    assert reader('sha', key='r')['sha'] == sha  # the view outlives its publisher
    # The reader's housekeeping thread (or its exit, or any other user's) removes the file;
    # unlinking does not unmap, so the reader's view stays valid.
    deadline = time.monotonic() + 10.0
    while _segments_of(publisher.pid):
        assert time.monotonic() < deadline, 'dead publisher segment not reclaimed in 10 s'
        time.sleep(0.05)
    assert reader('sha', key='r')['sha'] == sha
    reader.exit()
    assert not _segments_of(publisher.pid)


def test_normal_exit_removes_everything_it_created(fresh, peers):
    peer = peers()
    for n in (10, 100_000):
        peer('publish', n=n, fill=1, keep=str(n))
    assert len(_segments_of(peer.pid)) == 2
    peer.exit()
    assert not _segments_of(peer.pid)


def test_shutdown_removes_our_segments_and_fork_child_leaves_them(fresh):
    buf = DemoBuffer.from_cpu(b'f' * 100)
    name = buf.segment_name
    pid = os.fork()
    if pid == 0:  # the child inherits the pool but must never remove the parent's segments
        try:
            demo_buffer_backend.shutdown()
        finally:
            os._exit(0)
    assert os.waitpid(pid, 0)[1] == 0
    assert name in _segments_of(os.getpid())
    demo_buffer_backend.shutdown()
    assert not _segments_of(os.getpid())
    assert bytes(memoryview(buf)) == b'f' * 100  # a live Buffer keeps its mapping


# --- malformed descriptors -----------------------------------------------------------------------

def _forge(good, **changes):
    d = descriptor.unpack(good)._replace(**changes)
    return descriptor.pack(d)


def _with_raw_name(good, raw_name):
    head = 36  # the fixed part of a descriptor
    return good[:5] + bytes([len(raw_name)]) + good[6:head] + raw_name


def test_malformed_descriptors_raise_value_error(backend):
    ep = _endpoint()
    buf = DemoBuffer.from_cpu(b'm' * 6000)
    good = backend.create_descriptor_with_endpoint(buf, ep)
    d = descriptor.unpack(good)
    pid = os.getpid()
    bad = {
        'not bytes': 12345,
        'empty': b'',
        'bad magic': b'XXXX' + good[4:],
        'bad version': good[:4] + b'\x09' + good[5:],
        'trailing byte': good + b'\x00',
        'bad name chars': _forge(good, name=f'rbpy_demo_{pid}_abcdefgh-1234567'),
        'slash': _forge(good, name=f'rbpy_demo_{pid}_/etc/passwd'),
        'dot dot': _forge(good, name=f'rbpy_demo_{pid}_../../../etc/x'),
        'absolute': _forge(good, name='/dev/shm/' + d.name),
        'other prefix': _forge(good, name='lttng-ust-wait-6'),
        'non ascii': _with_raw_name(good, 'rbpy_demo_é'.encode()),
        'nul in name': _with_raw_name(good, good[36:-1] + b'\0'),
        'owner mismatch': _forge(good, owner=d.owner + 1),
        'missing segment': _forge(good, name=f'rbpy_demo_{pid}_0123456789abcdef'),
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
    # planted copies of the real segment (valid header): not created by the backend
    with open(shm.path_of(d.name), 'rb') as f:
        image = f.read()
    planted = []
    for label, mode in (('planted 0644', 0o644), ('planted 0666', 0o666), ('planted link', None),
                        ('planted 0600 other owner', 0o600)):
        name = f'rbpy_demo_{pid}_{os.urandom(8).hex()}'
        planted.append(shm.path_of(name))
        if mode is None:
            os.symlink(shm.path_of(d.name), shm.path_of(name))
        else:
            content = bytearray(image)
            if 'other owner' in label:
                content[12:16] = (pid + 1).to_bytes(4, 'little')  # HEADER owner_pid
            fd = os.open(shm.path_of(name), os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
            os.write(fd, bytes(content))
            os.fchmod(fd, mode)
            os.close(fd)
        bad[label] = _forge(good, name=name)
    rng = random.Random(1234)
    for i in range(200):
        bad[f'random {i}'] = bytes(rng.randrange(256) for _ in range(rng.randrange(120)))
    for i in range(200):  # random corruptions of the valid descriptor
        corrupted = bytearray(good)
        corrupted[rng.randrange(len(good))] ^= 1 << rng.randrange(8)
        bad[f'bit flip {i}'] = bytes(corrupted)
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
    for path in planted:
        os.unlink(path)
    stats = demo_buffer_backend.stats()
    assert stats['rejected'] == rejected > 300
    assert stats['untrusted_segments'] == 3  # (the symlink is refused by O_NOFOLLOW)
    assert stats['views_held'] == 0  # no hold leaked by a rejection
    ok = backend.from_descriptor_with_endpoint(good, ep)  # still fine afterwards
    assert bytes(memoryview(ok)) == b'm' * 6000


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


def test_foreign_files_with_our_name_pattern_are_rejected(backend):
    ep = _endpoint()
    name = f'rbpy_demo_{os.getpid()}_{"ab" * 8}'
    path = os.path.join(shm.SHM_DIR, name)
    good = descriptor.Descriptor(name, os.getpid(), 0, 10, 1)
    try:
        for content in (b'', b'\0' * (shm.HEADER_SIZE + 4096), b'junk' * 5000):
            with open(path, 'wb') as f:
                f.write(content)
            with pytest.raises(ValueError):
                backend.from_descriptor_with_endpoint(descriptor.pack(good), ep)
        os.unlink(path)
        os.symlink('/etc/hostname', path)
        with pytest.raises(ValueError):
            backend.from_descriptor_with_endpoint(descriptor.pack(good), ep)
    finally:
        if os.path.lexists(path):
            os.unlink(path)


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
    assert presence.parse_token(token) == token
    assert meta.split('.')[:5] == domain.split('.') and domain.startswith('shm1.')
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
    monkeypatch.setenv(pool.ENV_MAX_SLOTS, '7')
    monkeypatch.setenv(pool.ENV_MAX_POOL_BYTES, '12345678')
    monkeypatch.setenv(pool.ENV_RECLAIM_TIMEOUT, '1.5')
    limits = pool._Limits()
    assert (limits.max_slots, limits.max_pool_bytes, limits.reclaim_timeout) == (7, 12345678, 1.5)


# --- steady state --------------------------------------------------------------------------------

def test_steady_state_creates_and_maps_nothing(backend, monkeypatch):
    ep = _endpoint()
    n = 1 << 20
    calls = {'create': 0, 'open': 0, 'map': 0}

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
    files = _segments_of(os.getpid())
    for key, name in (('create', 'create'), ('open', 'open_existing'),
                      ('map', 'map_data_readonly')):
        monkeypatch.setattr(shm, name, counting(key, getattr(shm, name)))
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for i in range(200):
        frame(i)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
    assert calls == {'create': 0, 'open': 0, 'map': 0}
    assert _segments_of(os.getpid()) == files
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


def test_compatibility_ignores_the_token_but_not_the_domain(fresh):
    be = DemoBackend()
    meta = be.get_backend_metadata()
    domain, _, token = meta.rpartition('.')
    buf = DemoBuffer.from_cpu(b't' * 10)
    other = f'{os.getpid() + 1}_0123456789abcdef'  # another process of the same domain
    cases = {
        f'{domain}.{other}': (True, other),  # compatible, but gone: CPU bytes (below)
        meta: (True, token),
        domain: (True, None),  # a peer without a token: compatible, never taken for dead
        f'shm1.{"0" * 32}.1.2.3.{token}': (False, None),  # another boot
        domain.rsplit('.', 1)[0] + f'.{os.geteuid() + 1:x}.{token}': (False, None),  # other user
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
        alive = expected[1] is None or presence.alive(expected[1])  # `other` has no presence
        assert (be.create_descriptor_with_endpoint(buf, ep) is not None) == \
            (expected[0] and alive), metadata
    assert be.parse_metadata(None) == (False, None)


# --- dead recipients -----------------------------------------------------------------------------

def test_presence_file_is_private_removed_at_exit_and_scavenged_after_sigkill(fresh, peers):
    be = DemoBackend()
    token = _token(be.get_backend_metadata())
    path = presence.path_of(token)
    st = os.stat(path)
    assert st.st_mode & 0o777 == 0o600 and st.st_uid == os.geteuid()
    assert demo_buffer_backend.stats()['presence'] == token
    demo_buffer_backend.shutdown()
    assert not os.path.exists(path)
    assert _token(be.get_backend_metadata()) == token  # the advertised token stays valid
    assert os.path.exists(path)

    clean, killed = peers(), peers()
    for peer in (clean, killed):
        peer_path = presence.path_of(_token(peer.metadata))
        assert os.stat(peer_path).st_mode & 0o777 == 0o600
        assert presence.alive(_token(peer.metadata))
        assert _presence_of(peer.pid) == {os.path.basename(peer_path)}
    clean.exit()
    assert not _presence_of(clean.pid)
    assert not presence.alive(_token(clean.metadata))
    killed.kill9()
    assert _presence_of(killed.pid)  # nobody cleaned up yet
    assert demo_buffer_backend.scavenge() >= 1
    assert not _presence_of(killed.pid)
    assert os.path.exists(path)  # ours is alive: never scavenged


def test_killed_recipient_stops_pinning_slots_live_ones_keep_theirs(backend, peers):
    """Descriptors for a SIGKILLed subscriber stop pinning slots at once; a live subscriber's
    untaken descriptors and held views stay protected."""
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
        frames.append(dict(name=buf.segment_name, sha=_sha(buf),
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
    assert not DemoBuffer.allocate(n).in_shm  # (and again, from the liveness cache)

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
    assert {b.segment_name for b in reused} == {frames[1]['name'], frames[2]['name']}, stats
    assert all(b.in_shm and b.generation == 2 for b in reused)
    assert not DemoBuffer.allocate(n).in_shm
    assert stats['released_dead_recipients'] >= 2 and stats['reclaimed'] == 0, stats
    assert _token(victim.metadata) in stats['recipients_dead']
    assert stats['slots'] == 4
    # the survivor's bytes are intact and its late take is not stale
    assert survivor('sha', key='held')['sha'] == frames[0]['sha']
    late = survivor('take', desc=frames[3]['a'], key='late')
    assert late['ok'] and late['sha'] == frames[3]['sha'], late
    assert not _presence_of(victim.pid)  # found dead: its presence file is gone already
    survivor.exit()
    print(f'slots reusable {latency * 1000:.0f} ms after the SIGKILL')


def _open_fds_on(path):
    found = []
    for fd in os.listdir('/proc/self/fd'):
        try:
            if os.readlink(f'/proc/self/fd/{fd}') == path:
                found.append(int(fd))
        except OSError:
            pass
    return found


def test_presence_watch_keeps_a_live_peers_file_open_until_it_dies(backend, peers):
    """A re-test of a live peer is one fcntl on its presence file, kept open; once the peer
    dies (SIGKILL) the next test says so and the file is closed (and removed)."""
    peer = peers()
    token = _token(peer.metadata)
    path = presence.path_of(token)
    watch = presence.Watch()
    try:
        assert watch.alive(token) and watch.alive(token)
        assert len(_open_fds_on(path)) == 1
        watch.forget(token)
        assert _open_fds_on(path) == []
        assert watch.alive(token) and len(_open_fds_on(path)) == 1
        peer.kill9()
        assert not watch.alive(token)
        assert _open_fds_on(path) == [] and not _presence_of(peer.pid)
        assert not watch.alive(token)
    finally:
        watch.close()


def test_liveness_is_cached_not_tested_per_allocation(backend, peers):
    demo_buffer_backend.configure(max_slots=1, reclaim_timeout=3600)
    slow = peers()
    ep = _endpoint(b'\xc3' * 16)
    backend.on_discovering_endpoint(ep, [], {'demo': slow.metadata})
    buf = DemoBuffer.allocate(1000)
    backend.create_descriptor_with_endpoint(buf, ep)
    del buf
    before = demo_buffer_backend.stats()['liveness_checks']
    started = time.monotonic()
    for _ in range(300):
        assert not DemoBuffer.allocate(1000).in_shm  # a live, slow subscriber keeps its slot
    elapsed = time.monotonic() - started
    checks = demo_buffer_backend.stats()['liveness_checks'] - before
    assert checks <= elapsed / pool.LIVENESS_TTL + 2, (checks, elapsed)
    backend.on_removing_endpoint(ep)  # its endpoint went away but its process lives: kept
    assert not DemoBuffer.allocate(1000).in_shm
    slow.exit()  # now it is gone: the slot comes back within the cache's lifetime
    deadline = time.monotonic() + 10.0
    while not DemoBuffer.allocate(1000).in_shm:
        assert time.monotonic() < deadline
        time.sleep(0.01)


def test_takers_table_counts_per_process_and_overflows_safely(fresh):
    buf = DemoBuffer.allocate(10)
    header = buf._keepalive.slot.header
    for ident in (5, 7, 5, 5):
        shm.record_taker(header, ident)
    assert shm.taken_by(header, {5}) == 3 and shm.taken_by(header, {5, 7}) == 4
    assert shm.taken_by(header, {9}) == 0
    for ident in range(100, 100 + shm.MAX_TAKERS):
        shm.record_taker(header, ident)
    assert shm.taken_by(header, {5}) is None  # incomplete: the caller cannot tell
    shm.reset_takers(header)
    assert shm.taken_by(header, {5}) == 0
    assert bytes(header[shm.OFF_TAKERS:shm.OFF_TAKERS + 16 * shm.MAX_TAKERS]) == \
        bytes(16 * shm.MAX_TAKERS)


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
        backend.peer_ledgers()[ep.gid_hex], depth=0, in_flight=3)


def test_share_caps_what_one_peer_pins_the_others_keep_zero_copy(backend, peers):
    """A KEEP_ALL peer (another live process) that never takes keeps its share pinned and gets
    CPU bytes past it (what it was sent stays valid: nothing a stock subscriber would get is
    lost); a peer that takes gets every frame zero-copy and the pool never falls back."""
    demo_buffer_backend.configure(max_slots=4, max_inflight_per_peer=1, reclaim_timeout=3600)
    stuck = _discovered(backend, b'\x31' * 16, depth=0, metadata=peers().metadata)
    healthy = _discovered(backend, b'\x32' * 16, depth=0)
    to_stuck = []
    for i in range(30):
        buf = DemoBuffer.from_cpu(bytes([i]) * 3000)
        assert buf.in_shm, demo_buffer_backend.stats()
        to_stuck.append((buf.segment_name, buf.generation,
                         backend.create_descriptor_with_endpoint(buf, stuck)))
        desc = backend.create_descriptor_with_endpoint(buf, healthy)
        assert desc is not None
        del buf
        assert bytes(memoryview(backend.from_descriptor_with_endpoint(desc, healthy))) == \
            bytes([i]) * 3000
    stats = demo_buffer_backend.stats()
    assert stats['over_share'] == 29 and stats['fallbacks'] == 0, stats
    assert stats['reclaimed'] == 0, stats
    assert [d is not None for _, _, d in to_stuck] == [True] + [False] * 29
    # its share (the first frame) is still protected: never reclaimed
    name, generation, first = to_stuck[0]
    assert pool.get_state().slots[name].generation == generation


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


def test_peer_that_stops_taking_gets_cpu_and_probes_until_it_takes(backend, monkeypatch):
    monkeypatch.setattr(pool, 'IDLE_SECONDS', 0.2)
    monkeypatch.setattr(pool, 'PROBE_SECONDS', 0.3)
    demo_buffer_backend.configure(max_slots=16, max_inflight_per_peer=4, reclaim_timeout=3600)
    ep = _discovered(backend, b'\x51' * 16, depth=0)

    def ledger():
        return backend.peer_ledgers()[f'{ep.gid_hex}/{PUBLISHER_GID.hex()}']
    first = backend.create_descriptor_with_endpoint(DemoBuffer.allocate(100), ep)
    assert first is not None
    time.sleep(0.25)
    buf = DemoBuffer.allocate(100)
    probe = backend.create_descriptor_with_endpoint(buf, ep)  # now idle: the first probe
    assert probe is not None and ledger()['not_taking']
    got = [backend.create_descriptor_with_endpoint(buf, ep) for _ in range(5)]
    assert got == [None] * 5  # CPU bytes between probes
    view = backend.from_descriptor_with_endpoint(probe, ep)  # it takes again
    assert backend.create_descriptor_with_endpoint(DemoBuffer.allocate(100), ep) is not None
    assert not ledger()['not_taking']
    stats = demo_buffer_backend.stats()
    assert stats['peers_idle'] == 1 and stats['probes'] == 1 and stats['cpu_not_taking'] == 5
    del view


def test_dead_or_foreign_peer_gets_cpu_and_pins_nothing(backend, tmp_path):
    domain = backend.get_backend_metadata().rpartition('.')[0]
    dead = _discovered(backend, b'\x61' * 16,
                       metadata=f'{domain}.{os.getpid() + 1}_00000000000000aa')
    assert backend.create_descriptor_with_endpoint(DemoBuffer.allocate(10), dead) is None
    # a "presence file" that is a symlink to a file of ours (what another user cannot fake
    # better): not a live peer of our domain
    token = f'{os.getpid() + 2}_00000000000000bb'
    target = tmp_path / 'elsewhere'
    target.write_bytes(shm.PRESENCE_MAGIC)
    os.symlink(target, presence.path_of(token))
    try:
        liar = _discovered(backend, b'\x62' * 16, metadata=f'{domain}.{token}')
        assert not presence.alive(token)
        assert backend.create_descriptor_with_endpoint(DemoBuffer.allocate(10), liar) is None
    finally:
        os.unlink(presence.path_of(token))
    assert demo_buffer_backend.stats()['cpu_dead_peer'] == 2


def test_take_waits_a_bounded_time_for_a_held_mutex_byte(backend):
    """A process of our user that keeps a segment's mutex byte locked (stopped inside its
    take) delays a take by at most MUTEX_WAIT_SECONDS; the message is still delivered."""
    ep = _endpoint()
    buf = DemoBuffer.from_cpu(b'q' * 4096)
    desc = backend.create_descriptor_with_endpoint(buf, ep)
    fd = os.open(shm.path_of(buf.segment_name), os.O_RDWR)  # another open file description
    try:
        assert pool.locks.try_lock(fd, shm.MUTEX_BYTE, exclusive=True)
        started = time.monotonic()
        got = backend.from_descriptor_with_endpoint(desc, ep)
        waited = time.monotonic() - started
        assert bytes(memoryview(got)) == b'q' * 4096
        assert waited < 1.0, waited  # generous: a loaded machine; the bound is 20 ms
        assert demo_buffer_backend.stats()['take_unrecorded'] == 1
    finally:
        os.close(fd)
    del got


def test_pool_exhausted_warning_names_the_cause(backend, monkeypatch):
    messages = []
    monkeypatch.setattr(pool._logger, 'warning', lambda msg, **kw: messages.append(msg))
    demo_buffer_backend.configure(max_pool_bytes=1 << 16, max_slots=2)
    assert not DemoBuffer.allocate(1 << 20).in_shm
    assert 'larger than max_pool_bytes' in messages[-1]
    held = [DemoBuffer.allocate(100) for _ in range(2)]
    assert not DemoBuffer.allocate(100).in_shm
    assert '2 pinned by buffers this process still holds' in messages[-1]

    def enospc(capacity):
        raise OSError(errno.ENOSPC, 'No space left on device')
    monkeypatch.setattr(shm, 'create', enospc)
    demo_buffer_backend.configure(max_slots=4)
    assert not DemoBuffer.allocate(100).in_shm
    assert 'ENOSPC' in messages[-1]
    stats = demo_buffer_backend.stats()
    assert (stats['fallbacks_too_large'], stats['fallbacks_held'], stats['fallbacks_enospc']) \
        == (1, 1, 1), stats
    del held
