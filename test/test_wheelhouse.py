"""``./dev wheelhouse`` (docs/development.md, "Installing on a machine without internet"): the
wheels of everything the package and its tests need, for a target Python, one version each,
installable with pip offline. Made here for this machine's own Python (what pip can check)."""
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_wheelhouse_installs_offline(tmp_path):
    version = f'{sys.version_info.major}.{sys.version_info.minor}'
    out = tmp_path / 'wheelhouse'
    made = subprocess.run(
        [str(ROOT / 'dev'), 'wheelhouse', '--python-version', version, '--out', str(out),
         '--skip-present', 'numpy,setuptools,pytest,pytest-xdist,hypothesis,matplotlib,wheel'],
        capture_output=True, text=True, timeout=600)
    if made.returncode != 0 and 'No matching distribution' in made.stderr + made.stdout:
        pytest.skip(f'no wheels for CPython {version} here: {made.stderr[-500:]}')
    assert made.returncode == 0, made.stderr[-3000:]
    wheels = sorted(out.glob('*.whl'))
    names = [w.name.split('-')[0].lower().replace('_', '-') for w in wheels]
    assert len(names) == len(set(names)), 'two versions of one package stop pip'
    assert not [n for n in names if 'ament-cmake' in n or n in ('numpy', 'pytest', 'setuptools')]
    assert {'ros-rclpy', 'ros-fastrtps', 'ros-sensor-msgs', 'mcap', 'empy'} <= set(names)
    assert 'python3 -m pip install --no-index --no-deps' in (out / 'INSTALL.txt').read_text()
    # the documented install, offline, of rclpy's wheel and the message package the demo uses
    # (the rest installs the same way; the GPU machine ran the whole of INSTALL.txt)
    target = tmp_path / 'site'
    chosen = [w for w in wheels if w.name.startswith(('ros_rclpy-', 'ros_sensor_msgs-'))]
    assert len(chosen) == 2, [w.name for w in wheels]
    installed = subprocess.run(
        [sys.executable, '-m', 'pip', 'install', '--no-index', '--no-deps', '--no-compile',
         '--target', str(target), *map(str, chosen)], capture_output=True, text=True,
        timeout=600)
    assert installed.returncode == 0, installed.stderr[-3000:]
    assert (target / 'rclpy').is_dir() and (target / 'sensor_msgs').is_dir()
    assert sysconfig.get_platform().startswith('linux')


def test_the_gpu_check_script_parses_and_runs_only_what_exists():
    """tools/gpu_check.sh runs on a GPU machine, never here: it cannot drift unseen. It parses,
    and every test file, test and module it runs exists."""
    import importlib.util
    import re
    script = ROOT / 'tools' / 'gpu_check.sh'
    parsed = subprocess.run(['bash', '-n', str(script)], capture_output=True, text=True)
    assert parsed.returncode == 0, parsed.stderr
    text = script.read_text()
    files = re.findall(r'(test/\w+\.py)', text)
    assert 'test/test_cuda_gpu.py' in files
    assert not [f for f in files if not (ROOT / f).exists()]
    for file, name in re.findall(r'(test/\w+\.py)::(\w+)', text):
        assert f'def {name}(' in (ROOT / file).read_text(), (file, name)
    modules = re.findall(r'-m (launch_free_demos\.[\w.]+)', text)
    assert 'launch_free_demos.bench.cuda' in modules
    assert not [m for m in modules if importlib.util.find_spec(m) is None]
