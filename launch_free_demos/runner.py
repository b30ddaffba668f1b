"""Start node processes with ROS parameters, wait for them, collect their reports.

The one process runner of the project: the demos, the scenarios and the integration tests all
use it. Every process it starts is reaped: on timeout it gets SIGINT, then SIGKILL (after a
SIGUSR1, on which the nodes print their threads' Python stacks to stderr).
"""
import fcntl
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Set

from rosidl_buffer_py.report import REPORT_PREFIX, last_report

#: Executable name -> module run with ``python -m`` (the same names as the console scripts).
#: Any other executable is the path of a Python file, run as a script (the tests' probe node).
NODES = {
    'image_publisher': 'rosidl_buffer_py.nodes.image_publisher',
    'image_subscriber': 'rosidl_buffer_py.nodes.image_subscriber',
    'legacy_image_publisher': 'rosidl_buffer_py.nodes.legacy_image_publisher',
    'legacy_image_subscriber': 'rosidl_buffer_py.nodes.legacy_image_subscriber',
}


def format_parameter(value) -> str:
    """A ``-p name:=value`` value that ROS parses back to the same Python type."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        return str(value)
    return json.dumps(str(value))  # a YAML double-quoted string: '' and '1' stay strings


#: Fast DDS shared-memory transport files: segments ``fastrtps_<16 hex>`` and ports
#: ``fastrtps_port<N>``, each with a lock file ``..._el`` (or ``_sl``) that its owner holds
#: (flock) while it lives; a port also has a ``sem.fastrtps_port<N>_mutex``.
_FASTDDS_LOCK = re.compile(r'^(fastrtps_(?:port\d+|[0-9a-f]{16}))_(?:el|sl)$')
_FASTDDS_PORT = re.compile(r'^fastrtps_port(\d+)$')


def lock_free(path: str) -> bool:
    """True when nobody holds the flock on ``path`` (its owner process is gone)."""
    try:
        with open(path, 'ab') as f:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError:
        return False


def _fastdds_base(name: str) -> str:
    """The segment or port a Fast DDS file belongs to: ``fastrtps_port7411`` for
    ``fastrtps_port7411_el`` and ``sem.fastrtps_port7411_mutex``."""
    name = name[len('sem.'):] if name.startswith('sem.') else name
    for suffix in ('_el', '_sl', '_mutex'):
        if name.endswith(suffix):
            return name[:-len(suffix)]
    return name


def fastdds_files_of(pid: int) -> Set[str]:
    """The Fast DDS segments and ports (base names, see :func:`fastdds_leftovers`) that
    process ``pid`` has mapped or open now: what its exit may leave, told apart from the
    files of other processes on the machine (another test run's SIGKILLed nodes)."""
    names = set()
    try:
        with open(f'/proc/{pid}/maps') as maps:
            names.update(line.split('/dev/shm/', 1)[1].split()[0]
                         for line in maps if '/dev/shm/' in line)
        for fd in os.listdir(f'/proc/{pid}/fd'):
            target = os.readlink(f'/proc/{pid}/fd/{fd}')
            if target.startswith('/dev/shm/'):
                names.add(target[len('/dev/shm/'):].split()[0])
    except (FileNotFoundError, ProcessLookupError):
        pass
    return {_fastdds_base(n) for n in names if 'fastrtps_' in n}


def fastdds_leftovers(since: float, domain_id: int,
                      among: Optional[Set[str]] = None) -> List[str]:
    """Fast DDS files in /dev/shm that processes of this run left behind (created at or after
    ``since``): those whose lock file no living process holds (the rule of Fast DDS's own
    ``fastdds shm clean``), and lock-less port files of the domain's ports (7400 + 250 x
    domain onwards: the caller vouches that the domain is its alone). SIGKILLed participants
    leave them; a participant that exits normally removes its own. ``among``: only the files of
    these segments and ports (see :func:`fastdds_files_of`), when other runs share the machine."""
    names = set(os.listdir('/dev/shm'))

    def recent(name):
        try:
            return os.stat(os.path.join('/dev/shm', name)).st_mtime >= since
        except FileNotFoundError:
            return False

    dead = []
    for name in sorted(names):
        match = _FASTDDS_LOCK.match(name)
        if match and recent(name) and lock_free(os.path.join('/dev/shm', name)):
            base = match.group(1)
            dead += [name, base] + ([f'sem.{base}_mutex'] if base.startswith('fastrtps_port')
                                    else [])
    first = 7400 + 250 * domain_id
    for name in sorted(names):
        match = _FASTDDS_PORT.match(name)
        if (match and first <= int(match.group(1)) < first + 250 and recent(name) and
                not any(f'{name}_{kind}' in names for kind in ('el', 'sl'))):
            dead += [name, f'sem.{name}_mutex']
    return [name for name in dict.fromkeys(dead) if name in names and
            (among is None or _fastdds_base(name) in among)]


def remove_fastdds_leftovers(since: float, domain_id: int) -> List[str]:
    """Remove what :func:`fastdds_leftovers` finds; return the names removed."""
    removed = []
    for name in fastdds_leftovers(since, domain_id):
        try:
            os.remove(os.path.join('/dev/shm', name))
            removed.append(name)
        except FileNotFoundError:
            pass
    return removed


#: How long a node that ignored SIGINT gets to print its stacks (SIGUSR1) before SIGKILL.
STACK_DUMP_SECONDS = 1.0


@dataclass
class NodeProcess:
    """One node process of a scenario."""

    label: str
    executable: str
    parameters: Dict[str, object] = field(default_factory=dict)
    process: Optional[subprocess.Popen] = None
    output: List[str] = field(default_factory=list)
    stderr: List[str] = field(default_factory=list)
    _threads: List[threading.Thread] = field(default_factory=list)
    #: True once the process outlived SIGINT's grace period (it was then dumped and killed).
    stuck: bool = False
    #: Command-line arguments before ``--ros-args`` (the probe's JSON spec).
    arguments: List[str] = field(default_factory=list)
    #: Environment overrides (a scenario's own ``ROS_DOMAIN_ID``).
    env: Dict[str, str] = field(default_factory=dict)
    #: Called from the reader thread with every stdout line; with it, stdin is a pipe too
    #: (:meth:`send`), so that a caller can relay lines between processes.
    on_line: Optional[Callable[['NodeProcess', str], None]] = None
    #: Name the node after ``label`` (``-r __node:=``, which renames every node of the
    #: process: off for the probe, whose nodes are named after its endpoints).
    rename_node: bool = True
    _stdin_lock: threading.Lock = field(default_factory=threading.Lock)

    def command(self) -> List[str]:
        program = ['-m', NODES[self.executable]] if self.executable in NODES else [self.executable]
        args = [sys.executable, *program, *self.arguments, '--ros-args']
        if self.rename_node:
            args += ['-r', f'__node:={self.label}']
        for name, value in self.parameters.items():
            args += ['-p', f'{name}:={format_parameter(value)}']
        return args

    def start(self, echo: bool = False) -> None:
        self.process = subprocess.Popen(
            self.command(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            stdin=subprocess.PIPE if self.on_line else None,
            env=dict(os.environ, PYTHONUNBUFFERED='1', **self.env), start_new_session=True)
        relay = (lambda line: self.on_line(self, line)) if self.on_line else None
        for stream, sink, on_line in ((self.process.stdout, self.output, relay),
                                      (self.process.stderr, self.stderr, None)):
            thread = threading.Thread(target=_pump, args=(stream, sink, self.label, echo,
                                                          on_line), daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self, grace: float = 5.0) -> None:
        """SIGINT, then SIGKILL after ``grace`` seconds; always reaps.

        A node still running after the grace period first gets SIGUSR1 (the nodes dump their
        Python stacks on it, see ``rosidl_buffer_py.nodes.common``): the dump lands in
        ``stderr`` and so in ``Run.diagnostics()``.
        """
        if self.process is None:
            return
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(grace)
            except subprocess.TimeoutExpired:
                self.stuck = True
                self.process.send_signal(signal.SIGUSR1)
                try:
                    self.process.wait(STACK_DUMP_SECONDS)
                except subprocess.TimeoutExpired:
                    pass
                self.process.kill()
                self.process.wait()
        for thread in self._threads:
            thread.join(5)

    def send(self, line: str) -> None:
        """Write one line to the process's stdin (with ``on_line`` only); a process that
        already exited is ignored."""
        with self._stdin_lock:
            try:
                self.process.stdin.write(line + '\n')
                self.process.stdin.flush()
            except (BrokenPipeError, ValueError, OSError):
                pass

    def kill(self) -> None:
        """SIGKILL now (a crashed peer) and reap."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()

    @property
    def report(self) -> Optional[dict]:
        """The process's report (:mod:`rosidl_buffer_py.report`), None before it."""
        return last_report(self.output)


def _pump(stream, sink: List[str], label: str, echo: bool,
          on_line: Optional[Callable[[str], None]] = None) -> None:
    for line in stream:
        sink.append(line.rstrip('\n'))
        if on_line is not None:
            on_line(line.rstrip('\n'))
        if echo and not line.startswith(REPORT_PREFIX):
            print(f'[{label}] {line}', end='', flush=True)


class Run:
    """A set of node processes started together; use as a context manager (always reaped)."""

    def __init__(self, echo: bool = False) -> None:
        self.nodes: Dict[str, NodeProcess] = {}
        self.echo = echo

    def start(self, label: str, executable: str, **parameters) -> NodeProcess:
        node = NodeProcess(label, executable, dict(parameters))
        node.start(self.echo)
        self.nodes[label] = node
        return node

    def add(self, node: NodeProcess) -> NodeProcess:
        """Start a prepared process (arguments, environment, ``on_line``) as one of the run."""
        node.start(self.echo)
        self.nodes[node.label] = node
        return node

    def wait(self, labels: Optional[List[str]] = None, timeout: float = 60.0,
             fail_fast: bool = False) -> bool:
        """Wait until the given (default: all) processes exited; False on timeout.

        With ``fail_fast``, also return False as soon as any process of the run exits with a
        non-zero status (:meth:`failed` names it): a node that failed at start-up is reported
        at once instead of when its peers time out.
        """
        deadline = time.monotonic() + timeout
        waiting = [self.nodes[label].process for label in labels or list(self.nodes)]
        while True:
            if fail_fast and self.failed():
                return False
            if all(process.poll() is not None for process in waiting):
                return True
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            if not fail_fast:
                try:
                    next(p for p in waiting if p.poll() is None).wait(remaining)
                except subprocess.TimeoutExpired:
                    return False
                continue
            time.sleep(min(0.05, remaining))

    def failed(self) -> List[NodeProcess]:
        """The processes that exited with a non-zero status, in start order."""
        return [node for node in self.nodes.values()
                if node.process is not None and node.process.poll() not in (None, 0)]

    def stop_all(self) -> None:
        for node in self.nodes.values():
            node.stop()

    def reports(self) -> Dict[str, Optional[dict]]:
        return {label: node.report for label, node in self.nodes.items()}

    def diagnostics(self) -> str:
        """Exit codes and the tails of stderr (longer for a stuck node), for failure messages."""
        parts = []
        for label, node in self.nodes.items():
            code = node.process.returncode if node.process else None
            stuck = ', stuck: ignored SIGINT, stacks below' if node.stuck else ''
            tail = node.stderr[-80:] if node.stuck else node.stderr[-15:]
            parts.append(f'--- {label} (exit {code}{stuck})\n' + '\n'.join(tail))
        return '\n'.join(parts)

    def __enter__(self) -> 'Run':
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()
