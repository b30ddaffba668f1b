"""What the runnable nodes share: QoS parameters, reports, clean shutdown on SIGINT/SIGTERM."""
import faulthandler
import json
import signal
import sys
from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

#: A report line starts with this, followed by one JSON object (parsed by launch_free_demos).
REPORT_PREFIX = 'REPORT '

RELIABILITY = {'reliable': ReliabilityPolicy.RELIABLE, 'best_effort': ReliabilityPolicy.BEST_EFFORT}


def declare_qos_parameters(node) -> QoSProfile:
    """Declare ``reliability`` and ``depth`` and return the QoS profile they give."""
    reliability = node.declare_parameter('reliability', 'reliable').value
    depth = node.declare_parameter('depth', 10).value
    if reliability not in RELIABILITY:
        raise ValueError(f'reliability must be one of {sorted(RELIABILITY)}, got {reliability!r}')
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=RELIABILITY[reliability])


def print_report(report: dict) -> None:
    """Print the node's report as one parseable line on stdout."""
    print(REPORT_PREFIX + json.dumps(report, sort_keys=True), flush=True)


#: How long a node may take to tear down after its report before it is ended (see run_node).
TEARDOWN_TIMEOUT_SEC = 20.0


def run_node(make_node: Callable, run: Callable) -> int:
    """Init rclpy, build the node, run it; SIGINT and SIGTERM end it cleanly with its report."""
    # SIGUSR1 prints every thread's Python stack to stderr: the process runner sends it to a
    # node that ignores SIGINT, before SIGKILL, so that a stuck node says where it is stuck.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    rclpy.init(args=sys.argv)
    # SIGTERM takes Ctrl-C's path. (Shutting the context down from the handler instead leaves
    # the next rclpy.spin_once() building a global executor on a dead context: a traceback.)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    node = None
    try:
        node = make_node()
        run(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        # a second Ctrl-C or SIGTERM must not interrupt the report and the cleanup
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if node is not None:
            node.finish()
            # rmw's participant teardown can spin for minutes in Fast DDS 2.14's
            # DomainParticipant::set_listener(nullptr) while a discovery callback of a peer
            # leaving at the same moment waits for the mutex the spinning thread keeps taking
            # (caught here twice in a day of runs, once under gdb; the busy wait is reported as
            # eProsima/Fast-DDS#6513). That thread holds the GIL, so only faulthandler's C
            # thread can act: after TEARDOWN_TIMEOUT_SEC it prints every thread's stack and
            # exits with status 1. The report is already out.
            faulthandler.dump_traceback_later(TEARDOWN_TIMEOUT_SEC, exit=True)
            node.destroy_node()
        rclpy.try_shutdown()
        faulthandler.cancel_dump_traceback_later()
    return 0
