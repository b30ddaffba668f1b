"""The benchmarks' node processes, measured from outside: CPU time (their CPU clock), peak
resident memory, reaping with ``os.wait4`` (their rusage), the subscribers' progress lines; the
peer transports' nodes; CPU steal; a ROS_DOMAIN_ID of the benchmark's own.

The suite (:mod:`.suite`), :mod:`.mixed` and :mod:`.record` measure with these.
"""
import ctypes
import os
import re
import signal
import sys
import time
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

from launch_free_demos.domains import claim_domain_ids
from launch_free_demos.runner import STACK_DUMP_SECONDS, NodeProcess, Run

#: A peer transport's node (``launch_free_demos/bench/peers``) -> its module.
PEER_NODES = {'iceoryx2_peer': 'launch_free_demos.bench.peers.iceoryx2_peer',
              'zenoh_peer': 'launch_free_demos.bench.peers.zenoh_peer'}
#: The subscribers' progress line: log time, frames received, distinct frames.
LOG_RECEIVED = re.compile(r'\[(\d+\.\d+)\] \[[^\]]*\]: received (\d+) \((\d+) distinct\)')


# --- CPU time of another process ------------------------------------------------------------

class _Timespec(ctypes.Structure):
    _fields_ = [('tv_sec', ctypes.c_long), ('tv_nsec', ctypes.c_long)]


try:
    _LIBC = ctypes.CDLL(None, use_errno=True)
    _LIBC.clock_getcpuclockid.argtypes = [ctypes.c_int, ctypes.POINTER(ctypes.c_int)]
    _LIBC.clock_gettime.argtypes = [ctypes.c_int, ctypes.POINTER(_Timespec)]
except (OSError, AttributeError):  # pragma: no cover - not glibc: /proc ticks instead
    _LIBC = None
_CLK_TCK = os.sysconf('SC_CLK_TCK')


def cpu_clock_of(pid: int) -> Optional[int]:
    """The process-wide CPU-time clock of ``pid`` (all its threads), or None."""
    if _LIBC is None:
        return None
    clock = ctypes.c_int()
    return clock.value if _LIBC.clock_getcpuclockid(pid, ctypes.byref(clock)) == 0 else None


def cpu_seconds(pid: int, clock: Optional[int]) -> Optional[float]:
    """CPU time (user + system) of a live process so far, or None once it is gone."""
    if clock is not None:
        ts = _Timespec()
        if _LIBC.clock_gettime(clock, ctypes.byref(ts)) == 0:
            return ts.tv_sec + ts.tv_nsec * 1e-9
        return None
    try:  # fallback: utime + stime in clock ticks
        with open(f'/proc/{pid}/stat') as f:
            fields = f.read().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / _CLK_TCK
    except (OSError, IndexError, ValueError):
        return None


# --- node processes reaped with os.wait4 (their rusage) -------------------------------------

@dataclass
class MeasuredNode(NodeProcess):
    """A runner NodeProcess that is reaped with ``os.wait4`` (keeping its rusage), samples its
    CPU clock and parses the subscriber's progress lines."""

    rusage: Optional[object] = None
    hwm_kib: Optional[int] = None
    clock: Optional[int] = None
    marks: List[Tuple[float, int]] = field(default_factory=list)  # (wall time, distinct)
    _log_index: int = 0

    def start(self, echo: bool = False) -> None:
        super().start(echo)
        self.clock = cpu_clock_of(self.process.pid)

    @property
    def reaped(self) -> bool:
        return self.process is None or self.process.returncode is not None

    def cpu(self) -> Optional[float]:
        return None if self.reaped else cpu_seconds(self.process.pid, self.clock)

    def read_peak_rss(self) -> None:
        """Note VmHWM (peak resident set) from /proc while the process lives. (Not ru_maxrss:
        after a vfork + exec it also counts the parent's resident set at the fork.)"""
        if self.reaped:
            return
        try:
            with open(f'/proc/{self.process.pid}/status') as f:
                for line in f:
                    if line.startswith('VmHWM:'):
                        self.hwm_kib = max(self.hwm_kib or 0, int(line.split()[1]))
                        return
        except (OSError, ValueError, IndexError):
            pass

    def try_reap(self, block: bool = False) -> bool:
        """Reap the process if it exited (never through Popen: that would lose the rusage)."""
        if self.reaped:
            return True
        try:
            pid, status, rusage = os.wait4(self.process.pid, 0 if block else os.WNOHANG)
        except ChildProcessError:  # reaped elsewhere: no rusage
            self.process.returncode = -1
            return True
        if pid == 0:
            return False
        self.rusage = rusage
        self.process.returncode = os.waitstatus_to_exitcode(status)
        return True

    def _signal(self, sig: int) -> None:
        if not self.reaped:  # an unreaped pid (even a zombie) is still ours
            os.kill(self.process.pid, sig)

    def stop(self, grace: float = 5.0) -> None:
        """SIGINT, then (as NodeProcess.stop) SIGUSR1 for a stack dump and SIGKILL after
        ``grace`` seconds; always reaps."""
        if self.process is None:
            return
        if not self.try_reap():
            self._signal(signal.SIGINT)
            if not self._reaped_within(grace):
                self.stuck = True
                self._signal(signal.SIGUSR1)  # the nodes print every thread's stack
                if not self._reaped_within(STACK_DUMP_SECONDS):
                    self._signal(signal.SIGKILL)
                    self.try_reap(block=True)
        for thread in self._threads:
            thread.join(5)

    def _reaped_within(self, seconds: float) -> bool:
        deadline = time.monotonic() + seconds
        while not self.try_reap() and time.monotonic() < deadline:
            time.sleep(0.02)
        return self.reaped

    def kill(self) -> None:
        self._signal(signal.SIGKILL)
        self.try_reap(block=True)

    def read_log(self) -> None:
        lines = self.stderr[self._log_index:]
        self._log_index += len(lines)
        for line in lines:
            match = LOG_RECEIVED.search(line)
            if match:
                self.marks.append((float(match.group(1)), int(match.group(3))))

    def distinct_now(self) -> int:
        return self.marks[-1][1] if self.marks else 0

    @property
    def peak_rss_mib(self) -> Optional[float]:
        return self.hwm_kib / 1024 if self.hwm_kib is not None else None


@dataclass
class PeerNode(MeasuredNode):
    """A peer node (``launch_free_demos/bench/peers``), measured as the ROS nodes are; its command
    line is its own: ``--name=value`` for every parameter."""

    def command(self) -> List[str]:
        return [sys.executable, '-m', PEER_NODES[self.executable], f'--label={self.label}',
                *(f'--{name}={value}' for name, value in self.parameters.items())]


class MeasuredRun(Run):
    def start(self, label: str, executable: str, **parameters) -> MeasuredNode:
        kind = PeerNode if executable in PEER_NODES else MeasuredNode
        node = kind(label, executable, dict(parameters))
        self.nodes[label] = node  # registered first: reaped by __exit__ whatever happens
        node.start(self.echo)
        return node


# --- CPU steal: time a hypervisor gave this machine's CPUs to other guests ----------------

def _cpu_times() -> Optional[Tuple[int, int]]:
    """(steal, total) jiffies of all CPUs from /proc/stat, or None where unavailable."""
    try:
        with open('/proc/stat') as f:
            fields = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    if len(fields) < 8:
        return None
    return fields[7], sum(fields[:8])  # user nice system idle iowait irq softirq steal


class StealMeter:
    """The share of CPU time stolen by the hypervisor since the meter was made."""

    def __init__(self) -> None:
        self._start = _cpu_times()

    def fraction(self) -> Optional[float]:
        end = _cpu_times()
        if self._start is None or end is None or end[1] <= self._start[1]:
            return None
        return (end[0] - self._start[0]) / (end[1] - self._start[1])


# --- a domain of the benchmark's own --------------------------------------------------------

def claim_domain_id() -> bool:
    """Take a ROS_DOMAIN_ID nobody else on the machine holds (:mod:`launch_free_demos.domains`),
    unless one is set already; True when this process took one (then it alone uses it)."""
    if os.environ.get('ROS_DOMAIN_ID'):
        return False
    os.environ['ROS_DOMAIN_ID'] = str(claim_domain_ids()[0])
    return True
