"""The repository builds and tests as a ROS package with colcon, as a ROS user would run it.

A copy of the working tree (tracked and untracked-but-not-ignored files: no .venv, build or
egg-info) goes to ``<tmp>/src/rosidl_buffer_py``; ``colcon build`` compiles the native extension
into ``install/``, ``colcon test`` runs a few test files against that install space (the rest
of the suite runs directly in ``./dev test``) and ``colcon test-result`` must report no failure
or error. Everything happens under the test's tmp_path, which is removed at the end.

The underlay is the venv the tests run in (``./dev``'s: exactly ``requirements.txt``,
``requirements-build.txt`` and ``requirements-test.txt``, what package.xml declares, as
test_packaging.py checks), declared as colcon users declare one: in ``AMENT_PREFIX_PATH``
(setup.py looks for ROS headers there; colcon's own sitecustomize hides the venv's
``sys.prefix`` from setup.py during the build). The inner run imports the package colcon built,
not the one ``./dev`` installed (checked below). A fresh venv holding only the requirement files
is test_install.py's.

The inner run sets ``RBPY_INSIDE_COLCON_TEST`` to the install prefix: the build-and-test test
below is then skipped (no recursion) and :func:`test_inner_run_uses_the_colcon_install_space`
checks that the inner run imported the package colcon built, not the repository's.
"""
import os
import shutil
import stat
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from configparser import ConfigParser
from pathlib import Path

import pytest

from rosidl_buffer_py.report import last_report

ROOT = Path(__file__).resolve().parent.parent
INSIDE = 'RBPY_INSIDE_COLCON_TEST'
PACKAGE = 'rosidl_buffer_py'
#: What the inner `colcon test` runs: the install-space check in this file, and test files that
#: exercise the built extension and the package's entry points without DDS traffic.
INNER_TESTS = ('test/test_colcon.py', 'test/test_codec.py', 'test/test_registry.py',
               'test/test_packaging.py')
INNER_TIMEOUT = 600
#: What the fresh environment installs: the PyPI form of package.xml's dependencies.


def _underlay() -> Path:
    """The venv this test runs in (``./dev``'s, made from exactly the requirement files), as the
    underlay colcon users declare: its interpreter. A fresh venv holding only the requirement
    files is test_install.py's job (``pip install <checkout>`` there); here what matters is the
    colcon build and its install space."""
    venv = Path(sys.prefix)
    if shutil.which('colcon', path=str(venv / 'bin')) is None:
        pytest.skip('colcon is not installed (requirements-test.txt installs it: ./dev setup)')
    return venv


#: What a source tree holds that is not source: left out when it is not a git checkout.
BUILD_OUTPUTS = ('.git', '.venv', 'build', 'install', 'log', '*.egg-info', '__pycache__',
                 '.pytest_cache', '_native*.so')


def _copy_source(destination: Path) -> None:
    """Copy what git would ship, plus untracked files not ignored (work in progress); a source
    tree that is no git checkout (copied into a workspace's src/) without its build outputs."""
    listing = subprocess.run(
        ['git', 'ls-files', '-z', '--cached', '--others', '--exclude-standard'], cwd=ROOT,
        capture_output=True)
    if listing.returncode != 0:
        shutil.copytree(ROOT, destination, ignore=shutil.ignore_patterns(*BUILD_OUTPUTS),
                        dirs_exist_ok=True)
        return
    listed = listing.stdout.decode().split('\0')
    for name in filter(None, listed):
        source = ROOT / name
        if not source.is_file():  # deleted in the working tree
            continue
        target = destination / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(source, target)


def _run(cmd, cwd, env, timeout=600):
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, (f'{" ".join(map(str, cmd))} exited {proc.returncode}\n'
                                  f'{proc.stdout[-6000:]}\n{proc.stderr[-4000:]}')
    return proc


@pytest.mark.skipif(bool(os.environ.get(INSIDE)), reason='inside the colcon test run')
def test_colcon_build_install_space_and_colcon_test(tmp_path):
    venv = _underlay()
    workspace = tmp_path / 'ws'
    source = workspace / 'src' / PACKAGE
    try:
        python = venv / 'bin' / 'python'
        colcon = str(venv / 'bin' / 'colcon')
        _copy_source(source)
        env = dict(os.environ)
        env.pop('PYTHONPATH', None)
        env.pop('VIRTUAL_ENV', None)
        env['PATH'] = os.pathsep.join([str(venv / 'bin'), env.get('PATH', '')])
        env['AMENT_PREFIX_PATH'] = str(venv)  # the underlay: the fresh venv's ROS from PyPI
        env['COLCON_HOME'] = str(tmp_path / 'colcon_home')  # no user configuration
        env['COLCON_LOG_PATH'] = str(workspace / 'log')

        _run([colcon, 'build', '--event-handlers', 'console_cohesion+'], workspace, env)
        prefix = workspace / 'install' / PACKAGE
        site = prefix / 'lib' / f'python{sys.version_info[0]}.{sys.version_info[1]}' / \
            'site-packages'

        # the native extension, the package index entry and the manifest
        assert list((site / PACKAGE).glob('_native*.so')), sorted((site / PACKAGE).iterdir())
        assert (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' /
                PACKAGE).is_file()
        assert (prefix / 'share' / PACKAGE / 'package.xml').is_file()

        # every console script setup.py declares is in lib/<package>/ (where ros2 run looks)
        [egg_info] = site.glob(f'{PACKAGE}-*.egg-info')
        entry_points = ConfigParser(delimiters=('=',))
        entry_points.read(egg_info / 'entry_points.txt')
        assert entry_points.get('rosidl_buffer_py.backends', 'demo').strip() == \
            'demo_buffer_backend:DemoBackend'
        scripts = sorted(entry_points['console_scripts']) \
            if entry_points.has_section('console_scripts') else []
        for script in scripts:
            path = prefix / 'lib' / PACKAGE / script
            assert path.is_file() and path.stat().st_mode & stat.S_IXUSR, path
        print(f'console scripts installed: {scripts or "none declared in setup.py"}')

        # the install space works once sourced, from anywhere: the built extension is imported
        sourced = f'. "{workspace}/install/setup.sh" && '
        probe = _run(['sh', '-c', sourced + f'"{python}" -c "import rosidl_buffer_py, '
                      'rosidl_buffer_py._native as n; print(n.__file__); '
                      'print(sorted(rosidl_buffer_py.get_installed_backends()))"'],
                     tmp_path, env)
        native_file, backends = probe.stdout.strip().splitlines()[-2:]
        assert native_file.startswith(str(site)), probe.stdout
        assert 'demo' in backends, probe.stdout
        # ros2run.api.get_executable_path: <get_package_prefix(pkg)>/lib/<pkg>/<executable>,
        # the prefix found through the ament index of the sourced install space
        (tmp_path / 'lookup.py').write_text(
            'import os\n'
            'from ament_index_python.packages import get_package_prefix\n'
            f'base = os.path.join(get_package_prefix({PACKAGE!r}), "lib", {PACKAGE!r})\n'
            'print(sorted(n for n in os.listdir(base)\n'
            '             if os.access(os.path.join(base, n), os.X_OK)))\n')
        lookup = _run(['sh', '-c', sourced + f'"{python}" lookup.py'], tmp_path, env)
        assert lookup.stdout.strip().splitlines()[-1] == str(scripts), lookup.stdout
        # a node started the way `ros2 run` starts it, publishing over the demo backend
        node = _run(['sh', '-c', sourced + f'"{prefix}/lib/{PACKAGE}/image_publisher" '
                     '--ros-args -r __node:=short_pub -p count:=3 -p width:=16 -p height:=8 '
                     '-p rate_hz:=50.0 -p linger_sec:=0.0 -p settle_sec:=0.0 -p backend:=demo'],
                    tmp_path, env, timeout=120)
        report = last_report(node.stdout.splitlines())
        assert report is not None and report['published'] == 3, node.stdout + node.stderr

        # colcon test: a small subset, against the install space
        test_env = dict(env, **{INSIDE: str(prefix)})
        # `python -m pytest` runs in the source copy, whose rosidl_buffer_py has no compiled
        # _native and would shadow the installed one: keep the working directory off sys.path.
        test_env['PYTHONSAFEPATH'] = '1'
        started = time.monotonic()
        _run([colcon, 'test', '--packages-select', PACKAGE, '--event-handlers',
              'console_cohesion+', '--pytest-args', '-q', '--durations=15', *INNER_TESTS],
             workspace, test_env, timeout=INNER_TIMEOUT)
        print(f'colcon test: {time.monotonic() - started:.0f} s')
        result = _run([colcon, 'test-result', '--verbose', '--test-result-base', 'build'],
                      workspace, env)
        summary = [line for line in result.stdout.splitlines() if line.startswith('Summary:')]
        assert summary, result.stdout
        words = summary[-1].replace(',', '').split()  # Summary: N tests, E errors, F failures,
        counts = {words[i + 1]: int(words[i]) for i in range(1, len(words) - 1, 2)}
        assert counts['tests'] > 100 and counts['errors'] == counts['failures'] == 0, \
            result.stdout
        cases = {case.get('name') for case in ET.parse(
            workspace / 'build' / PACKAGE / 'pytest.xml').iter('testcase')}
        assert 'test_inner_run_uses_the_colcon_install_space' in cases, sorted(cases)
        print(summary[-1])
    finally:
        shutil.rmtree(workspace, ignore_errors=True)
        shutil.rmtree(tmp_path / 'colcon_home', ignore_errors=True)


@pytest.mark.skipif(not os.environ.get(INSIDE), reason='only inside the colcon test run')
def test_inner_run_uses_the_colcon_install_space():
    import rosidl_buffer_py
    import rosidl_buffer_py._native as native
    prefix = os.environ[INSIDE]
    assert rosidl_buffer_py.__file__.startswith(prefix), rosidl_buffer_py.__file__
    assert native.__file__.startswith(prefix), native.__file__
