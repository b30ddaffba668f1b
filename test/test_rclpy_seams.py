"""rclpy's private parts: all in rosidl_buffer_py/rclpy_seams_7_1.py, and that module mirrors
the rclpy that is running (a new rclpy release fails here first: read those parts again)."""
import os
import pathlib
import re
import subprocess
import sys
import textwrap
import time

from rclpy.node import Node

from rosidl_buffer_py import _dds, rclpy_seams_7_1 as seams

PACKAGE = pathlib.Path(seams.__file__).parent
#: What reaching into rclpy looks like: its C module, a node's private attribute, its private
#: QoS-parameter helper.
PRIVATE = re.compile(r'rclpy\.impl|_rclpy_pybind11|\bnode\._[a-z]|_declare_qos_parameters')


def test_the_seams_mirror_the_running_rclpy():
    """Fails when the running rclpy is not the release the seams were read from: compare each
    part named in rclpy_seams_7_1.py with the new rclpy, then update MIRRORS (and the name)."""
    assert seams.running_version() == seams.MIRRORS, (seams.running_version(), seams.MIRRORS)
    assert seams.matches()


def test_every_private_part_the_seams_name_exists_in_the_running_rclpy():
    for name in ('_validate_qos_or_depth_parameter', '_validate_topic_or_service_name',
                 '_wake_executor'):
        assert callable(getattr(Node, name, None)), name
    from rclpy import qos_overriding_options
    assert callable(qos_overriding_options._declare_qos_parameters)
    assert hasattr(seams.DelegatingReader, 'take_message')
    from rclpy.impl.implementation_singleton import rclpy_implementation
    assert callable(rclpy_implementation.rclpy_logging_rcutils_log)  # seams.log


def test_no_other_module_of_the_package_reaches_into_rclpy():
    offenders = []
    for path in sorted(PACKAGE.rglob('*.py')):
        if path.name == 'rclpy_seams_7_1.py':
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if PRIVATE.search(line.split('#')[0]):
                offenders.append(f'{path.relative_to(PACKAGE.parent)}:{number}: {line.strip()}')
    assert not offenders, '\n'.join(offenders)


def test_a_delegating_reader_takes_what_its_take_gives():
    import rclpy
    from std_msgs.msg import String
    rclpy.init()
    try:
        node = rclpy.create_node('seams_reader')
        _dds.type_support(String)  # as rclpy's create_* import it first
        reader = seams.delegating_reader(node, String, '/seams_reader', rclpy.qos.QoSProfile(
            depth=1))
        assert reader.take_message(String, False) is None  # nothing set: nothing taken
        reader.take = lambda: ('message', {'source_timestamp': 1})
        assert reader.take_message(String, False) == ('message', {'source_timestamp': 1})
        reader.destroy_when_not_in_use()
        node.destroy_node()
    finally:
        rclpy.shutdown()


def test_the_subscription_counter_counts_as_rclpy_does():
    import rclpy
    from std_msgs.msg import String
    rclpy.init()
    try:
        node = rclpy.create_node('seams_counter')
        pub = node.create_publisher(String, '/seams_counter', 1)
        count = seams.subscription_counter(pub)
        assert count() == pub.get_subscription_count() == 0
        subs = [node.create_subscription(String, '/seams_counter', lambda m: None, 1)
                for _ in range(2)]
        deadline = time.monotonic() + 10.0
        while pub.get_subscription_count() < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert count() == pub.get_subscription_count() == 2
        node.destroy_subscription(subs[0])
        while pub.get_subscription_count() > 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert count() == pub.get_subscription_count() == 1
        node.destroy_node()
    finally:
        rclpy.shutdown()


def test_log_writes_what_rclpys_logger_writes_and_nothing_below_the_level():
    """seams.log is rclpy's logger call without its caller lookup: the same console line (a
    node's logger, so /rosout too: test_rclpy_citizenship), nothing when the level is off."""
    script = textwrap.dedent('''
        import rclpy
        from rclpy.logging import LoggingSeverity
        from rosidl_buffer_py import rclpy_seams_7_1 as seams
        rclpy.init()
        logger = rclpy.create_node('seams_log').get_logger().get_child('child')
        def caller():
            pass
        logger.info('the same line')
        assert seams.log(logger, LoggingSeverity.INFO, 'the same line', caller)
        assert not seams.log(logger, LoggingSeverity.DEBUG, 'not this one', caller)
        rclpy.shutdown()
    ''')
    env = {**os.environ, 'RCUTILS_CONSOLE_OUTPUT_FORMAT':
           '[{severity}] [{name}]: {message} ({function_name})'}
    done = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                          timeout=60, env=env)
    assert done.returncode == 0, done.stderr
    lines = [line for line in done.stderr.splitlines() if 'seams_log' in line]
    assert lines == ['[INFO] [seams_log.child]: the same line (<module>)',
                     '[INFO] [seams_log.child]: the same line (caller)'], done.stderr
