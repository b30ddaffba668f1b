"""The package is a proper ament_python package, its dependency lists agree, and the wheel
ships what is installed, nothing of the checkout's demos, benchmarks and tests."""
import ast
import configparser
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


#: package.xml keys the PyPI path gets without a requirements line, and why.
NOT_FROM_PIP = {'python3-dev': "the Python headers come with the venv's interpreter",
                'python3-pip': 'every venv has pip'}

#: Top-level modules imported by the code -> the package.xml key that provides them.
MODULE_KEYS = {
    'rclpy': 'rclpy', 'rcl_interfaces': 'rcl_interfaces', 'rosidl_parser': 'rosidl_parser',
    'sensor_msgs': 'sensor_msgs', 'std_msgs': 'std_msgs', 'geometry_msgs': 'geometry_msgs',
    'visualization_msgs': 'visualization_msgs', 'ament_index_python': 'ament_index_python',
    'stereo_msgs': 'stereo_msgs', 'test_msgs': 'test_msgs',
    'numpy': 'python3-numpy', 'pytest': 'python3-pytest', 'hypothesis': 'python3-hypothesis',
    'matplotlib': 'python3-matplotlib', 'setuptools': 'python3-setuptools',
    'mcap': 'python3-mcap', 'yaml': 'python3-yaml', 'mcap_ros2': 'python3-mcap-ros2-support',
}
#: Modules a test uses only where they are installed (that check is skipped otherwise): never
#: declared, never installed by ./dev or CI.
OPTIONAL_TEST_MODULES = {'rosbags': 'test_reindex.py reads repaired bags back with it too',
                         'torch': 'the GPU tests use it as a consumer where it is installed',
                         'cupy': 'the GPU tests use it as a consumer where it is installed'}
#: GPU libraries the GPU peer and benchmark import (inside functions), where the machine has them:
#: never declared (the cuda backend itself needs none of them), never installed by ./dev or CI.
OPTIONAL_GPU_MODULES = {'torch', 'cupy'}
GPU_FILES = ('launch_free_demos/cuda_peer.py', 'launch_free_demos/bench/cuda.py')
#: What setup.py installs: the library with its nodes and tools, and the two backends.
INSTALLED_PACKAGES = ('rosidl_buffer_py', 'demo_buffer_backend', 'cuda_buffer_backend')
#: Modules of this repository (or made by the tests) that need no dependency.
OWN_MODULES = {'rosidl_buffer_py', 'demo_buffer_backend', 'cuda_buffer_backend',
               'launch_free_demos', 'harness',
               'rbpy_example_backend', 'test_codec', 'test_codec_general', 'test_packaging',
               'my_backend'}


def requirement_lines(name):
    """(requirement, package.xml keys) of a requirements file: after ``#``, the keys the line
    provides, comma-separated, up to an optional ``:`` and explanation."""
    pairs = []
    for line in (ROOT / name).read_text().splitlines():
        requirement, _, comment = line.partition('#')
        if requirement.strip():
            keys = comment.split(':', 1)[0]
            pairs.append((requirement.strip(), {k.strip() for k in keys.split(',') if k.strip()}))
    return pairs


def package_xml_keys():
    """package.xml dependency keys by kind: build, exec and test (``depend`` is build and exec)."""
    root = ET.parse(ROOT / 'package.xml').getroot()
    keys = {kind: {e.text for e in root.findall(f'{kind}_depend')}
            for kind in ('build', 'exec', 'test', 'buildtool')}
    both = {e.text for e in root.findall('depend')}
    keys['build'] |= both | keys.pop('buildtool')
    keys['exec'] |= both
    return keys


def provided(name):
    return set().union(*(keys for _, keys in requirement_lines(name)))


def test_package_xml_is_format_3_ament_python():
    root = ET.parse(ROOT / 'package.xml').getroot()
    assert root.tag == 'package' and root.get('format') == '3'
    assert root.findtext('name') == 'rosidl_buffer_py'
    assert root.findtext('export/build_type') == 'ament_python'
    assert (ROOT / 'resource' / 'rosidl_buffer_py').is_file()


def test_requirements_agree_with_package_xml_both_ways():
    keys = package_xml_keys()
    runtime, build, tests = (provided(f) for f in (
        'requirements.txt', 'requirements-build.txt', 'requirements-test.txt'))
    for name in ('requirements.txt', 'requirements-build.txt', 'requirements-test.txt'):
        for requirement, line_keys in requirement_lines(name):
            assert line_keys, f'{name}: {requirement!r} names no package.xml key'
    # every requirement provides declared keys of the matching kind ...
    assert runtime <= keys['exec'] | keys['test'], runtime - keys['exec'] - keys['test']
    assert build <= keys['build'], build - keys['build']
    assert tests <= keys['test'], tests - keys['test']
    # ... and every declared key is provided by a requirement (or listed in NOT_FROM_PIP)
    assert keys['exec'] - set(NOT_FROM_PIP) <= runtime, keys['exec'] - runtime
    assert keys['build'] - set(NOT_FROM_PIP) <= runtime | build, \
        keys['build'] - runtime - build - set(NOT_FROM_PIP)
    assert keys['test'] - set(NOT_FROM_PIP) <= runtime | tests, \
        keys['test'] - runtime - tests - set(NOT_FROM_PIP)
    assert any(re.match(r'ros-jazzy-rclpy\[fastrtps\]', req)
               for req, _ in requirement_lines('requirements.txt'))


def _imported_modules(paths):
    modules = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                modules |= {alias.name.split('.')[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                modules.add(node.module.split('.')[0])
    return modules - set(sys.stdlib_module_names) - OWN_MODULES


def bench_modules():
    """Module -> requirement of requirements-bench.txt, the benchmark's optional peers (the
    comment of each line names the module it provides; they have no package.xml key)."""
    modules = {}
    for requirement, keys in requirement_lines('requirements-bench.txt'):
        assert len(keys) == 1, f'requirements-bench.txt: {requirement!r} names no one module'
        modules[keys.pop()] = requirement
    return modules


def test_every_imported_module_is_declared():
    """The installed packages' imports are exec dependencies; the demos' and benchmarks' (run
    from the checkout) exec dependencies too, or matplotlib for the benchmark's plots (a test
    dependency, which ./dev installs); the tests' exec or test dependencies; setup.py's build
    dependencies. Only the benchmark's peer nodes import the optional modules of
    requirements-bench.txt."""
    keys = package_xml_keys()
    peers = ROOT / 'launch_free_demos' / 'bench' / 'peers'
    package = [p for d in INSTALLED_PACKAGES for p in (ROOT / d).rglob('*.py')]
    demos = [p for p in (ROOT / 'launch_free_demos').rglob('*.py') if peers not in p.parents]
    tests = list((ROOT / 'test').rglob('*.py'))
    for paths, allowed in ((package, keys['exec']),
                           (demos, keys['exec'] | {'python3-matplotlib'}),
                           (tests, keys['exec'] | keys['test']),
                           ([ROOT / 'setup.py'], keys['build'])):
        modules = _imported_modules(paths)
        if paths is tests:
            modules -= set(OPTIONAL_TEST_MODULES)
        if paths is demos:
            others = [p for p in demos if p.relative_to(ROOT).as_posix() not in GPU_FILES]
            assert not _imported_modules(others) & OPTIONAL_GPU_MODULES
            modules -= OPTIONAL_GPU_MODULES
        unknown = modules - set(MODULE_KEYS)
        assert not unknown, f'imported, no package.xml key known: {sorted(unknown)}'
        undeclared = {MODULE_KEYS[m] for m in modules} - allowed
        assert not undeclared, f'imported but not declared: {sorted(undeclared)}'
    peer_modules = _imported_modules(peers.rglob('*.py'))
    assert peer_modules - set(bench_modules()) <= {'numpy'}, peer_modules


def test_bench_requirements_are_optional_and_match_the_benchmark_peers():
    """requirements-bench.txt names exactly the peers' modules; neither ./dev setup, CI nor
    setup.py reads it (./dev's help and docs/benchmarks.md say how to install it), and no
    package.xml key is one of them."""
    from launch_free_demos.bench.suite import PEERS
    modules = bench_modules()
    assert {t.peer_module: t.pip_name for t in PEERS} == {
        module: re.split(r'[<>=!~\[ ]', requirement)[0] for module, requirement in modules.items()}
    dev = (ROOT / 'dev').read_text()
    setup_function = dev.split('setup() {', 1)[1].split('\n}\n', 1)[0]
    for name, text in (('./dev setup', setup_function),
                       ('setup.py', (ROOT / 'setup.py').read_text()),
                       ('.ci/run', (ROOT / '.ci' / 'run').read_text())):
        assert 'requirements-bench' not in text, name
    assert 'requirements-bench.txt' in dev.split('set -euo', 1)[0]  # ./dev's help says how
    assert not set(modules) & set().union(*package_xml_keys().values())
    assert 'pip install -r requirements-bench.txt' in (ROOT / 'docs' / 'benchmarks.md').read_text()


def test_python_requires_matches_what_dev_requires():
    setup_py = (ROOT / 'setup.py').read_text()
    assert "python_requires='>=3.11'" in setup_py
    assert 'sys.version_info < (3, 11)' in (ROOT / 'dev').read_text()


def test_the_wheel_holds_the_installed_packages_not_the_demos_benchmarks_or_runner(tmp_path):
    """What setup.py packs into the wheel beside the extension (build_py: the Python files,
    py.typed, the stub) is the library with its nodes and tools, and the backends, whole; not
    launch_free_demos (the demo, the benchmarks, the process runner: ./dev and the tests run
    them from the checkout), nor the tests. test_install.py checks a real pip install."""
    built = subprocess.run(
        [sys.executable, 'setup.py', '-q', 'egg_info', '--egg-base', str(tmp_path),
         'build_py', '--build-lib', str(tmp_path / 'lib')],
        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert built.returncode == 0, built.stdout[-3000:] + built.stderr[-3000:]
    [top_level] = tmp_path.glob('*.egg-info/top_level.txt')
    assert sorted(top_level.read_text().split()) == sorted(INSTALLED_PACKAGES)
    lib = tmp_path / 'lib'
    assert sorted(p.name for p in lib.iterdir()) == sorted(INSTALLED_PACKAGES)
    shipped = {p.relative_to(lib).as_posix() for p in lib.rglob('*') if p.is_file()}
    sources = {p.relative_to(ROOT).as_posix()
               for package in INSTALLED_PACKAGES for p in (ROOT / package).rglob('*.py')}
    assert sources <= shipped, f'modules the wheel leaves out: {sorted(sources - shipped)}'
    assert {'rosidl_buffer_py/py.typed', 'rosidl_buffer_py/_native.pyi',
            'rosidl_buffer_py/report.py'} <= shipped
    # every console script and backend entry point names a module the wheel ships
    [entry_points] = tmp_path.glob('*.egg-info/entry_points.txt')
    targets = re.findall(r'^\S+ = ([\w.]+):', entry_points.read_text(), re.M)
    assert len(targets) >= 10, entry_points.read_text()
    for module in targets:
        path = module.replace('.', '/')
        assert f'{path}.py' in shipped or f'{path}/__init__.py' in shipped, module


def test_setup_cfg_installs_scripts_where_ros2_run_looks():
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / 'setup.cfg')
    assert cfg['develop']['script_dir'] == '$base/lib/rosidl_buffer_py'
    assert cfg['install']['install_scripts'] == '$base/lib/rosidl_buffer_py'


def test_setup_py_declares_pytest_for_colcon_and_the_demo_backend_entry_point():
    text = (ROOT / 'setup.py').read_text()
    assert "tests_require=requirements('requirements-test.txt')" in text
    assert "'demo = demo_buffer_backend:DemoBackend'" in text


def test_ci_runs_exactly_the_readme_test_command():
    readme = (ROOT / 'README.md').read_text()
    first_block = readme.split('```bash', 1)[1].split('```', 1)[0]
    commands = [line.split('#')[0].strip() for line in first_block.strip().splitlines()]
    assert commands[:2] == ['./dev demo', './dev test']
    ci = [line.strip() for line in (ROOT / '.ci' / 'run').read_text().splitlines()
          if line.strip() and not line.startswith('#')]
    assert ci[-1] == commands[1]
