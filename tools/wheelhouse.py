"""Prepares an offline wheelhouse: binary wheels, for a target Python and platform, of everything
requirements.txt, requirements-build.txt and requirements-test.txt need (colcon aside), so that
the package and its test suite install on a machine without internet. Run by `./dev wheelhouse`;
docs/development.md, "Installing on a machine without internet", says how it is used.
Standard library and pip only: it runs with .venv's python or a plain python3."""
import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

try:
    from packaging.version import InvalidVersion, Version
except ImportError:  # a plain python3 has pip's copy
    from pip._vendor.packaging.version import InvalidVersion, Version

ROOT = Path(__file__).resolve().parent.parent
REQUIREMENTS = ['requirements.txt', 'requirements-build.txt', 'requirements-test.txt']
PLATFORMS = ['manylinux_2_28_x86_64', 'manylinux_2_17_x86_64', 'manylinux2014_x86_64']
#: Never fetched: colcon (only test/test_colcon.py uses it, and skips without it) and the
#: ament_cmake linters that ROS's message packages pull in (build-time only).
NEVER = ['colcon-common-extensions']
DROPPED = re.compile(r'ros[-_]jazzy[-_]ament[-_]cmake[-_]|ros[-_]ament[-_]cmake[-_]')


def name_of(requirement: str) -> str:
    """The normalized distribution name of a requirement line or wheel file name."""
    if requirement.endswith('.whl'):
        requirement = requirement.split('-', 1)[0]
    return re.sub(r'[-_.]+', '-', re.match(r'[A-Za-z0-9._-]+', requirement).group()).lower()


def requirements() -> list:
    lines = []
    for file in REQUIREMENTS:
        for line in (ROOT / file).read_text().splitlines():
            line = line.split('#', 1)[0].strip()
            if line and line not in lines:
                lines.append(line)
    return lines


def version(wheel: Path):
    try:
        return Version(wheel.name.split('-')[1])
    except InvalidVersion:
        return Version('0')


def main() -> int:
    parser = argparse.ArgumentParser(prog='./dev wheelhouse',
                                     description=__doc__.split('.')[0] + '.')
    parser.add_argument('--python-version', default='3.12', help='target CPython (default 3.12)')
    parser.add_argument('--platform', action='append',
                        help=f'target platform tag, repeatable (default {" ".join(PLATFORMS)})')
    parser.add_argument('--out', default=str(ROOT / '.wheelhouse'),
                        help='the wheelhouse folder (default .wheelhouse/ in the checkout)')
    parser.add_argument('--skip-present', default='',
                        help='comma-separated packages the target already has: not fetched, '
                        'and dropped where others pull them in (e.g. numpy,setuptools,pytest)')
    args = parser.parse_args()
    out = Path(args.out).resolve()
    skip = {name_of(name) for name in args.skip_present.split(',') if name.strip()}
    skip |= {name_of(name) for name in NEVER}
    wanted = [line for line in requirements() if name_of(line) not in skip]
    out.mkdir(parents=True, exist_ok=True)
    if (out / 'INSTALL.txt').exists():  # an earlier wheelhouse (maybe for another Python): anew
        for wheel in out.glob('*.whl'):
            wheel.unlink()
    pip = [sys.executable, '-m', 'pip', '--disable-pip-version-check']

    # empy 3 (rosidl's templates) is published as an sdist only: a pure-Python wheel built here
    with tempfile.TemporaryDirectory() as empy:
        subprocess.run([*pip, 'wheel', '--quiet', '--no-deps', '-w', empy, 'empy<4'], check=True)
        platforms = [flag for tag in (args.platform or PLATFORMS) for flag in ('--platform', tag)]
        print(f'wheelhouse: fetching wheels for CPython {args.python_version} into {out}',
              file=sys.stderr)
        subprocess.run([*pip, 'download', '--quiet', '--only-binary=:all:',
                        '--python-version', args.python_version, '--implementation', 'cp',
                        *platforms, '--find-links', empy, '-d', str(out), *wanted], check=True)

    removed = []
    newest = {}
    for wheel in sorted(out.glob('*.whl')):
        name = name_of(wheel.name)
        if name in skip or DROPPED.match(name):
            removed.append(wheel)
            continue
        if name in newest:  # two versions of one package stop pip's install: keep the newest
            older, newest[name] = sorted([newest[name], wheel], key=version)
            removed.append(older)
        else:
            newest[name] = wheel
    for wheel in removed:
        wheel.unlink()
    for other in out.iterdir():  # sdists pip may have left (none with --only-binary)
        if other.is_file() and other.suffix != '.whl' and other.name != 'INSTALL.txt':
            other.unlink()

    (out / 'INSTALL.txt').write_text(f"""\
Offline wheelhouse for rosidl_buffer_py: CPython {args.python_version}, \
{' '.join(args.platform or PLATFORMS)}.
Made by `./dev wheelhouse`; left out: {', '.join(sorted(skip))} (the target's own; colcon:
test/test_colcon.py skips without it).
Copy this folder and a checkout of rosidl_buffer_py (without .venv, build/, *.so) to the target,
then install into the target's own python3 (a new venv would not see its torch or CuPy):

  cd <this folder> && python3 -m pip install --no-index --no-deps --no-compile ./*.whl
  cd <the checkout> && python3 -m pip install --no-index --no-deps --no-build-isolation -e .

The second command builds the native extension with the system g++ and the Python headers
(about 40 s) and needs setuptools on the target. Check:

  cd /tmp && python3 -c "import rclpy, rosidl_buffer_py, sensor_msgs.msg; print('ok')"
""")

    wheels = sorted(out.glob('*.whl'))
    size = sum(wheel.stat().st_size for wheel in wheels)
    for wheel in removed:
        print(f'wheelhouse: dropped {wheel.name}', file=sys.stderr)
    print(f'{len(wheels)} wheels, {size / 1e6:.1f} MB in {out} (install: {out / "INSTALL.txt"})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
