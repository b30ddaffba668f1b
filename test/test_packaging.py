"""The package is a proper ament_python package and its dependency lists agree."""
import configparser
import re
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def requirement_lines(name):
    """(requirement, ROS key from the comment) pairs of a requirements file."""
    pairs = []
    for line in (ROOT / name).read_text().splitlines():
        requirement, _, comment = line.partition('#')
        if requirement.strip():
            pairs.append((requirement.strip(), comment.split()[0] if comment.split() else None))
    return pairs


def test_package_xml_is_format_3_ament_python():
    root = ET.parse(ROOT / 'package.xml').getroot()
    assert root.tag == 'package' and root.get('format') == '3'
    assert root.findtext('name') == 'rosidl_buffer_py'
    assert root.findtext('export/build_type') == 'ament_python'
    assert (ROOT / 'resource' / 'rosidl_buffer_py').is_file()


def test_requirements_agree_with_package_xml():
    root = ET.parse(ROOT / 'package.xml').getroot()
    exec_depends = {e.text for e in root.findall('exec_depend')}
    test_depends = {e.text for e in root.findall('test_depend')}
    runtime = requirement_lines('requirements.txt')
    tests = requirement_lines('requirements-test.txt')
    # every runtime requirement names the package.xml key it provides, and vice versa
    assert {key for _, key in runtime} == exec_depends
    assert {'python3-pytest'} <= {key for _, key in tests}
    assert test_depends <= {key for _, key in tests}
    assert any(re.match(r'ros-jazzy-rclpy\[fastrtps\]', req) for req, _ in runtime)


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
