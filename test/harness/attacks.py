"""Processes of our user attacking a demo subscriber, beside a genuine publisher and subscriber.

A genuine ``image_publisher`` (demo backend) sends verifiable frames (counter and CRC32 in each)
to one ``image_subscriber`` accepting ``demo``, in real processes over Fast DDS, while an
attacker, written only from the backend's handover, memory and inbox modules, works against the
subscriber's listener (found, as any process of the user can, in ``/proc/net/unix``):

- ``control``: no attacker;
- ``mappings_first``: before the publisher starts, one connection queues 300 small valid sealed
  segments (enough, before per-process limits, to fill the subscriber's mapping table);
- ``backlog``: before the publisher starts, 65 connections that send nothing (one more than the
  listen backlog);
- ``junk``: 200 connections, each kept full of junk records;
- ``rejected``: what was always refused, on one connection each: garbage records, an unsealed
  and a writable memfd, a file, a pipe, a socket, ``/dev/zero``, two descriptors in one record,
  valid-looking segments and retire records under the genuine publisher's nonce, and fake
  acknowledgments to the publisher's own listener.

``.venv/bin/python test/harness/attacks.py [--frames 300] [--rate 10] [--size 640x480] [CASE ...]``
prints a table: per case, frames received of those published, how many zero-copy, CRC failures,
latency p50 / p99, and what became of the attacker's connections. test_attacks.py runs the same
cases, shorter. ``attacks.py --attacker MODE PID [PUBLISHER_PID]`` is the attacker itself.
"""
import argparse
import fcntl
import json
import os
import re
import select
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

if __package__ in (None, ''):  # run as a file: launch_free_demos (not installed) is the
    sys.path.append(str(Path(__file__).resolve().parents[2]))  # checkout's, after the others

#: The cases, in the order the table lists them.
CASES = ('control', 'mappings_first', 'backlog', 'junk', 'rejected')
#: Cases whose attacker must be in place before the publisher starts.
BEFORE_PUBLISHER = ('mappings_first', 'backlog')
#: How long a case may take beyond its frames (start-up, discovery, the attacker's set-up).
SLACK_SECONDS = 60.0


# --- the attacker --------------------------------------------------------------------------------

def listener_token(pid: int) -> Optional[str]:
    """The demo listener token of process ``pid``, read from /proc/net/unix (None: none yet)."""
    with open('/proc/net/unix') as f:
        for line in f:
            match = re.search(rf'@rbpy_demo/({pid}_[0-9a-f]{{16}})$', line.strip())
            if match:
                return match.group(1)
    return None


def _await_listener(pid: int, seconds: float = 30.0) -> Optional[str]:
    deadline = time.monotonic() + seconds
    token = listener_token(pid)
    while token is None and time.monotonic() < deadline:
        time.sleep(0.05)
        token = listener_token(pid)
    return token


def _connect(token: str) -> Optional[socket.socket]:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    s.setblocking(False)
    try:
        s.connect('\0rbpy_demo/' + token)
        return s
    except OSError:  # the backlog is full, or it is gone
        s.close()
        return None


def _segment(capacity: int = 4096, seals: Optional[int] = None, backed: bool = True) -> int:
    """A memfd laid out as the demo backend makes its segments (sealed unless told)."""
    from demo_buffer_backend import memory
    fd = os.memfd_create('rbpy_demo', os.MFD_ALLOW_SEALING)
    size = memory.HEADER_SIZE + capacity
    if backed:
        os.posix_fallocate(fd, 0, size)
    else:
        os.ftruncate(fd, size)
    os.pwrite(fd, memory.HEADER.pack(memory.MAGIC, capacity, 1, 0, capacity), 0)
    fcntl.fcntl(fd, fcntl.F_ADD_SEALS, memory.SEALS if seals is None else seals)
    return fd


def _handover(segment_id: int, nonce: int = 7, capacity: int = 4096, magic=None) -> bytes:
    from demo_buffer_backend import handover
    return handover.HANDOVER.pack(magic or handover.HANDOVER_MAGIC, nonce, segment_id, 0, capacity)


def _send(s: socket.socket, data: bytes, fds=()) -> bool:
    try:
        if fds:
            socket.send_fds(s, [data], list(fds), socket.MSG_DONTWAIT)
        else:
            s.send(data, socket.MSG_DONTWAIT)
        return True
    except OSError:
        return False


def _fill(s: socket.socket, limit: int = 100_000) -> int:
    """Queue junk records on ``s`` until its queue is full; how many went."""
    sent = 0
    junk = os.urandom(40)
    while sent < limit and _send(s, junk):
        sent += 1
    return sent


def attack(mode: str, target: int, publisher: Optional[int]) -> int:
    """Run one attacker (see the module docstring) against process ``target``: set up, print a
    JSON line, then keep the connections (refilling ``junk``) until stdin closes, and print
    how many of them the subscriber closed."""
    from demo_buffer_backend import handover
    token = _await_listener(target)
    publisher_token = _await_listener(publisher) if publisher else None
    if token is None or (publisher and publisher_token is None):
        print(json.dumps({'error': f'no demo listener of pid {target} or {publisher}'}),
              flush=True)
        return 1
    conns: List[socket.socket] = []
    queued = 0
    if mode == 'mappings_first':
        s = _connect(token)
        conns.append(s)
        for segment_id in range(1, 301):
            fd = _segment()
            queued += _send(s, _handover(segment_id), [fd])
            os.close(fd)
    elif mode == 'backlog':
        for _ in range(65):
            s = _connect(token)
            if s is not None:
                conns.append(s)
    elif mode == 'junk':
        for _ in range(200):
            s = _connect(token)
            if s is not None:
                conns.append(s)
                queued += _fill(s)
    elif mode == 'rejected':
        nonce = int(publisher_token[-16:], 16) if publisher_token else 7
        r, w = os.pipe()
        pair = socket.socketpair()
        cases = [
            (os.urandom(handover.HANDOVER.size), []),
            (_handover(1), [_segment(seals=0)]),
            (_handover(2), [_segment(seals=fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW)]),
            (_handover(3), [os.open(__file__, os.O_RDONLY)]),
            (_handover(4), [r]),
            (_handover(5), [pair[0].fileno()]),
            (_handover(6), [os.open('/dev/zero', os.O_RDONLY)]),
            (_handover(7), [_segment(), _segment()]),
        ]
        cases += [(_handover(i, nonce), [_segment()]) for i in range(1, 9)]  # the publisher's
        cases += [(_handover(i, nonce, 0, handover.RETIRE_MAGIC), []) for i in range(1, 9)]
        for data, fds in cases:
            s = _connect(token)
            if s is not None:
                conns.append(s)
                queued += _send(s, data, fds)
        if publisher_token:  # acknowledgments of takes nobody made, to the publisher
            s = _connect(publisher_token)
            if s is not None:
                conns.append(s)
                for segment_id in range(1, 65):
                    queued += _send(s, handover.REPLY.pack(segment_id, 0, 1))
    else:
        print(json.dumps({'error': f'unknown mode {mode!r}'}), flush=True)
        return 2
    print(json.dumps({'ready': True, 'connections': len(conns), 'queued': queued}), flush=True)
    closed: set = set()
    poller = select.poll()
    for s in conns:
        poller.register(s, select.POLLHUP | select.POLLERR | getattr(select, 'POLLRDHUP', 0x2000))
    while not select.select([sys.stdin], [], [], 0.1)[0]:
        for fd, _ in poller.poll(0):
            if fd not in closed:
                closed.add(fd)
                poller.unregister(fd)
        if mode == 'junk':
            for s in conns:
                if s.fileno() not in closed:
                    _fill(s, 1000)  # kept full
    for fd, _ in poller.poll(0):
        closed.add(fd)
    print(json.dumps({'connections': len(conns), 'closed_by_subscriber': len(closed)}),
          flush=True)
    return 0


class Attacker:
    """An attacker process (this file with ``--attacker``), reaped by :meth:`finish`."""

    def __init__(self, mode: str, target: int, publisher: Optional[int] = None) -> None:
        args = [sys.executable, __file__, '--attacker', mode, str(target)]
        if publisher:
            args.append(str(publisher))
        self.started = time.monotonic()
        self.proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True)
        line = self.proc.stdout.readline()
        self.setup = json.loads(line) if line else {'error': f'exited {self.proc.poll()}'}

    def finish(self) -> dict:
        """Stop it; what became of its connections."""
        try:
            out, _ = self.proc.communicate('', timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        lines = [line for line in out.splitlines() if line.startswith('{')]
        return json.loads(lines[-1]) if lines else {}


# --- a case --------------------------------------------------------------------------------------

@dataclass
class Outcome:
    """What the subscriber got in one case, and what became of the attacker's connections."""

    case: str
    frames: int
    received: int = 0
    zero_copy: int = 0
    crc_failures: int = 0
    p50_ms: float = 0.0
    p99_ms: float = 0.0
    attacker: dict = field(default_factory=dict)
    subscriber_stats: dict = field(default_factory=dict)
    publisher_stats: dict = field(default_factory=dict)
    problems: List[str] = field(default_factory=list)

    def row(self) -> str:
        a = self.attacker
        conns = (f"{a.get('closed_by_subscriber', '-')} of {a.get('connections', '-')}"
                 if a else '-')
        s = self.subscriber_stats
        return (f'| {self.case} | {self.received} of {self.frames} | {self.zero_copy} | '
                f'{self.crc_failures} | {self.p50_ms:.2f} / {self.p99_ms:.2f} | {conns} | '
                f"{s.get('connections_refused', '-')} | {s.get('handovers_rejected', '-')} |")


HEADER = ('| case | frames received | zero-copy | CRC failures | latency p50 / p99 ms | '
          'attacker connections closed by the subscriber | connections refused | '
          'handovers refused |\n|---|---|---|---|---|---|---|---|')


def run_case(case: str, frames: int = 300, rate: float = 10.0, width: int = 640,
             height: int = 480, attacker_seconds: float = 4.5) -> Outcome:
    """Run one case (see the module docstring) and return its outcome. The subscriber stays
    until the publisher is done and ``attacker_seconds`` have passed since the attacker
    started: long enough to refuse the connections it kept waiting
    (``limits.PENDING_SECONDS``); then the attacker says which of its connections the
    subscriber closed, and the subscriber is stopped (Ctrl-C) and reports."""
    from launch_free_demos.runner import Run
    outcome = Outcome(case, frames)
    topic = f'/attack_{case}_{os.getpid()}_{time.monotonic_ns()}'
    timeout = frames / rate + SLACK_SECONDS
    attacker = None
    with Run() as run:
        sub = run.start('sub', 'image_subscriber', topic=topic, acceptable_buffer_backends='demo',
                        timeout_sec=timeout + attacker_seconds, report_period_sec=0.0)
        if _await_listener(sub.process.pid) is None:
            outcome.problems.append('the subscriber never listened')
            return outcome
        if case in BEFORE_PUBLISHER:
            attacker = Attacker(case, sub.process.pid)
        pub = run.start('pub', 'image_publisher', topic=topic, backend='demo', count=frames,
                        rate_hz=rate, width=width, height=height, wait_for_subscribers=1,
                        wait_for_buffer_peers=1, wait_timeout_sec=30.0, linger_sec=2.0)
        if case != 'control' and case not in BEFORE_PUBLISHER:
            attacker = Attacker(case, sub.process.pid, pub.process.pid)
        if attacker is not None and 'error' in attacker.setup:
            outcome.problems.append(f'attacker: {attacker.setup}')
        if not run.wait(['pub'], timeout):
            outcome.problems.append('the publisher did not finish: ' + run.diagnostics()[-2000:])
        if attacker is not None:
            time.sleep(max(0.0, attacker.started + attacker_seconds - time.monotonic()))
            outcome.attacker = {**attacker.setup, **attacker.finish()}
        run.stop_all()
        report = sub.report or {}
        if not report:
            outcome.problems.append('the subscriber did not report: ' + run.diagnostics()[-2000:])
        outcome.received = report.get('distinct', 0)
        outcome.zero_copy = report.get('backends', {}).get('demo', 0)
        outcome.crc_failures = report.get('checksum_failures', 0)
        latency = report.get('latency_ms', {})
        outcome.p50_ms, outcome.p99_ms = latency.get('p50', 0.0), latency.get('p99', 0.0)
        outcome.subscriber_stats = report.get('backend_stats', {}).get('demo', {})
        outcome.publisher_stats = (pub.report or {}).get('backend_stats', {}).get('demo', {})
    return outcome


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('cases', nargs='*', metavar='CASE', help=', '.join(CASES))
    parser.add_argument('--frames', type=int, default=300)
    parser.add_argument('--rate', type=float, default=10.0)
    parser.add_argument('--size', default='640x480', help='WIDTHxHEIGHT of the rgb8 frames')
    parser.add_argument('--attacker', nargs='+', metavar='MODE PID', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.attacker:
        mode, target, *publisher = args.attacker
        return attack(mode, int(target), int(publisher[0]) if publisher else None)
    unknown = sorted(set(args.cases) - set(CASES))
    if unknown:
        parser.error(f'unknown case(s) {", ".join(unknown)}; the cases: {", ".join(CASES)}')
    width, height = (int(n) for n in args.size.split('x'))
    print(f'{args.frames} frames {width}x{height} rgb8 at {args.rate} Hz, demo publisher to one '
          'demo subscriber')
    print(HEADER, flush=True)
    for case in args.cases or CASES:
        outcome = run_case(case, args.frames, args.rate, width, height)
        print(outcome.row(), flush=True)
        for problem in outcome.problems:
            print(f'  {case}: {problem}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
