"""A third-party backend in its own pip package works with no change to rosidl_buffer_py.

test/example_backend/ is the package ``rbpy-example-backend`` (backend ``filestore``: payloads in
files of a shared directory, descriptors of about 50 bytes). It is pip-installed into a temporary
target directory that only the processes started here see (through PYTHONPATH), never into the
shared virtual environment. Then the real node executables prove, across processes, that the
backend is discovered, advertised in USER_DATA, negotiated per peer and used, with every frame's
checksum verified; and that every payload file is removed again.
"""
import json
import os
import shutil
import subprocess
import sys
import textwrap
from importlib import metadata
from pathlib import Path

import pytest

from harness.scenarios import SMALL
from launch_free_demos.runner import Run

SOURCE = Path(__file__).resolve().parent / 'example_backend'
DISTRIBUTION = 'rbpy-example-backend'
STORE_DIR_ENV = 'RBPY_EXAMPLE_STORE_DIR'


@pytest.fixture(scope='module')
def plugin_site(tmp_path_factory):
    """``pip install --no-build-isolation --no-deps --target`` of a copy of the package (pip
    builds in the source tree: the copy keeps build/ and egg-info out of the repository)."""
    root = tmp_path_factory.mktemp('third_party')
    source = root / 'src'
    shutil.copytree(SOURCE, source, ignore=shutil.ignore_patterns(
        'build', '*.egg-info', '__pycache__'))
    site = root / 'site'
    proc = subprocess.run(
        [sys.executable, '-m', 'pip', 'install', '--quiet', '--disable-pip-version-check',
         '--no-build-isolation', '--no-deps', '--no-index', '--target', str(site), str(source)],
        capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (site / 'rbpy_example_backend' / 'backend.py').is_file()
    yield site
    shutil.rmtree(root, ignore_errors=True)


@pytest.fixture
def store(tmp_path):
    directory = tmp_path / 'store'
    directory.mkdir()
    return directory


def _env(site, store_dir=None):
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(
        p for p in (str(site), os.environ.get('PYTHONPATH', '')) if p)
    if store_dir is not None:
        env[STORE_DIR_ENV] = str(store_dir)
    else:
        env.pop(STORE_DIR_ENV, None)
    return env


def _child(code, env):
    """Run ``code`` in a fresh interpreter; return (last stdout line as JSON, stderr)."""
    proc = subprocess.run([sys.executable, '-c', textwrap.dedent(code)], env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1]), proc.stderr


def test_the_shared_environment_does_not_see_the_plugin(plugin_site):
    with pytest.raises(metadata.PackageNotFoundError):
        metadata.distribution(DISTRIBUTION)
    assert 'filestore' not in {ep.name for ep in
                               metadata.entry_points(group='rosidl_buffer_py.backends')}


def test_installed_package_is_discovered_through_its_entry_point(plugin_site, store):
    code = '''
        import json
        from importlib import metadata
        import rosidl_buffer_py
        backends = rosidl_buffer_py.get_installed_backends()
        backend = backends.get('filestore')
        dist = metadata.distribution('rbpy-example-backend')
        print(json.dumps({
            'names': sorted(backends),
            'class': type(backend).__module__ + '.' + type(backend).__qualname__
                     if backend else None,
            'metadata': backend.get_backend_metadata() if backend else None,
            'entry_points': [(ep.group, ep.name, ep.value) for ep in dist.entry_points],
            'module_file': __import__('rbpy_example_backend').__file__,
        }))
    '''
    result, _ = _child(code, _env(plugin_site, store))
    assert {'cpu', 'demo', 'filestore'} <= set(result['names']), result
    assert result['class'] == 'rbpy_example_backend.backend.FileStoreBackend'
    assert result['metadata'] == os.path.realpath(store)
    assert result['entry_points'] == [
        ['rosidl_buffer_py.backends', 'filestore', 'rbpy_example_backend:FileStoreBackend']]
    assert result['module_file'].startswith(str(plugin_site))

    # Installed but not configured: the registry logs the reason once and skips it.
    result, stderr = _child('''
        import json, rosidl_buffer_py
        print(json.dumps(sorted(rosidl_buffer_py.get_installed_backends())))
    ''', _env(plugin_site, None))
    assert 'filestore' not in result and 'cpu' in result
    assert 'RBPY_EXAMPLE_STORE_DIR' in stderr and stderr.count("'filestore'") == 1, stderr

    # Without the target directory on the path nobody sees it.
    result, _ = _child('''
        import json, rosidl_buffer_py
        print(json.dumps(sorted(rosidl_buffer_py.get_installed_backends())))
    ''', dict(_env(plugin_site, store), PYTHONPATH=os.environ.get('PYTHONPATH', '')))
    assert 'filestore' not in result


def test_backend_contract_descriptors_validation_and_cleanup(plugin_site, store, tmp_path):
    other = tmp_path / 'other_store'
    other.mkdir()
    code = f'''
        import json, os, numpy
        from rosidl_buffer_py import get_backend
        from rosidl_buffer_py.backend import EndpointInfo, EndpointKind
        from rbpy_example_backend import FileStoreBackend
        be = get_backend('filestore')
        sub = EndpointInfo(b'\\x01' * 16, '/t', EndpointKind.SUBSCRIPTION)
        stranger = EndpointInfo(b'\\x02' * 16, '/t', EndpointKind.SUBSCRIPTION)
        pub = EndpointInfo(b'\\x03' * 16, '/t', EndpointKind.PUBLISHER)
        out = {{}}
        same = be.get_backend_metadata()
        elsewhere = FileStoreBackend({str(other)!r}).get_backend_metadata()
        out['same_dir'] = be.on_discovering_endpoint(sub, [], {{'filestore': same}})[0]
        out['other_dir_refused'] = not be.on_discovering_endpoint(
            stranger, [], {{'filestore': elsewhere}})[0]
        out['unadvertised_refused'] = not be.on_discovering_endpoint(
            stranger, [], {{'demo': 'x'}})[0]

        buf = be.allocate(1000)
        out['writable'] = not buf.readonly and len(buf) == 1000
        numpy.asarray(buf)[:] = numpy.arange(1000) % 251
        d = be.create_descriptor_with_endpoint(buf, sub)
        out['descriptor_len'] = len(d)
        out['stranger_gets_cpu'] = be.create_descriptor_with_endpoint(buf, stranger) is None
        got = be.from_descriptor_with_endpoint(d, pub)
        out['roundtrip'] = got.to_bytes() == buf.to_bytes()
        out['received_readonly'] = got.readonly and got.backend_type == 'filestore'
        out['republish_received_gets_cpu'] = be.create_descriptor_with_endpoint(got, sub) is None
        out['zero'] = be.from_descriptor_with_endpoint(
            be.create_descriptor_with_endpoint(be.allocate(0), sub), pub).to_bytes() == b''

        errors = []
        for bad in (b'', b'FSB1', d[:-1], b'XXXX' + d[4:], d[:16] + b'../../etc/passwd',
                    d[:4] + (1001).to_bytes(8, 'little') + d[12:],
                    d[:12] + bytes(4) + d[16:], d + b'x' * 100):
            try:
                be.from_descriptor_with_endpoint(bad, pub)
                errors.append('accepted')
            except ValueError as exc:
                errors.append('ValueError')
        out['bad'] = errors

        # Release: a descriptor is a link its receiver consumes (a second take is refused);
        # links a subscriber never took go when it leaves; a file goes with its last name.
        b = be.allocate(10)
        first = be.create_descriptor_with_endpoint(b, sub)
        untaken = be.create_descriptor_with_endpoint(b, sub)
        out['pending_before'] = be.pending_links()
        kept = be.from_descriptor_with_endpoint(first, pub)
        takes = []
        for desc in (first, untaken):
            try:
                be.from_descriptor_with_endpoint(desc, pub)
                takes.append('taken')
            except ValueError:
                takes.append('refused')
        out['second_takes'] = takes
        untaken_too = be.create_descriptor_with_endpoint(b, sub)
        be.on_removing_endpoint(sub)
        try:
            be.from_descriptor_with_endpoint(untaken_too, pub)
            out['after_leaving'] = 'taken'
        except ValueError:
            out['after_leaving'] = 'refused'
        del b
        out['kept_readable'] = kept.to_bytes() == bytes(10)
        out['pending_after'] = be.pending_links()
        out['files_now'] = len(os.listdir({str(store)!r}))
        print(json.dumps(out))
    '''
    env = _env(plugin_site, store)
    result, _ = _child(code, env)
    assert result.pop('bad') == ['ValueError'] * 8
    assert result.pop('second_takes') == ['refused', 'taken']
    assert result.pop('after_leaving') == 'refused'
    assert result.pop('pending_before') == 2 and result.pop('pending_after') == 0
    assert 0 < result.pop('descriptor_len') <= 80
    # only buf, still referenced: every link was taken or removed, b went with its Buffer
    assert result.pop('files_now') == 1
    assert all(result.values()), result
    assert os.listdir(store) == [], 'files left after the process exited'


def _pub_params(topic, count, **extra):
    params = dict(topic=topic, count=count, rate_hz=50.0, wait_for_subscribers=1,
                  wait_timeout_sec=60.0, linger_sec=10.0, **SMALL)
    params.update(extra)
    return params


def _sub_params(topic, count, **extra):
    return dict(topic=topic, expected_count=count, timeout_sec=60.0, **extra)


def test_end_to_end_across_processes_with_the_real_nodes(plugin_site, store, tmp_path,
                                                        monkeypatch):
    """image_publisher backend:=filestore (fill=allocate: frames written in place into the
    store files) to two image_subscriber processes accepting filestore: one sharing the store
    directory gets descriptors, one with another store directory is refused by the backend's
    on_discovering_endpoint and gets CPU bytes over its channel."""
    other = tmp_path / 'other_store'
    other.mkdir()
    count, topic = 30, '/third_party_image'
    monkeypatch.setenv('PYTHONPATH', _env(plugin_site)['PYTHONPATH'])
    monkeypatch.setenv(STORE_DIR_ENV, str(store))  # the runner passes os.environ on
    with Run() as run:
        run.start('sub', 'image_subscriber', **_sub_params(
            topic, count, acceptable_buffer_backends='filestore', expected_backend='filestore'))
        monkeypatch.setenv(STORE_DIR_ENV, str(other))
        run.start('sub_elsewhere', 'image_subscriber', **_sub_params(
            topic, count, acceptable_buffer_backends='filestore', expected_backend='cpu'))
        monkeypatch.setenv(STORE_DIR_ENV, str(store))
        run.start('pub', 'image_publisher', **_pub_params(
            topic, count, backend='filestore', fill='allocate', wait_for_subscribers=2,
            wait_for_buffer_peers=2))
        assert run.wait(timeout=180), run.diagnostics()
        reports = run.reports()
        pids = {node.process.pid for node in run.nodes.values()}
    sub, elsewhere, pub = reports['sub'], reports['sub_elsewhere'], reports['pub']
    assert sub and elsewhere and pub, run.diagnostics()
    store_meta, other_meta = os.path.realpath(store), os.path.realpath(other)

    # used: every frame arrived once as a filestore Buffer, checksum and counter verified
    assert sub['backends'] == {'filestore': count}, sub
    assert sub['distinct'] == sub['received'] == count, sub
    assert sub['checksum_failures'] == sub['duplicates'] == sub['gaps'] == 0, sub
    assert sub['wrong_backend'] == 0 and not sub['problems'], sub
    assert sub['statistics']['rejected'] == 0, sub['statistics']
    # the refused peer: the same frames, as CPU bytes
    assert elsewhere['backends'] == {'cpu': count}, elsewhere
    assert elsewhere['checksum_failures'] == elsewhere['wrong_backend'] == 0, elsewhere

    # discovered in each child and advertised in USER_DATA (what each side read of the other)
    # (a subscription's cpu entry carries its history, KEEP_LAST 10: see rosidl_buffer_py.qos)
    assert sub['statistics']['advertised_backends'] == {'cpu': 'keep_last.10',
                                                        'filestore': store_meta}
    assert elsewhere['statistics']['advertised_backends'] == {'cpu': 'keep_last.10',
                                                              'filestore': other_meta}
    assert pub['statistics']['advertised_backends']['filestore'] == store_meta
    [peer_seen_by_sub] = sub['statistics']['peers']
    assert peer_seen_by_sub['advertised_backends']['filestore'] == store_meta
    assert peer_seen_by_sub['backend_in_use'] == 'filestore'
    assert peer_seen_by_sub['received_as_descriptor'] == count

    # negotiated per peer by the backend's on_discovering_endpoint: both subscriptions are
    # served on their own channel; only the one sharing the store directory gets descriptors
    [peer_seen_elsewhere] = elsewhere['statistics']['peers']
    assert peer_seen_elsewhere['advertised_backends']['filestore'] == store_meta
    assert peer_seen_elsewhere['backend_in_use'] == 'cpu'
    assert peer_seen_elsewhere['received_as_cpu'] == count
    assert peer_seen_elsewhere['received_as_descriptor'] == 0
    for report in (sub, elsewhere):
        assert report['statistics']['from_channels'] == count, report['statistics']
    assert pub['published'] == count and pub['statistics']['sent_on_main_topic'] == 0, pub
    assert pub['statistics']['peers_added'] == 2, pub['statistics']

    # cleaned up: the publisher unlinked every payload file; nothing of our nodes in /dev/shm
    assert os.listdir(store) == [] and os.listdir(other) == []
    assert not [name for name in os.listdir('/dev/shm')
                if any(f'_{pid}_' in name for pid in pids)]
