"""Where the environment under test installed this package: one place for every test.

The package under test is the ``rosidl_buffer_py`` that is imported (conftest.py makes that the
install space's copy under ``colcon test``). Its executables are in ``<prefix>/lib/<package>/``
of the prefix it was installed into, where ``ros2 run`` looks:

- a colcon install space or any ``setup.py install`` prefix: the package is in
  ``<prefix>/lib/pythonX.Y/site-packages/``, so ``<prefix>`` is four levels above it;
- the ``./dev`` venv: the package is imported from the source tree (an editable install) and
  its scripts went to ``<venv>/lib/<package>/`` (setup.cfg's ``[develop] script_dir``).

Tests never assume one of these layouts: they call :func:`executable` and :func:`prefix`.
"""
import os
import sys
from pathlib import Path

import rosidl_buffer_py

PACKAGE = 'rosidl_buffer_py'
#: The repository (or, under colcon, the source copy the tests run from).
ROOT = Path(__file__).resolve().parents[2]
#: The venv ``./dev`` makes and runs in.
DEV_VENV = Path(os.environ.get('ROSIDL_BUFFER_PY_VENV', ROOT / '.venv'))


def prefix() -> Path:
    """The install prefix of the imported package (the venv for an editable install)."""
    package_dir = Path(rosidl_buffer_py.__file__).resolve().parent
    site = package_dir.parent
    if site.name in ('site-packages', 'dist-packages') and site.parent.parent.name == 'lib':
        return site.parent.parent.parent
    return Path(sys.prefix)


def executable(name: str) -> Path:
    """The installed executable ``name`` (``ros2 run rosidl_buffer_py <name>`` runs this)."""
    return prefix() / 'lib' / PACKAGE / name


def in_dev_venv() -> bool:
    """True when the tests run in the venv of ``./dev`` (the README's commands apply)."""
    return Path(sys.prefix).resolve() == DEV_VENV.resolve()
