"""Build and install rosidl_buffer_py (ament_python layout, also a plain pip package).

The native extension ``rosidl_buffer_py._native`` is compiled from ``src/native``. Where the
ROS 2 headers and libraries come from is decided by :func:`ros_prefixes` and nowhere else:

1. the running interpreter's prefix (``sys.prefix``, or ``sys.real_prefix`` when colcon
   overrides it), where the PyPI ROS wheels put ``include/<pkg>/`` and ``lib/`` (a venv made by
   ``./dev``);
2. the prefix where the ``ros-rmw-fastrtps-cpp`` wheel (from ``ros-jazzy-rclpy[fastrtps]``) is
   installed, when it is not the interpreter's: pip's isolated build environment for
   ``pip install <checkout>``, which installs pyproject.toml's build requirements there;
3. then every entry of ``AMENT_PREFIX_PATH``, in order (``/opt/ros/jazzy`` once its
   ``setup.bash`` is sourced, and colcon workspaces above it).

A prefix counts only if it holds ``include/rmw_fastrtps_cpp``. Nothing else is searched; with
none, the build stops with one error that says what to install.

When the ROS packages come from PyPI wheels (1 or 2), they are also install requirements; with
ROS from apt (3 only) they are not pip distributions, and are not required.
"""
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from setuptools import Extension, find_packages, setup
from setuptools.command.build_ext import build_ext

PACKAGE = 'rosidl_buffer_py'
HERE = Path(__file__).resolve().parent


#: The wheel whose headers the extension needs most; where it is installed is a ROS prefix.
ROS_WHEEL = 'ros-rmw-fastrtps-cpp'
#: What the error says to install when no ROS prefix is found.
MISSING_ROS = (
    'rosidl_buffer_py: building the native extension needs the ROS 2 Jazzy headers and '
    'libraries (rmw_fastrtps_cpp, rcl, rmw, fastrtps), and none were found: in {where}, nor in '
    'AMENT_PREFIX_PATH ({ament}). Either let pip install them (the default build, '
    'pyproject.toml\'s build requirements; not with --no-build-isolation), or install them '
    'first: pip install "ros-jazzy-rclpy[fastrtps]" ros-jazzy-common-interfaces; or, with ROS '
    'from apt: source /opt/ros/jazzy/setup.bash')


def wheel_prefix() -> str:
    """The prefix holding the ROS wheel's headers ('' when the wheel is not installed)."""
    from importlib import metadata
    try:
        files = metadata.distribution(ROS_WHEEL).files or []
    except metadata.PackageNotFoundError:
        return ''
    for entry in files:
        parts = Path(entry).parts
        if 'include' in parts and 'rmw_fastrtps_cpp' in parts:
            path = Path(metadata.distribution(ROS_WHEEL).locate_file(entry)).resolve()
            while path.name != 'include':
                path = path.parent
            return str(path.parent)
    return ''


def ros_prefixes() -> list:
    """Return the ROS install prefixes to build against, most preferred first."""
    # colcon's sitecustomize points sys.prefix at the install space and keeps the interpreter's
    # own prefix in sys.real_prefix
    candidates = [sys.prefix, getattr(sys, 'real_prefix', sys.prefix), wheel_prefix()] + [
        p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    found = []
    for prefix in candidates:
        if prefix and (Path(prefix) / 'include' / 'rmw_fastrtps_cpp').is_dir() and \
                prefix not in found:
            found.append(prefix)
    return found


def requirements(name: str) -> list:
    """Read a requirements file: one requirement a line, `#` starts a comment."""
    lines = (line.split('#', 1)[0].strip() for line in (HERE / name).read_text().splitlines())
    return [line for line in lines if line]


def package_version(prefix: str, package: str, path: str = '') -> str:
    """The <version> of ``<prefix>/share/<package>/package.xml`` (or of ``<prefix>/<path>``);
    'unknown' when absent."""
    import xml.etree.ElementTree as ElementTree
    try:
        version = ElementTree.parse(
            Path(prefix) / (path or Path('share') / package / 'package.xml')).findtext('version')
    except (OSError, ElementTree.ParseError):
        return 'unknown'
    return (version or 'unknown').strip()


def built_against_macros(prefixes: list) -> list:
    """The rmw_fastrtps versions the extension is built against, compiled in as macros (Fast
    DDS's comes from its own config.h): rosidl_buffer_py._dds compares them with the running
    libraries at import (see src/native/rmw_fastrtps_private.cpp)."""
    prefix = prefixes[0] if prefixes else ''
    return [(f'RBPY_BUILT_{package.upper()}', f'"{package_version(prefix, package)}"')
            for package in ('rmw_fastrtps_cpp', 'rmw_fastrtps_shared_cpp')]


def native_extension(prefixes: list) -> Extension:
    if not prefixes:
        raise SystemExit(MISSING_ROS.format(
            where=sys.prefix, ament=os.environ.get('AMENT_PREFIX_PATH') or 'not set'))
    # ROS packages install their headers as include/<pkg>/<pkg>/...; Fast DDS as include/fastdds.
    include_dirs = []
    for prefix in prefixes:
        include = Path(prefix) / 'include'
        include_dirs.append(str(include))
        include_dirs.extend(
            str(d) for d in sorted(include.iterdir()) if d.is_dir() and (d / d.name).is_dir())
    library_dirs = [str(Path(p) / 'lib') for p in prefixes]
    # pip's build environment is gone once the wheel is built: the extension then finds the
    # libraries in the venv's lib/, seen from site-packages/<package>/
    lasting = [str(Path(p) / 'lib') for p in prefixes if p != wheel_prefix() or
               p in (sys.prefix, getattr(sys, 'real_prefix', sys.prefix))]
    return Extension(
        f'{PACKAGE}._native',
        sources=sorted(str(p.relative_to(HERE)) for p in (HERE / 'src' / 'native').glob('*.cpp')),
        include_dirs=include_dirs,
        define_macros=built_against_macros(prefixes),
        library_dirs=library_dirs,
        runtime_library_dirs=lasting + ['$ORIGIN/../../..'],
        # rcl: rcl_*_get_rmw_handle, rcl_take_serialized_message, rcl_trigger_guard_condition;
        # rmw: default options, serialized message helpers; rmw_fastrtps_cpp: the rmw_* entry
        # points and get_datawriter/get_datareader/get_domain_participant; fastrtps: DDS API.
        libraries=['rcl', 'rmw', 'rmw_fastrtps_cpp', 'fastrtps', 'fastcdr', 'rcutils'],
        # no debug info (-g0 overrides the interpreter's -g), as a wheel on PyPI is stripped:
        # 0.3 MB instead of 5.9 MB and each build 15% sooner; RBPY_DEBUG_INFO=1 keeps it
        extra_compile_args=['-std=c++17', '-O2', '-Wall', '-Wextra',
                            '-g' if os.environ.get('RBPY_DEBUG_INFO') == '1' else '-g0'],
        # export PyInit__native alone: see src/native/exports.map (why a numpy- or torch-first
        # import crashed where the extension's copies of Fast DDS symbols won the lookup)
        extra_link_args=[f'-Wl,--version-script={HERE / "src" / "native" / "exports.map"}'],
        language='c++',
    )


class ParallelBuildExt(build_ext):
    """build_ext that compiles the extension's C++ sources side by side, one per core:
    setuptools compiles one source after another, and the extension is the slowest step of
    ./dev setup, pip install, colcon build (and of the tests that run them)."""

    def build_extension(self, ext) -> None:
        compile_sources = self.compiler.compile  # the compiler's own, for one source a call

        def compile_each(sources, *args, **kwargs):
            workers = max(1, min(len(sources), os.cpu_count() or 1))
            with ThreadPoolExecutor(workers) as pool:
                batches = pool.map(lambda source: compile_sources([source], *args, **kwargs),
                                   sources)
                return [obj for batch in batches for obj in batch]

        self.compiler.compile = compile_each
        try:
            super().build_extension(ext)
        finally:
            del self.compiler.compile  # back to the class's method


def ros_from_wheels() -> bool:
    """True when the ROS packages come from PyPI wheels (then they are install requirements)."""
    return bool(wheel_prefix())


PREFIXES = ros_prefixes()

setup(
    name=PACKAGE,
    version=package_version(str(HERE), '.', 'package.xml'),
    # the library with its nodes and tools, and the two backends; not launch_free_demos (the
    # demo, the benchmarks, the process runner the tests start nodes with): ./dev and the tests
    # run it from the checkout, and no installed program needs it
    packages=find_packages(include=[PACKAGE, f'{PACKAGE}.*', 'demo_buffer_backend',
                                    'demo_buffer_backend.*', 'cuda_buffer_backend',
                                    'cuda_buffer_backend.*']),
    ext_modules=[native_extension(PREFIXES)],
    cmdclass={'build_ext': ParallelBuildExt},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
    ],
    # PEP 561: the package's type hints are for users, the native module's (its stub) too
    package_data={PACKAGE: ['py.typed', '_native.pyi']},
    zip_safe=False,
    maintainer='rosidl_buffer_py maintainers',
    maintainer_email='maintainers@rosidl-buffer-py.invalid',
    description='Zero-copy uint8[] payloads for rclpy on stock ROS 2 Jazzy.',
    license='Apache-2.0',
    python_requires='>=3.11',  # what ./dev requires and CI tests
    # ROS packages (ros-jazzy-*) are install requirements only when they come from PyPI: with
    # apt ROS they are not pip distributions (see the module docstring).
    install_requires=[r for r in requirements('requirements.txt')
                      if ros_from_wheels() or not r.startswith('ros-')],
    extras_require={'test': requirements('requirements-test.txt')},
    tests_require=requirements('requirements-test.txt'),
    entry_points={
        'rosidl_buffer_py.backends': [
            'demo = demo_buffer_backend:DemoBackend',
            'cuda = cuda_buffer_backend:CudaBackend',
        ],
        # installed in lib/rosidl_buffer_py (setup.cfg), where `ros2 run rosidl_buffer_py` looks
        'console_scripts': [
            'image_publisher = rosidl_buffer_py.nodes.image_publisher:main',
            'image_subscriber = rosidl_buffer_py.nodes.image_subscriber:main',
            'legacy_image_publisher = rosidl_buffer_py.nodes.image_publisher:legacy_main',
            'legacy_image_subscriber = rosidl_buffer_py.nodes.image_subscriber:legacy_main',
            'buffer_topic_info = rosidl_buffer_py.tools.info:main',
            'buffer_record = rosidl_buffer_py.tools.record:main',
            'buffer_play = rosidl_buffer_py.tools.play:main',
            'buffer_bag_info = rosidl_buffer_py.tools.bag_info:main',
            'buffer_bag_reindex = rosidl_buffer_py.tools.reindex:main',
        ],
    },
)
