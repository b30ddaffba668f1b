"""What the runnable nodes share: declared parameters with their help, QoS parameters, clean
shutdown on SIGINT/SIGTERM (the report line they end with is :mod:`.report`'s).

Each node lists its ROS parameters once, as :class:`Param` entries. From that one table come
``--help`` (every parameter with its type, default and meaning), the ``ParameterDescriptor``
each parameter is declared with (what ``ros2 param describe`` shows) and the start-up checks: a
value of the wrong type or outside what is accepted ends the node before it touches the graph,
with one line on stderr naming the parameter, the value and what is accepted, and exit status 2
(:class:`ParameterError`, caught by :func:`run_node`).
"""
import dataclasses
import faulthandler
import json
import signal
import sys
from dataclasses import dataclass
from typing import Any, Callable, Dict, Iterable, Optional, Sequence

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.executors import ExternalShutdownException
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args

from rosidl_buffer_py.report import REPORT_PREFIX

RELIABILITY = {'reliable': ReliabilityPolicy.RELIABLE, 'best_effort': ReliabilityPolicy.BEST_EFFORT}

#: Exit status of a node started with a bad parameter (as argparse's usage errors).
USAGE_ERROR = 2


class ParameterError(ValueError):
    """A parameter value the node cannot run with; the message is the one line the user sees."""


@dataclass(frozen=True)
class Param:
    """One ROS parameter of a node: name, default (which fixes its type) and meaning.

    ``choices`` (accepted values) and ``minimum`` are checked at start-up; ``accepts`` is the
    text shown for other constraints that the node checks itself.
    """

    name: str
    default: Any
    description: str
    choices: Sequence[Any] = ()
    minimum: Optional[float] = None
    accepts: str = ''

    @property
    def type_name(self) -> str:
        return {bool: 'bool', int: 'integer', float: 'double', str: 'string'}[type(self.default)]

    def constraints(self) -> str:
        """What values are accepted, in words ('' when any value of the type is)."""
        if self.choices:
            return 'one of ' + ', '.join(map(str, self.choices))
        if self.accepts:
            return self.accepts
        if self.minimum is not None:
            return f'>= {self.minimum:g}'
        return ''

    def descriptor(self) -> ParameterDescriptor:
        return ParameterDescriptor(
            name=self.name, type=Parameter.Type.from_parameter_value(self.default).value,
            description=self.description, additional_constraints=self.constraints())


def bad_parameter(name: str, value: Any, accepted: str) -> ParameterError:
    """The one-line error for parameter ``name``: its bad value and what is accepted."""
    return ParameterError(f'parameter {name}: {value!r} is not accepted; expected {accepted}')


def _declare(node, spec: Param) -> Any:
    """Declare one parameter with its descriptor; an integer given for a double is converted."""
    try:
        return node.declare_parameter(spec.name, spec.default, spec.descriptor()).value
    except InvalidParameterTypeException:
        pass
    # Read the override as given (any type), then declare the parameter typed as documented.
    given = node.declare_parameter(
        spec.name, None, ParameterDescriptor(dynamic_typing=True)).value
    node.undeclare_parameter(spec.name)
    if isinstance(spec.default, float) and isinstance(given, int) and \
            not isinstance(given, bool):
        return node.declare_parameter(spec.name, float(given), spec.descriptor(),
                                      ignore_override=True).value
    constraint = spec.constraints()
    raise bad_parameter(spec.name, given, f'a {spec.type_name}' +
                        (f' ({constraint})' if constraint else ''))


def declare_parameters(node, specs: Sequence[Param]) -> Dict[str, Any]:
    """Declare every parameter of ``specs`` on ``node``; return name -> value.

    :raises ParameterError: A value of the wrong type, not among ``choices`` or below
        ``minimum``.
    """
    values = {}
    for spec in specs:
        value = _declare(node, spec)
        if spec.choices and value not in spec.choices:
            raise bad_parameter(spec.name, value, spec.constraints())
        if spec.minimum is not None and value < spec.minimum:
            raise bad_parameter(spec.name, value, spec.constraints())
        values[spec.name] = value
    return values


def with_default(specs: Sequence[Param], name: str, default: Any) -> tuple:
    """``specs`` with parameter ``name`` defaulting to ``default`` (the legacy node variants)."""
    return tuple(dataclasses.replace(s, default=default) if s.name == name else s for s in specs)


#: The QoS parameters every image node has (see :func:`qos_profile`).
QOS_PARAMETERS = (
    Param('reliability', 'reliable', 'QoS reliability of the endpoint',
          choices=tuple(RELIABILITY)),
    Param('depth', 10, 'QoS history depth (KEEP_LAST)', minimum=1),
)


def qos_profile(params: Dict[str, Any]) -> QoSProfile:
    """The QoS profile the ``reliability`` and ``depth`` parameters give."""
    return QoSProfile(depth=params['depth'], history=HistoryPolicy.KEEP_LAST,
                      reliability=RELIABILITY[params['reliability']])


def usage(program: str, summary: str, specs: Sequence[Param]) -> str:
    """The ``--help`` text: how to pass parameters, then each one with type, default, meaning."""
    lines = [f'usage: {program} [--help] [--ros-args -p NAME:=VALUE ...]', '', summary, '',
             'ROS parameters (-p NAME:=VALUE; an integer is accepted for a double):']
    for spec in specs:
        default = json.dumps(spec.default) if isinstance(spec.default, (str, bool)) \
            else repr(spec.default)
        lines.append(f'  {spec.name} ({spec.type_name}, default {default})')
        constraint = spec.constraints()
        lines.append(f'      {spec.description}' + (f'; {constraint}' if constraint else ''))
    lines += ['', 'Ctrl-C or SIGTERM ends the node cleanly; it then prints its report as one '
              f'line starting with {REPORT_PREFIX.strip()!r}. Exit status: 0, 2 for a bad '
              'parameter.']
    return '\n'.join(lines)


def handle_command_line(program: str, summary: str, specs: Sequence[Param],
                        argv: Sequence[str]) -> Optional[int]:
    """``--help``: print the usage and return 0. Other non-ROS arguments: one line, return 2.

    Returns None when the node should start. Runs before ``rclpy.init``: no DDS participant is
    created for ``--help`` or a usage error.
    """
    extra = remove_ros_args(list(argv))[1:]
    if '-h' in extra or '--help' in extra:
        print(usage(program, summary, specs))
        return 0
    if extra:
        print(f'{program}: unrecognized arguments {" ".join(extra)}; parameters go after '
              '--ros-args as -p NAME:=VALUE (see --help)', file=sys.stderr)
        return USAGE_ERROR
    return None


class _Interrupts:
    """SIGINT and SIGTERM raise KeyboardInterrupt, as Python's default SIGINT handler does, and
    are remembered: :func:`run_node` tells an interrupt from an error by them."""

    def __init__(self) -> None:
        self.received: list = []
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, self._handle)

    def _handle(self, signum: int, frame) -> None:
        self.received.append(signal.Signals(signum).name)
        raise KeyboardInterrupt


#: How long a node may take to tear down after its report before it is ended (see run_node).
TEARDOWN_TIMEOUT_SEC = 20.0


def run_node(make_node: Callable, run: Callable, *, program: str = '', summary: str = '',
             parameters: Sequence[Param] = ()) -> int:
    """Init rclpy, build the node, run it; SIGINT and SIGTERM end it cleanly with its report.

    With ``parameters``, ``--help`` prints their usage first (and the node does not start); a
    :class:`ParameterError` raised while the node is built is printed as one line with exit
    status 2.
    """
    program = program or sys.argv[0].rsplit('/', 1)[-1]
    if parameters:
        status = handle_command_line(program, summary, parameters, sys.argv)
        if status is not None:
            return status
    # SIGUSR1 prints every thread's Python stack to stderr: the process runner sends it to a
    # node that ignores SIGINT, before SIGKILL, so that a stuck node says where it is stuck.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    # SIGTERM takes Ctrl-C's path. Both handlers are installed before rclpy.init(), which chains
    # its own to them (waking the executor and shutting the context down, as on Ctrl-C).
    signals = _Interrupts()
    rclpy.init(args=sys.argv)
    node = None
    status = 0
    try:
        node = make_node()
        run(node)
    except ParameterError as error:
        print(f'{program}: {error}', file=sys.stderr)
        status = USAGE_ERROR
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        # A KeyboardInterrupt raised while rclpy's C++ code runs Python (the message class's
        # constructor, inside Subscription.take_message) comes out of pybind11 as RuntimeError
        # "Unable to convert call argument '0' to Python object", and rclpy calls on the context
        # its signal handler shut down raise too: after a signal, they are that signal.
        if not signals.received:
            raise
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
    return status


def backend_stats(names: Iterable[str]) -> Dict[str, dict]:
    """The process-wide counters of each named backend that keeps some (``stats()``), for a
    node's report: what it sent, took, refused and why."""
    from rosidl_buffer_py.registry import get_installed_backends
    installed = get_installed_backends()
    return {name: installed[name].stats() for name in sorted(set(names))
            if callable(getattr(installed.get(name), 'stats', None))}
