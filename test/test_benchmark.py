"""The benchmark suite runs end to end and writes its table and plot (no timing asserts).

Runs README's ``./dev bench`` in its smoke mode (the quick mode's code with the fewest
frames and sizes that still fill every table) in a subprocess, inside this test session's ROS
domain (see conftest.py), as CI does. Outside the ./dev venv (under ``colcon
test``) the same module runs with the interpreter under test, as ``./dev`` would exec it.
"""
import contextlib
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from harness.installed import in_dev_venv
from launch_free_demos.bench import suite as benchmark
from launch_free_demos.bench.measured import StealMeter
from launch_free_demos.bench.suite import (
    ALL_ROWS, BIG, CPU, FANOUT_TRANSPORTS, MEMCPY, MODES, PEER_TABLE_OURS, PEERS, STOCK, Result,
    measure, median_run, paired_ratios, peer_scratch, peer_version, skipped_note)

ROOT = Path(__file__).resolve().parent.parent
PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


def table_rows(text: str):
    """The cells of every markdown table row that is not a header separator."""
    rows = []
    for line in text.splitlines():
        if line.startswith('|') and not line.startswith('|---'):
            rows.append([cell.strip() for cell in line.strip('|').split('|')])
    return rows


@pytest.fixture(scope='module')
def smoke_run(tmp_path_factory):
    out = tmp_path_factory.mktemp('benchmark')
    command = [str(ROOT / 'dev'), 'bench'] if in_dev_venv() else \
        [sys.executable, '-m', 'launch_free_demos.bench.suite']
    completed = subprocess.run(  # README's command; --smoke: the quick mode's code, fewer frames
        command + ['--smoke', '--out', str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=300, env=dict(os.environ))
    assert completed.returncode == 0, completed.stderr[-3000:]
    return out, completed.stdout


def test_markdown_has_every_transport_row_for_every_payload(smoke_run):
    out, stdout = smoke_run
    saved = (out / 'benchmark.md').read_text()
    assert stdout.split('Wrote ')[0].strip() in saved  # stdout and the file agree
    rows = table_rows(saved)
    for payload in MODES['smoke'].payloads:
        found = {cells[1] for cells in rows if cells[0] == payload}
        assert set(ALL_ROWS) <= found, (payload, found)
    for payload in MODES['smoke'].fanout_payloads:
        for transport in FANOUT_TRANSPORTS:
            counts = {cells[2] for cells in rows if cells[:2] == [payload, transport]}
            assert {str(n) for n in MODES['smoke'].fanout_subscribers} <= counts
    assert '## Target checks' in saved
    assert 'latency CPU path / stock' in saved


def test_mixed_graph_latency_table_and_its_targets(smoke_run):
    """Issue #19's timing targets in the suite: the demo subscriber alone, beside a plain one,
    and the stock graph, at each payload of the mode, with the two target checks."""
    saved = (smoke_run[0] / 'benchmark.md').read_text()
    assert '## Mixed graph latency' in saved
    latency = saved.split('## Mixed graph latency')[1]
    graphs = [cells[0] for cells in table_rows(latency)]
    assert graphs[:4] == ['graph', 'pure', 'mixed', 'stock mixed'], latency
    for payload in MODES['smoke'].mixed_latency_payloads:
        assert f'mixed graph at {payload}: demo p99 beside a plain subscriber / alone' in saved
        assert f"mixed graph at {payload}: demo p99 / the plain subscriber's p99" in saved
    full = MODES['full']
    assert full.mixed_latency_payloads == ['640x480 rgb8', '1920x1080 rgb8', BIG]
    assert full.churn_seconds > 0


def test_peers_table_shows_installed_peers_and_skips_absent_ones(smoke_run):
    """The peers table: our rows (with a time to a numpy view) for the quick payloads; each
    peer's rows when it is installed, else the note that says how to install it (CI has
    none)."""
    out, _ = smoke_run
    saved = (out / 'benchmark.md').read_text()
    assert '## Peers side by side' in saved
    section = saved.split('## Peers side by side', 1)[1].split('\n## ', 1)[0]
    assert f'Produced by `./dev bench --smoke --out {out}`' in section
    rows = {(cells[0], cells[1]): cells for cells in table_rows(section)}
    for payload in MODES['smoke'].payloads:
        for label in PEER_TABLE_OURS:
            cells = rows[(payload, label)]
            float(cells[5])  # time to a numpy view, ms
            frames = MODES['smoke'].frames
            assert cells[6] == f'{frames}/{frames}' or cells[6].endswith('!'), cells
        assert (payload, MEMCPY) in rows
    for t in PEERS:
        shown = {payload for payload, label in rows if label == t.label}
        if peer_version(t) is None:
            assert skipped_note(t) in section and not shown
        else:
            assert shown == set(MODES['smoke'].peer_payloads), shown


def test_plot_is_a_png(smoke_run):
    out, _ = smoke_run
    png = out / 'benchmark.png'
    data = png.read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 10_000
    assert '![benchmark plot](benchmark.png)' in (out / 'benchmark.md').read_text()


def test_modes_cover_every_transport_and_the_quick_mode_stays_small():
    quick = MODES['quick']
    assert quick.frames <= MODES['full'].frames and len(quick.rates) <= 3
    for mode in MODES.values():
        assert mode.payloads and mode.rate_payloads and mode.fanout_payloads
        assert 1 in mode.fanout_subscribers and len(mode.fanout_subscribers) >= 2


def _run(p50, complete=True, pub_cpu_ms=None):
    return Result(STOCK, '1 KiB', 1, 30, 5.0, complete=complete,
                  latency={} if p50 is None else {'p50': p50}, pub_cpu_ms=pub_cpu_ms)


def test_median_run_takes_the_middle_latency_of_the_complete_runs():
    runs = [_run(3.0), _run(1.0), _run(2.0)]
    assert median_run(runs) is runs[2]
    runs.append(_run(0.5, complete=False))  # lost frames: never the row shown
    assert median_run(runs) is runs[2]
    assert median_run([_run(4.0), _run(1.0), _run(3.0), _run(2.0)]).latency['p50'] == 2.0
    only_failed = [_run(None, complete=False)]
    assert median_run(only_failed) is only_failed[0]


def test_paired_ratios_compare_cpu_path_and_stock_round_by_round():
    rounds = {(CPU, '1 KiB'): [_run(1.1, pub_cpu_ms=2.0), _run(3.0), _run(1.0)],
              (STOCK, '1 KiB'): [_run(1.0, pub_cpu_ms=4.0), _run(2.0)]}
    assert paired_ratios(rounds, '1 KiB', lambda r: r.latency.get('p50')) == \
        pytest.approx([1.1, 1.5])  # the unpaired third CPU-path round is left out
    assert paired_ratios(rounds, '1 KiB', lambda r: r.pub_cpu_ms) == [0.5]  # None skipped
    assert paired_ratios(rounds, '1 MiB', lambda r: r.pub_cpu_ms) == []


def test_steal_meter_reads_a_share_of_this_machines_cpu_time():
    meter = StealMeter()
    deadline = time.monotonic() + 0.3
    while time.monotonic() < deadline:  # let the kernel's jiffies move
        pass
    fraction = meter.fraction()
    if not Path('/proc/stat').exists():
        assert fraction is None
    else:
        assert fraction is not None and 0.0 <= fraction <= 1.0, fraction


def test_a_node_that_ignores_sigint_is_killed_and_reaped():
    """The benchmark's nodes are reaped with os.wait4 (for their rusage); one that does not
    stop on SIGINT gets SIGUSR1 (stack dump), then SIGKILL, and is reaped all the same."""
    import signal

    from launch_free_demos.bench.measured import MeasuredRun
    with MeasuredRun() as run:
        node = run.start('frozen', 'image_subscriber', topic='/frozen', timeout_sec=60.0)
        time.sleep(1.0)
        os.kill(node.process.pid, signal.SIGSTOP)  # deaf to SIGINT and SIGUSR1 from now on
        started = time.monotonic()
        node.stop(grace=0.5)
        assert node.reaped and node.stuck
        assert node.process.returncode == -signal.SIGKILL
        assert time.monotonic() - started < 10


def test_bench_mixed_prints_cpu_per_frame_of_every_process_of_every_graph():
    """README's ./dev bench mixed, small and short: every graph's row, a figure for every
    process it has (every subscriber checks every frame's counter and CRC32)."""
    command = [str(ROOT / 'dev'), 'bench', 'mixed'] if in_dev_venv() else \
        [sys.executable, '-m', 'launch_free_demos.bench.mixed']
    completed = subprocess.run(
        command + ['--payload', '64x48', '--frames', '1', '--extra', '2', '--rounds', '1'],
        cwd=ROOT, capture_output=True, text=True, timeout=300, env=dict(os.environ))
    assert completed.returncode == 0, completed.stdout + completed.stderr
    rows = {row[0]: row[1:] for row in table_rows(completed.stdout)}
    assert set(rows) == {'graph', 'pure', 'mixed', 'neighbour', 'stock', 'stock mixed'}, \
        completed.stdout
    present = {graph: [cell != '-' for cell in cells] for graph, cells in rows.items()
               if graph != 'graph'}
    assert present == {'pure': [True, False, True], 'mixed': [True, True, True],
                       'neighbour': [True, True, True], 'stock': [False, True, True],
                       'stock mixed': [True, True, True]}, completed.stdout
    for graph, cells in rows.items():
        for cell in cells:
            if graph != 'graph' and cell != '-':
                float(cell.split()[0])  # a number of ms (it may be negative for so few frames)


def test_bench_mixed_threads_splits_the_demo_subscriber_by_thread():
    """./dev bench mixed --threads, small and short, with the publisher's two-subscriber graph:
    a row per graph, the executor's thread and Fast DDS's receive threads among the columns,
    each cell CPU ms / wake-ups per frame."""
    completed = subprocess.run(
        [sys.executable, '-m', 'launch_free_demos.bench.mixed', '--threads', '--graphs',
         'pure 2,mixed', '--payload', '64x48', '--frames', '14', '--rounds', '1'],
        cwd=ROOT, capture_output=True, text=True, timeout=300, env=dict(os.environ))
    assert completed.returncode == 0, completed.stdout + completed.stderr
    rows = {row[0]: row[1:] for row in table_rows(completed.stdout)}
    header = rows.pop('graph')
    assert set(rows) == {'pure 2', 'mixed'}, completed.stdout
    assert header[0] == 'total CPU' and header[1] == 'main', completed.stdout
    assert any(name.startswith('dds.shm') for name in header), completed.stdout
    for cells in rows.values():
        float(cells[0])
        cpu, wakes = cells[1].split(' / ')
        float(cpu), int(wakes)


def test_under_churn_on_a_loaded_machine_steady_subscribers_get_what_stocks_get_zero_copy():
    """Issue #19's churn and load scenarios, stock as the oracle: bench_churn's graph (a
    subscriber coming and going, one SIGKILLed, two busy processes holding both cores), once
    with stock endpoints and once with ours. Each of our steady subscribers receives at least
    what its stock counterpart received, the demo one at least 95 % of it as zero-copy
    Buffers, and the publisher writes no CPU copy to a peer that shares its backend (dead
    ones included)."""
    completed = subprocess.run(
        [sys.executable, '-m', 'launch_free_demos.bench.churn', '--seconds', '4', '--payload',
         '640x480', '--come-go', '1', '--kill-every', '1.5', '--load', '2'],
        cwd=ROOT, capture_output=True, text=True, timeout=300, env=dict(os.environ))
    assert completed.returncode == 0, completed.stdout + completed.stderr
    rows = {row[0]: row[1:] for row in table_rows(completed.stdout)}
    assert set(rows) == {'graph', 'stock', 'ours'}, completed.stdout
    stock, ours = rows['stock'], rows['ours']
    assert int(stock[0]) == int(ours[0]) == 120, completed.stdout  # published
    demo, zero_copy = (int(v.strip('()')) for v in ours[1].split())
    for position, (theirs, mine) in enumerate(zip(stock[1:4], [demo, *ours[2:4]])):
        assert int(mine) >= int(theirs), (position, completed.stdout)
    assert zero_copy >= 0.95 * demo, completed.stdout
    assert stock[4] == '-' and ours[4] == '0', completed.stdout


def test_bench_bare_prints_stock_the_bare_descriptor_path_and_demo_per_round():
    """README's ./dev bench bare, short: the latency split of stock rclpy, the bare descriptor
    path (native write, guard wake, native take) and the demo backend, and each round's
    ratios; the bare path's frames arrive decoded (its medians exist)."""
    command = [str(ROOT / 'dev'), 'bench', 'bare'] if in_dev_venv() else \
        [sys.executable, '-m', 'launch_free_demos.bench.bare']
    completed = subprocess.run(command + ['--frames', '8', '--rate', '20', '--rounds', '1'],
                               cwd=ROOT, capture_output=True, text=True, timeout=300,
                               env=dict(os.environ))
    assert completed.returncode == 0, completed.stdout + completed.stderr
    rows = {row[0]: row[1:] for row in table_rows(completed.stdout)}
    assert rows[''] == ['stock rclpy', 'bare', 'demo'], completed.stdout
    for what in ('stamp -> reception (publisher, DDS)', 'reception -> callback (subscriber)',
                 'total'):
        assert len(rows[what]) == 3 and all(float(c) > 0 for c in rows[what]), completed.stdout
    assert rows['round'] == ['bare / stock rclpy', 'demo / stock rclpy', 'demo - bare (µs)']
    assert len(rows['1']) == 3 and float(rows['1'][0]) > 0, completed.stdout


def test_bench_bare_counts_the_python_opcodes_of_each_side_by_origin():
    """./dev bench bare --opcodes, short: per message and side, the opcodes of this package,
    rclpy, the message classes, the benchmark and Python's library, per mode. The bare path
    runs nothing of ours on the subscriber (its take decodes in C); the demo path runs ours on
    both sides; stock's subscriber builds its message in the generated class."""
    command = [str(ROOT / 'dev'), 'bench', 'bare'] if in_dev_venv() else \
        [sys.executable, '-m', 'launch_free_demos.bench.bare']
    completed = subprocess.run(command + ['--opcodes', '--frames', '8', '--rate', '20'],
                               cwd=ROOT, capture_output=True, text=True, timeout=300,
                               env=dict(os.environ))
    assert completed.returncode == 0, completed.stdout + completed.stderr
    rows = {row[0]: [float(c) for c in row[1:]] for row in table_rows(completed.stdout)
            if row[0]}  # (the header row's first cell is empty)
    origins = ['this package', 'rclpy', 'generated message classes', 'this benchmark',
               "Python's library", 'total']
    assert set(rows) == {f'{side}: {o}' for side in ('publisher', 'subscriber')
                         for o in origins}, completed.stdout
    stock, bare, demo = range(3)
    for side in ('publisher', 'subscriber'):
        assert all(v > 0 for v in rows[f'{side}: total']), completed.stdout
        assert rows[f'{side}: this package'][demo] > 100, completed.stdout
    assert rows['subscriber: this package'][bare] == 0, completed.stdout
    assert rows['subscriber: generated message classes'][stock] > 0, completed.stdout


def test_bench_wakeup_times_a_wakeup_with_stock_and_our_endpoints():
    """README's ./dev bench wakeup, short: a row per round with both modes' figures, and what
    the nodes hold in steady state: stock endpoints no guard condition or timer of ours, ours
    one guard condition per node and one per subscription, and no timer."""
    command = [str(ROOT / 'dev'), 'bench', 'wakeup'] if in_dev_venv() else \
        [sys.executable, '-m', 'launch_free_demos.bench.wakeup']
    completed = subprocess.run(command + ['--topics', '2', '--wakeups', '5', '--period', '0.05',
                                          '--rounds', '1'],
                               cwd=ROOT, capture_output=True, text=True, timeout=300,
                               env=dict(os.environ))
    assert completed.returncode == 0, completed.stdout + completed.stderr
    rows = {row[0]: row[1:] for row in table_rows(completed.stdout)}
    stock, ours, ratio = rows['1']
    assert all(float(v) > 0 for cell in (stock, ours) for v in cell.split(' / ')), rows
    assert float(ratio) > 0, rows
    assert ('stock rclpy: 0 guard conditions, 0 timers; rosidl_buffer_py: 4 guard conditions, '
            '0 timers') in completed.stdout, completed.stdout


def test_bench_lane_times_publish_through_the_lane_and_the_full_path():
    """README's ./dev bench lane, short: a row per round, stock rclpy's publish() and the demo
    publisher's, most of its calls through its steady lane once its route serves, and the
    demo subscription's deliveries, through its steady step."""
    command = [str(ROOT / 'dev'), 'bench', 'lane'] if in_dev_venv() else \
        [sys.executable, '-m', 'launch_free_demos.bench.lane']
    completed = subprocess.run(command + ['--frames', '12', '--rate', '20', '--rounds', '1'],
                               cwd=ROOT, capture_output=True, text=True, timeout=300,
                               env=dict(os.environ))
    assert completed.returncode == 0, completed.stdout + completed.stderr
    rows = {row[0]: row[1:] for row in table_rows(completed.stdout)}
    stock, lane, _, steady_step, _ = rows['1']
    assert float(stock.split()[0]) > 0, rows
    assert int(lane.split()[1].strip('()')) > 0, rows  # (the first under a plan prepares it)
    assert int(steady_step.split()[1].strip('()')) > 0, rows


def test_bench_hotpath_times_every_stage_of_every_transport():
    """README's ./dev bench hotpath, short: the latency split of each transport, and a median
    for every stage it times on each side (the functions it wraps still exist), a demo
    message's through its steady lane or step where it took them."""
    command = [str(ROOT / 'dev'), 'bench', 'hotpath'] if in_dev_venv() else \
        [sys.executable, '-m', 'launch_free_demos.bench.hotpath']
    completed = subprocess.run(command + ['--frames', '8', '--rate', '20', '--rounds', '2'],
                               cwd=ROOT,
                               capture_output=True, text=True, timeout=300,
                               env=dict(os.environ))
    assert completed.returncode == 0, completed.stdout + completed.stderr
    rows = {row[0]: row[1:] for row in table_rows(completed.stdout)}
    for what in ('stamp -> reception (publisher, DDS)', 'reception -> callback (subscriber)',
                 'total', 'publish()'):
        assert len(rows[what]) == 3 and all(float(c.split()[0]) > 0 for c in rows[what]), \
            completed.stdout
    # every message of ours runs these; the cpu path's have no backend
    always = ['delivery path: take to message',
              'native open, either path: segment checks and hold lock']
    # a demo message goes one way of each pair (a steady lane or step, or the general path)
    either = [('writes (descriptor or CPU message)',
               'steady lane (its prepared writes; declined calls and re-plans too)'),
              ('channel takes (empty ones too; descriptor messages decoded in them)',
               "steady step (the one channel's take, decoded in C; empty ones too)")]
    for stage in always:
        stock, cpu, demo = rows[stage]
        assert stock == '' and float(demo.split()[0]) > 0, (stage, completed.stdout)
        assert (cpu == '') == (stage != always[0]), (stage, completed.stdout)
    for general, steady in either:
        stock, cpu, demo = rows[general]
        assert stock == '' and float(cpu.split()[0]) > 0, (general, completed.stdout)
        assert demo or rows.get(steady, ('', '', ''))[2], (general, completed.stdout)
    assert 'after 50 ms idle' in completed.stdout
    for transport in ('cpu', 'demo'):  # two rounds, interleaved: a ratio for each
        assert re.search(rf'^{transport} / stock rclpy total per round: [\d.]+, [\d.]+ '
                         rf'\(median [\d.]+\)$', completed.stdout, re.M), completed.stdout


@pytest.mark.parametrize('peer', PEERS, ids=[t.peer_module for t in PEERS])
def test_a_peer_is_measured_as_our_nodes_are_and_leaves_no_files(peer, monkeypatch):
    """A peer transport's publisher and subscriber in two processes, through the benchmark's
    own measurement: every frame arrives intact (through shared memory), latency, time to a
    numpy view and CPU per frame of both are measured, and the run's files (its directory, its
    /dev/shm files, zenoh segments nobody holds) are gone after it."""
    pytest.importorskip(peer.peer_module)
    used, scratch = [], benchmark.peer_scratch

    @contextlib.contextmanager
    def noted(transport):
        with scratch(transport) as params:
            used.append(params)
            yield params

    monkeypatch.setattr(benchmark, 'peer_scratch', noted)
    since = time.time() - 1.0
    result = measure(peer.label, '1 KiB', 1, 6, 10.0)
    assert result.complete and result.distinct == [6], result
    assert result.backends == {peer.label: 6}
    assert result.latency['p50'] > 0 and result.view['p50'] > 0
    assert result.pub_cpu_ms is not None and result.sub_cpu_ms is not None
    [params] = used
    assert not os.path.exists(params['root_path'])
    assert not benchmark.peer_shm_leftovers(params.get('shm_prefix', 'rbpy_none_'), since)


def test_peer_scratch_removes_what_a_run_left_and_keeps_what_is_in_use(tmp_path):
    """The iceoryx2 run's prefixed files go, its directory goes; a zenoh segment goes when no
    process holds its flock any more (zenoh holds one while it uses a segment)."""
    import fcntl
    iceoryx2 = next(t for t in PEERS if t.peer_module == 'iceoryx2')
    name = f'{os.getpid()}{time.monotonic_ns() % 10**6}'
    held_path, dead_path = f'/dev/shm/{name}1.zenoh', f'/dev/shm/{name}2.zenoh'
    with open(held_path, 'wb') as held:
        fcntl.flock(held, fcntl.LOCK_SH)
        try:
            with peer_scratch(iceoryx2) as params:
                root, prefix = Path(params['root_path']), params['shm_prefix']
                assert prefix.startswith('rbpy_') and root.is_dir()
                (root / 'services').mkdir()
                Path('/dev/shm', prefix + 'x.global_mgmt').write_bytes(b'')
                Path(dead_path).write_bytes(b'')
            assert not root.exists() and not Path('/dev/shm', prefix + 'x.global_mgmt').exists()
            assert not Path(dead_path).exists() and Path(held_path).exists()
        finally:
            for path in (held_path, dead_path):
                if os.path.exists(path):
                    os.remove(path)


def test_a_fanout_series_whose_cpu_falls_with_more_subscribers_is_flagged():
    """The issue's figures: stock's publisher CPU per message 62.6 ms with 1 subscriber and 3.7
    ms with 4 is a measurement error; a series that grows (or stays within noise) is not."""
    from launch_free_demos.bench.suite import fanout_implausibility
    reason = fanout_implausibility([(1, 62.6), (2, 20.1), (4, 3.7)])
    assert reason == ('CPU per message fell from 62.6 to 20.1 ms from 1 to 2 subscribers: a '
                      'measurement error, not plotted')
    assert fanout_implausibility([(1, 3.7), (2, 7.9), (4, 15.2)]) is None
    assert fanout_implausibility([(1, 1.30), (2, 1.21), (4, 1.35)]) is None  # noise
    assert fanout_implausibility([]) is None


def test_a_peer_prints_the_report_line_of_the_nodes(capsys):
    """The peers write the report line themselves (rclpy-free); it reads as a node's."""
    from launch_free_demos.bench.peers import common
    from rosidl_buffer_py.report import last_report
    common.print_report({'role': 'publisher', 'published': 3})
    assert last_report(capsys.readouterr().out.splitlines()) == {'role': 'publisher',
                                                                 'published': 3}
