"""The package imports after numpy, torch or CuPy, in a fresh interpreter (what a perception
node does). It once crashed there: src/native/exports.map says why."""
import subprocess
import sys

import pytest


def _have(module: str) -> bool:
    return subprocess.run([sys.executable, '-c', f'import {module}'],
                          capture_output=True).returncode == 0


@pytest.mark.parametrize('first', ['numpy', 'numpy.linalg', 'torch', 'cupy'])
def test_the_package_imports_after_a_numeric_library(first):
    if first in ('torch', 'cupy') and not _have(first):
        pytest.skip(f'{first} is not installed here')
    code = (f'import {first}; import rosidl_buffer_py; import demo_buffer_backend; '
            'import cuda_buffer_backend; from rosidl_buffer_py._native import BufferBase; '
            'print("ok")')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=120, cwd='/')
    assert result.returncode == 0 and 'ok' in result.stdout, \
        f'exit {result.returncode}: {result.stderr[-2000:]}'


def test_the_native_extension_exports_its_init_function_alone():
    """Its copies of Fast DDS's inline symbols must never win the lookup (exports.map)."""
    from rosidl_buffer_py import _native
    result = subprocess.run(['nm', '-D', '--defined-only', _native.__file__],
                            capture_output=True, text=True)
    if result.returncode != 0:
        pytest.skip(f'nm is not usable here: {result.stderr.strip()}')
    names = [line.split()[-1] for line in result.stdout.splitlines() if line.strip()]
    assert names == ['PyInit__native'], names[:20]
