"""Backend discovery from entry points and acceptable_buffer_backends parsing.

Plugins here are real installed distributions (a dist-info directory with entry_points.txt on
PYTHONPATH), discovered by a fresh interpreter exactly as a pip-installed backend would be.
"""
import json
import os
import subprocess
import sys
import textwrap

import pytest

from rosidl_buffer_py import BufferBackend, registry

PLUGINS = {
    # module name: (entry point name, module source)
    'good_backend': ('good', '''
        from rosidl_buffer_py import BufferBackend, Buffer
        class GoodBackend(BufferBackend):
            def get_backend_type(self): return 'good'
            def get_backend_metadata(self): return 'meta1'
            def create_descriptor_with_endpoint(self, buffer, endpoint_info): return b'd'
            def from_descriptor_with_endpoint(self, descriptor, endpoint_info):
                return Buffer('good', bytes(descriptor))
        '''),
    'import_error_backend': ('importerr', 'import no_such_module_anywhere\n'),
    'raising_backend': ('raising', '''
        from rosidl_buffer_py.cpu_backend import CpuBackend
        class RaisingBackend(CpuBackend):
            def __init__(self): raise RuntimeError('no device found')
        '''),
    'wrong_type_backend': ('wrongtype', 'class WrongType:\n    pass\n'),
    'mismatch_backend': ('mismatch', '''
        from rosidl_buffer_py.cpu_backend import CpuBackend
        class Mismatch(CpuBackend):
            pass
        '''),
}
ENTRY_POINTS = {
    'good': 'good_backend:GoodBackend',
    'importerr': 'import_error_backend:Anything',
    'raising': 'raising_backend:RaisingBackend',
    'wrongtype': 'wrong_type_backend:WrongType',
    'mismatch': 'mismatch_backend:Mismatch',
    'Bad-Name': 'good_backend:GoodBackend',
    'cpu': 'good_backend:GoodBackend',
}


@pytest.fixture(scope='module')
def plugin_path(tmp_path_factory):
    root = tmp_path_factory.mktemp('plugins')
    for module, (_, source) in PLUGINS.items():
        (root / f'{module}.py').write_text(textwrap.dedent(source))
    dist = root / 'test_backends-1.0.dist-info'
    dist.mkdir()
    (dist / 'METADATA').write_text('Metadata-Version: 2.1\nName: test-backends\nVersion: 1.0\n')
    (dist / 'entry_points.txt').write_text(
        '[rosidl_buffer_py.backends]\n' +
        ''.join(f'{name} = {value}\n' for name, value in ENTRY_POINTS.items()))
    return str(root)


def run_with_plugins(plugin_path, code):
    env = dict(os.environ, PYTHONPATH=plugin_path + os.pathsep + os.environ.get('PYTHONPATH', ''))
    proc = subprocess.run([sys.executable, '-c', textwrap.dedent(code)], env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1]), proc.stderr


def test_installed_plugins_are_found_and_broken_ones_skipped_once(plugin_path):
    result, stderr = run_with_plugins(plugin_path, '''
        import json, rosidl_buffer_py as r
        first = r.get_installed_backends()
        second = r.get_installed_backends()
        good = first['good']
        print(json.dumps({'names': sorted(first), 'same': sorted(second) == sorted(first),
                          'meta': good.get_backend_metadata(),
                          'cpu_type': type(first['cpu']).__name__}))
        ''')
    assert 'good' in result['names'] and 'cpu' in result['names']
    for broken in ('importerr', 'raising', 'wrongtype', 'mismatch', 'Bad-Name'):
        assert broken not in result['names']
    assert result['same'] and result['meta'] == 'meta1'
    assert result['cpu_type'] == 'CpuBackend'  # the built-in cpu cannot be replaced
    # every broken plugin is reported exactly once, with its own error
    for name, expected in [('importerr', 'ModuleNotFoundError'), ('raising', 'no device found'),
                           ('wrongtype', 'not a BufferBackend'), ('mismatch', "returns 'cpu'"),
                           ('Bad-Name', 'must match'), ('cpu', 'already has that name')]:
        lines = [line for line in stderr.splitlines() if f"buffer backend '{name}'" in line]
        assert len(lines) == 1, (name, stderr)
        assert expected in lines[0], (name, lines[0])


def test_acceptable_backends_with_plugins_installed(plugin_path):
    result, stderr = run_with_plugins(plugin_path, '''
        import json, rosidl_buffer_py as r
        p = r.parse_acceptable_buffer_backends
        cases = [None, '', 'cpu', 'any', 'good', ' good , cpu ', 'good,nosuch', 'nosuch',
                 'nosuch,nosuch', ',,', 'ANY']
        print(json.dumps({repr(c): sorted(p(c)) for c in cases} |
                         {'installed': sorted(r.get_installed_backends())}))
        ''')
    installed = result['installed']
    assert result['None'] == result["''"] == result["'cpu'"] == ['cpu']
    assert result["'any'"] == installed
    assert result["'good'"] == result["' good , cpu '"] == ['cpu', 'good']
    assert result["'good,nosuch'"] == ['cpu', 'good']
    assert result["'nosuch'"] == result["'nosuch,nosuch'"] == result["',,'"] == ['cpu']
    assert result["'ANY'"] == ['cpu']  # names are case-sensitive; 'ANY' is an unknown name
    warnings = [line for line in stderr.splitlines() if "'nosuch'" in line]
    assert len(warnings) == 1, stderr
    assert 'not an installed buffer backend' in warnings[0]
    assert all(name in warnings[0] for name in installed)


def test_acceptable_backends_rejects_non_strings():
    with pytest.raises(TypeError, match="got list"):
        registry.parse_acceptable_buffer_backends(['cpu'])


def test_get_backend_names_the_installed_ones():
    assert registry.get_backend('cpu').get_backend_type() == 'cpu'
    with pytest.raises(KeyError, match="'nosuch' is not installed; installed: .*cpu"):
        registry.get_backend('nosuch')


def test_cpu_backend_has_no_descriptors():
    cpu = registry.get_backend('cpu')
    assert isinstance(cpu, BufferBackend)
    assert cpu.create_descriptor_with_endpoint(None, None) is None
    with pytest.raises(ValueError):
        cpu.from_descriptor_with_endpoint(b'', None)
