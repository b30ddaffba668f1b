"""probe_node: host several publishers and subscriptions, run a timeline, report what was seen.

The equivalence suite (:mod:`harness.equivalence`) runs one scenario as two or three
probe processes. A probe takes one JSON spec as its first argument::

    python test/harness/probe_node.py '{"variant": "ours", "endpoints": {...}, "steps": [...]}'

- ``variant``: ``"stock"`` makes every endpoint a plain rclpy one and never imports this
  package (the oracle); ``"ours"`` makes endpoints whose ``impl`` is ``"ours"`` buffer-aware
  (:func:`rosidl_buffer_py.create_publisher` / ``create_subscription``).
- ``endpoints``: id -> ``{"kind": "pub"|"sub", "impl": "ours"|"stock", "topic", "qos": {...},
  "payload": "cpu"|"demo" (pub), "accept": "cpu"|"demo"|"any" (sub), "events": true (register a
  callback for every QoS event; false leaves rclpy's default ones, which log incompatible QoS)}``.
  Each endpoint has its own node, ``eq_<id>``, so the log lines name the endpoint.
- ``steps``: run in order; each waits by spinning the executor (one thread, no sleeps):
  ``create``/``destroy`` (ids), ``wait_matched`` (ids, count, timeout), ``publish`` (ids, n,
  rate, first_seq: each publisher publishes n messages, in turn), ``acked`` (ids, timeout:
  ``wait_for_all_acked``), ``wait_received`` (ids and count, or counts: id -> count; timeout),
  ``drain`` (quiet, timeout: until no subscription here received anything for ``quiet`` s),
  ``sleep`` (s), ``phase`` (name: tags what is received and every event from now on),
  ``signal`` (name: a ``SIGNAL <name>`` line on stdout, which the suite relays to the other
  probes of the scenario), ``await`` (names, timeout: signals relayed on stdin). Every signal,
  sent or relayed, also starts a phase of that name.

Every message carries ``"<publisher id> <seq> <crc32 of data>"`` in ``header.frame_id`` and its
seq in the first 8 bytes of ``data``; subscriptions check both. The report (a ``REPORT`` JSON
line on stdout at exit) lists, per endpoint, the messages received ``[publisher, seq, phase,
backend, ok]``, the QoS events ``[type, phase, fields]``, whether its node lists it, what
destroying it through its node and ``wait_for_all_acked`` returned; and the steps that timed out
or raised. Log lines (incompatible QoS warnings) are on stderr, which
the suite reads.
"""
import array
import json
import sys
import threading
import time
import zlib
from pathlib import Path
from typing import Dict, List, Optional

import numpy
import rclpy
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import InvalidHandle
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import (
    DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy)
from sensor_msgs.msg import Image

from rosidl_buffer_py.nodes.common import run_node
from rosidl_buffer_py.report import print_report

#: What the process runner starts (``NodeProcess(label, PROBE_NODE, ...)``): this file.
PROBE_NODE = str(Path(__file__).resolve())
SIGNAL_PREFIX = 'SIGNAL '
#: Payload bytes per message.
PAYLOAD_BYTES = 2048
_PATTERN = numpy.random.default_rng(11).integers(0, 256, PAYLOAD_BYTES, dtype=numpy.uint8)

_RELIABILITY = {'reliable': ReliabilityPolicy.RELIABLE,
                'best_effort': ReliabilityPolicy.BEST_EFFORT}
_DURABILITY = {'volatile': DurabilityPolicy.VOLATILE,
               'transient_local': DurabilityPolicy.TRANSIENT_LOCAL}
_HISTORY = {'keep_last': HistoryPolicy.KEEP_LAST, 'keep_all': HistoryPolicy.KEEP_ALL}
_LIVELINESS = {'automatic': LivelinessPolicy.AUTOMATIC,
               'manual_by_topic': LivelinessPolicy.MANUAL_BY_TOPIC}


def qos_profile(spec: dict) -> QoSProfile:
    """A QoSProfile from ``{"reliability", "durability", "history", "depth", "deadline",
    "liveliness", "lease"}`` (seconds; every key optional: rclpy's defaults, depth 10)."""
    qos = QoSProfile(history=_HISTORY[spec.get('history', 'keep_last')],
                     depth=spec.get('depth', 10),
                     reliability=_RELIABILITY[spec.get('reliability', 'reliable')],
                     durability=_DURABILITY[spec.get('durability', 'volatile')],
                     liveliness=_LIVELINESS[spec.get('liveliness', 'automatic')])
    if 'deadline' in spec:
        qos.deadline = Duration(seconds=spec['deadline'])
    if 'lease' in spec:
        qos.liveliness_lease_duration = Duration(seconds=spec['lease'])
    return qos


def frame(publisher_id: str, seq: int) -> tuple:
    """The payload of message ``seq`` of ``publisher_id`` and its frame_id label."""
    data = _PATTERN.copy()
    data[:8] = numpy.frombuffer(seq.to_bytes(8, 'little'), dtype=numpy.uint8)
    data[8:16] = numpy.frombuffer(zlib.crc32(publisher_id.encode()).to_bytes(8, 'little'),
                                  dtype=numpy.uint8)
    return data, f'{publisher_id} {seq} {zlib.crc32(data)}'


class Endpoint:
    """One publisher or subscription of the probe, on its own node, and what it observed."""

    def __init__(self, probe: 'Probe', endpoint_id: str, spec: dict) -> None:
        self.probe = probe
        self.id = endpoint_id
        self.spec = spec
        self.kind = spec['kind']
        self.ours = probe.ours and spec.get('impl', 'ours') == 'ours'
        self.node = None
        self.entity = None
        self.next_seq = 0
        self.messages: List[list] = []
        self.events: List[list] = []
        self.destroy_results: List[bool] = []
        self.acked: List[bool] = []
        self.owned: List[bool] = []
        self.last_received = 0.0

    # lifecycle ---------------------------------------------------------------------------

    def create(self) -> None:
        if self.node is None:
            self.node = rclpy.create_node(f'eq_{self.id}')
            self.probe.executor.add_node(self.node)
        qos = qos_profile(self.spec.get('qos', {}))
        topic = self.spec['topic']
        if self.kind == 'pub':
            callbacks = self._publisher_callbacks()
            if self.ours:
                self.entity = self.probe.rbp.create_publisher(
                    self.node, Image, topic, qos, event_callbacks=callbacks)
            else:
                self.entity = self.node.create_publisher(Image, topic, qos,
                                                         event_callbacks=callbacks)
        else:
            callbacks = self._subscription_callbacks()
            if self.ours:
                self.entity = self.probe.rbp.create_subscription(
                    self.node, Image, topic, self.on_message, qos, event_callbacks=callbacks,
                    acceptable_buffer_backends=self.spec.get('accept', 'cpu'))
            else:
                self.entity = self.node.create_subscription(Image, topic, self.on_message, qos,
                                                            event_callbacks=callbacks)
        owners = self.node.publishers if self.kind == 'pub' else self.node.subscriptions
        self.owned.append(any(e is self.entity for e in owners))

    def destroy(self) -> None:
        """Destroy through the node, as a user would; a buffer-aware endpoint that the node
        does not own (recorded as False) is then destroyed by its own ``destroy()``."""
        if self.entity is None:
            return
        if self.kind == 'pub':
            done = self.node.destroy_publisher(self.entity)
        else:
            done = self.node.destroy_subscription(self.entity)
        self.destroy_results.append(bool(done))
        if not done and hasattr(self.entity, 'destroy'):
            self.entity.destroy()
        self.entity = None

    # traffic -----------------------------------------------------------------------------

    def publish_next(self) -> None:
        data, label = frame(self.id, self.next_seq)
        msg = Image(height=1, width=PAYLOAD_BYTES, encoding='mono8', step=PAYLOAD_BYTES)
        msg.header.frame_id = label
        if self.ours and self.spec.get('payload', 'cpu') == 'demo':
            buf = self.probe.demo.DemoBuffer.allocate(PAYLOAD_BYTES)
            numpy.asarray(buf)[:] = data
            msg.data = buf
        else:
            msg.data = array.array('B', data.tobytes())
        self.entity.publish(msg)
        self.next_seq += 1

    def on_message(self, msg) -> None:
        self.last_received = time.monotonic()
        payload = msg.data
        backend = getattr(payload, 'backend_type', 'cpu') or 'cpu'
        try:
            publisher_id, seq, crc = msg.header.frame_id.split(' ')
            seq, crc = int(seq), int(crc)
        except ValueError:
            self.messages.append(['?', -1, self.probe.phase, backend, False])
            return
        view = memoryview(payload).cast('B') if not isinstance(payload, bytes) else payload
        ok = (zlib.crc32(view) == crc and len(view) >= 8 and
              int.from_bytes(bytes(view[:8]), 'little') == seq)
        self.messages.append([publisher_id, seq, self.probe.phase, backend, ok])

    # events ------------------------------------------------------------------------------

    def _record(self, kind: str):
        def callback(info) -> None:
            fields = {name: getattr(info, name) for name in (
                'total_count', 'total_count_change', 'current_count', 'current_count_change',
                'alive_count', 'not_alive_count', 'last_policy_kind') if hasattr(info, name)}
            fields = {k: int(v) if not isinstance(v, int) else v for k, v in fields.items()}
            self.events.append([kind, self.probe.phase, fields])
        return callback

    def _publisher_callbacks(self) -> Optional[PublisherEventCallbacks]:
        if not self.spec.get('events', True):
            return None  # rclpy's defaults: incompatible QoS is logged
        return PublisherEventCallbacks(
            deadline=self._record('deadline'), liveliness=self._record('liveliness'),
            incompatible_qos=self._record('incompatible_qos'), matched=self._record('matched'))

    def _subscription_callbacks(self) -> Optional[SubscriptionEventCallbacks]:
        if not self.spec.get('events', True):
            return None
        return SubscriptionEventCallbacks(
            deadline=self._record('deadline'), liveliness=self._record('liveliness'),
            incompatible_qos=self._record('incompatible_qos'),
            message_lost=self._record('message_lost'), matched=self._record('matched'))

    def matched(self) -> int:
        if self.entity is None:
            return 0
        if self.kind == 'pub':
            return self.entity.get_subscription_count()
        return self.entity.get_publisher_count()

    def report(self) -> dict:
        return {'kind': self.kind, 'ours': self.ours, 'messages': self.messages,
                'events': self.events, 'destroy_results': self.destroy_results,
                'acked': self.acked, 'owned': self.owned,
                'published': self.next_seq if self.kind == 'pub' else None}


class Probe:
    """The probe process: endpoints, one executor, the timeline, signals from stdin."""

    def __init__(self, spec: dict) -> None:
        self.spec = spec
        self.ours = spec.get('variant', 'ours') == 'ours'
        self.rbp = self.demo = None
        if self.ours:
            import demo_buffer_backend
            import rosidl_buffer_py
            self.rbp, self.demo = rosidl_buffer_py, demo_buffer_backend
        self.executor = SingleThreadedExecutor()
        self.phase = 'start'
        self.timeouts: List[str] = []
        self.errors: List[str] = []
        self.signals: Dict[str, float] = {}
        self._signals_lock = threading.Lock()
        self._wake_node = rclpy.create_node('eq_probe_wake')
        self._wake = self._wake_node.create_guard_condition(lambda: None)
        self.executor.add_node(self._wake_node)
        self.endpoints = {eid: Endpoint(self, eid, e) for eid, e in spec['endpoints'].items()}
        self.started = time.monotonic()
        threading.Thread(target=self._read_stdin, daemon=True).start()

    def _read_stdin(self) -> None:
        for line in sys.stdin:
            name = line.strip()
            if name:
                with self._signals_lock:
                    self.signals.setdefault(name, time.monotonic())
                self.phase = name  # what happens from now on happens after that signal
                try:
                    self._wake.trigger()
                except InvalidHandle:  # a signal relayed while the probe tears down
                    return

    def spin_until(self, condition, timeout: float, what: str) -> bool:
        """Spin until ``condition()``; False (and the step recorded as timed out) after
        ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while not condition():
            left = deadline - time.monotonic()
            if left <= 0:
                self.timeouts.append(f'{what} (phase {self.phase})')
                return False
            self.executor.spin_once(timeout_sec=min(left, 0.1))
        return True

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            self.executor.spin_once(timeout_sec=left)

    def run(self) -> None:
        for step in self.spec['steps']:
            try:
                getattr(self, 'step_' + step['op'])(step)
            except Exception as error:  # noqa: B902 (an endpoint that raises is an outcome)
                self.errors.append(f'{step["op"]} {step.get("ids", "")}: '
                                   f'{type(error).__name__}: {error}')

    # steps -------------------------------------------------------------------------------

    def step_create(self, step: dict) -> None:
        for eid in step['ids']:
            self.endpoints[eid].create()

    def step_destroy(self, step: dict) -> None:
        for eid in step['ids']:
            self.endpoints[eid].destroy()

    def step_wait_matched(self, step: dict) -> None:
        """Until the endpoints matched ``count`` peers: the bound (30 s) only ends a run whose
        discovery never completes (a stock-only graph once took over 10 s, under load)."""
        ends = [self.endpoints[eid] for eid in step['ids']]
        count = step.get('count', 1)
        self.spin_until(lambda: all(e.matched() >= count for e in ends),
                        step.get('timeout', 30.0), f'wait_matched {step["ids"]} >= {count}')

    def step_publish(self, step: dict) -> None:
        ends = [self.endpoints[eid] for eid in step['ids']]
        if 'first_seq' in step:  # a restarted publisher process goes on where it stopped
            for endpoint in ends:
                endpoint.next_seq = step['first_seq']
        period = 1.0 / step.get('rate', 50.0)
        start = time.monotonic()
        for i in range(step['n']):
            for k, endpoint in enumerate(ends):
                # spread over the period: a burst from every publisher at once overruns a
                # depth-1 reader (one instance per topic) whatever the endpoints are
                self.spin_for(start + (i + k / len(ends)) * period - time.monotonic())
                endpoint.publish_next()

    def step_acked(self, step: dict) -> None:
        for eid in step['ids']:
            endpoint = self.endpoints[eid]
            endpoint.acked.append(bool(endpoint.entity.wait_for_all_acked(
                Duration(seconds=step.get('timeout', 2.0)))))

    def step_wait_received(self, step: dict) -> None:
        counts = step.get('counts') or {eid: step['count'] for eid in step['ids']}
        ends = {self.endpoints[eid]: count for eid, count in counts.items()}
        self.spin_until(lambda: all(len(e.messages) >= n for e, n in ends.items()),
                        step.get('timeout', 5.0), f'wait_received {counts}')

    def step_drain(self, step: dict) -> None:
        quiet = step.get('quiet', 0.3)
        subs = [e for e in self.endpoints.values() if e.kind == 'sub']
        begin = time.monotonic()

        def calm() -> bool:
            last = max([begin] + [e.last_received for e in subs])
            return time.monotonic() - last >= quiet
        self.spin_until(calm, step.get('timeout', 5.0), 'drain')

    def step_sleep(self, step: dict) -> None:
        self.spin_for(step['s'])

    def step_phase(self, step: dict) -> None:
        self.phase = step['name']

    def step_signal(self, step: dict) -> None:
        self.phase = step['name']
        print(SIGNAL_PREFIX + step['name'], flush=True)

    def step_await(self, step: dict) -> None:
        names = step['names']

        def arrived() -> bool:
            with self._signals_lock:
                return all(name in self.signals for name in names)
        self.spin_until(arrived, step.get('timeout', 30.0), f'await {names}')
        if step.get('phase', True):
            self.phase = names[-1]

    # report and teardown (run_node's protocol) -------------------------------------------

    def finish(self) -> None:
        print_report({'endpoints': {eid: e.report() for eid, e in self.endpoints.items()},
                      'timeouts': self.timeouts, 'errors': self.errors,
                      'seconds': round(time.monotonic() - self.started, 3)})

    def destroy_node(self) -> None:
        for endpoint in self.endpoints.values():
            if endpoint.node is not None:
                endpoint.node.destroy_node()
        self._wake_node.destroy_node()
        self.executor.shutdown()


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    spec = json.loads(argv[0])
    return run_node(lambda: Probe(spec), Probe.run)


if __name__ == '__main__':
    sys.exit(main())
