"""The ABI guard: the native layer reads rmw_fastrtps's private memory layout, so it runs only
when the running rmw_fastrtps_cpp, rmw_fastrtps_shared_cpp and Fast DDS are the versions it was
built against; otherwise buffer-aware endpoints are plain rclpy ones, with one warning.

The mismatch is simulated in a subprocess by changing the recorded (built-against) Fast DDS
version and running the import-time check again; everything else is real.
"""
import json
import subprocess
import sys
import textwrap

from rosidl_buffer_py import _dds, _native

_MISMATCH = textwrap.dedent('''
    import json, time
    import rclpy
    from std_msgs.msg import UInt8MultiArray
    import rosidl_buffer_py
    from rosidl_buffer_py import _dds, _native
    assert _dds.abi_status().ok and _native.private_layout_verified()
    _dds.BUILT_AGAINST['fastrtps'] = '2.14.0-simulated'
    status = _dds.check_abi()
    _dds.check_abi()  # the same reason: no second warning
    rclpy.init()
    node = rclpy.create_node('abi_guard')
    pub = rosidl_buffer_py.create_publisher(node, UInt8MultiArray, 'abi_guard', 10)
    got = []
    sub = rosidl_buffer_py.create_subscription(
        node, UInt8MultiArray, 'abi_guard', got.append, 10, acceptable_buffer_backends='any')
    deadline = time.monotonic() + 20
    while not got and time.monotonic() < deadline:
        pub.publish(UInt8MultiArray(data=b'abc'))
        rclpy.spin_once(node, timeout_sec=0.1)
    try:
        _native.matched_subscription_gids(pub.handle)
        refused = None
    except _dds.DdsError as exc:
        refused = str(exc)
    print(json.dumps({'ok': status.ok, 'reason': status.reason,
                      'supported': _dds.is_supported(), 'why': _dds.unsupported_reason(),
                      'verified': _native.private_layout_verified(),
                      'received': [bytes(m.data).decode() for m in got[:1]],
                      'buffer_aware': pub.statistics()['buffer_aware'], 'refused': refused}))
    node.destroy_node()
    rclpy.shutdown()
''')


def test_running_libraries_are_the_built_ones_here():
    status = _dds.abi_status()
    assert status.ok, status
    assert set(status.built) == {'rmw_fastrtps_cpp', 'rmw_fastrtps_shared_cpp', 'fastrtps'}
    for package, version in status.built.items():
        assert version != 'unknown'
        assert status.running[package], package
        assert all(v == version for _, v in status.running[package]), status.running
    assert _native.private_layout_verified() and _dds.unsupported_reason() is None


def test_a_version_mismatch_falls_back_to_plain_rclpy_with_one_warning():
    proc = subprocess.run([sys.executable, '-c', _MISMATCH], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert not result['ok'] and not result['supported'] and not result['verified'], result
    assert 'fastrtps 2.14' in result['reason'] and '2.14.0-simulated' in result['reason']
    assert 'built against' in result['why']
    assert result['received'] == ['abc'] and result['buffer_aware'] is False, result
    assert result['refused'] and 'not verified' in result['refused'], result
    warnings = [line for line in proc.stderr.splitlines() if 'differ from those' in line]
    assert len(warnings) == 1, proc.stderr
