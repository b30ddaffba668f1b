"""`pip install <checkout>` into a fresh venv with nothing installed first (as a user of the
package does in their own venv), and the one error a build without ROS gets.

Slow (about a minute and a half: pip installs the ROS wheels twice, for the isolated build and
for the venv, from its cache, and compiles the extension); it reuses pip's cache.
"""
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from test_packaging import requirement_lines

ROOT = Path(__file__).resolve().parent.parent
#: Not copied with the checkout: environments, build products and caches.
IGNORE = shutil.ignore_patterns('.venv', 'build', 'install', 'log', '.git', '*.so',
                                '*.egg-info', '__pycache__', '.pytest_cache', '.hypothesis')


def _base_python() -> str:
    """An interpreter outside any venv (``python3 -m venv`` from inside one would inherit
    nothing, but pip's own packages must come from the new venv)."""
    return getattr(sys, '_base_executable', None) or shutil.which('python3')


def _checkout(tmp_path: Path) -> Path:
    copy = tmp_path / 'checkout'
    shutil.copytree(ROOT, copy, ignore=IGNORE)
    return copy


def _own_env() -> dict:
    """This environment without PYTHONPATH: under colcon test it holds the install space and
    the source tree (test/conftest.py), which the fresh venv would import instead of its own."""
    return {name: value for name, value in os.environ.items() if name != 'PYTHONPATH'}


def _venv(path: Path) -> Path:
    subprocess.run([_base_python(), '-m', 'venv', str(path)], check=True, timeout=120)
    return path / 'bin'


def test_build_requirements_are_requirements_build_txt():
    """pyproject.toml's [build-system] requires and requirements-build.txt list the same."""
    declared = tomllib.loads((ROOT / 'pyproject.toml').read_text())['build-system']['requires']
    assert declared == [req for req, _ in requirement_lines('requirements-build.txt')]


def test_pip_install_checkout_into_a_fresh_venv(tmp_path):
    bin_dir = _venv(tmp_path / 'v')
    install = subprocess.run([str(bin_dir / 'pip'), 'install', '--disable-pip-version-check',
                              str(_checkout(tmp_path))],
                             capture_output=True, text=True, timeout=600, env=_own_env())
    assert install.returncode == 0, install.stdout[-3000:] + install.stderr[-3000:]
    check = subprocess.run(
        [str(bin_dir / 'python'), '-c',
         'import rosidl_buffer_py, rclpy\n'
         'from rosidl_buffer_py import _dds\n'
         'from sensor_msgs.msg import Image\n'
         'assert _dds.abi_status().ok, _dds.abi_status().reason\n'
         'rclpy.init()\n'
         'node = rclpy.create_node("installed")\n'
         'rosidl_buffer_py.create_publisher(node, Image, "image", 10)\n'
         'print(rosidl_buffer_py.__version__)\n'
         'node.destroy_node()\n'
         'rclpy.shutdown()\n'],
        capture_output=True, text=True, timeout=120, cwd=tmp_path, env=_own_env())
    assert check.returncode == 0, check.stderr[-3000:]
    assert check.stdout.strip() == '0.1.0'
    package = next((tmp_path / 'v' / 'lib').glob('python3*/site-packages/rosidl_buffer_py'))
    assert (package / 'py.typed').is_file()
    # the wheel ships the library with its nodes and tools, and the backends; never the demos,
    # the benchmarks and the process runner (launch_free_demos, run from the checkout) nor the
    # test harness
    site = package.parent
    for shipped in ('rosidl_buffer_py/tools/record.py', 'rosidl_buffer_py/report.py',
                    'rosidl_buffer_py/nodes/image_publisher.py', 'demo_buffer_backend/pool.py',
                    'cuda_buffer_backend/backend.py'):
        assert (site / shipped).is_file(), shipped
    for left_out in ('launch_free_demos', 'harness', 'test'):
        assert not (site / left_out).exists(), left_out
    [record] = site.glob('rosidl_buffer_py-*.dist-info/RECORD')
    installed = {line.split('/', 1)[0] for line in record.read_text().splitlines()}
    assert not installed & {'launch_free_demos', 'harness', 'test'}, sorted(installed)
    # the executables are on the venv's PATH
    info = subprocess.run([str(bin_dir / 'buffer_bag_info'), '--help'], capture_output=True,
                          text=True, timeout=60, env=_own_env())
    assert info.returncode == 0 and 'usage: buffer_bag_info' in info.stdout, info.stderr


def test_build_without_ros_gets_one_error_naming_what_to_install(tmp_path):
    """Without build isolation and without ROS, the build stops at once with what to do."""
    bin_dir = _venv(tmp_path / 'v')
    if subprocess.run([str(bin_dir / 'python'), '-c', 'import setuptools'],
                      capture_output=True).returncode != 0:
        pytest.skip('this Python makes venvs without setuptools (3.12+); the isolated build '
                    'is the supported path there')
    result = subprocess.run([str(bin_dir / 'pip'), 'install', '--disable-pip-version-check',
                             '--no-build-isolation', '--no-deps', str(_checkout(tmp_path))],
                            capture_output=True, text=True, timeout=300,
                            env={'PATH': '/usr/bin:/bin', 'HOME': str(tmp_path)})
    assert result.returncode != 0
    output = result.stdout + result.stderr
    assert 'pip install "ros-jazzy-rclpy[fastrtps]"' in output, output[-3000:]
    assert 'source /opt/ros/jazzy/setup.bash' in output
