"""README's ``./dev bench bringup``, small and short (no timing asserts).

Each trial starts a fresh buffer-aware subscriber beside a running demo publisher: its channel
must come up (a zero-copy frame arrives), and from its first frame on nothing may be lost,
duplicated, corrupt or rejected (the publisher's channel probes are not messages).
"""
import os
import subprocess
import sys
from pathlib import Path

from harness.installed import in_dev_venv

ROOT = Path(__file__).resolve().parent.parent


def test_every_new_subscriber_reaches_zero_copy_with_nothing_lost_on_the_way():
    command = [str(ROOT / 'dev'), 'bench', 'bringup'] if in_dev_venv() else \
        [sys.executable, '-m', 'launch_free_demos.bench.bringup']
    completed = subprocess.run(
        command + ['--payload', '64x48', '--trials', '2', '--after', '3'],
        cwd=ROOT, capture_output=True, text=True, timeout=180, env=dict(os.environ))
    assert completed.returncode == 0, completed.stdout + completed.stderr
    rows = [[cell.strip() for cell in line.strip('|').split('|')]
            for line in completed.stdout.splitlines()
            if line.startswith('|') and not line.startswith('|---')]
    header = next(row for row in rows if row[0] == 'trial')
    trials = [dict(zip(header, row)) for row in rows if row[0].isdigit()]
    assert len(trials) == 2, completed.stdout
    for trial in trials:
        assert trial['match to zero-copy, ms'] != '-', completed.stdout
        assert int(trial['frames']) >= 4, completed.stdout
        for column in ('lost', 'duplicated', 'corrupt', 'rejected', 'fence timeouts'):
            assert trial[column] == '0', (column, completed.stdout)
        assert trial['problem'] == '', completed.stdout


def test_first_frame_command_prints_stock_and_ours_for_each_subscriber():
    """docs/development.md's first-frame comparison, one short run: a row per publisher and
    run, and a summary per publisher, for a stock and a buffer-aware subscriber."""
    script = ROOT / 'test' / 'harness' / 'first_frame.py'
    completed = subprocess.run(
        [sys.executable, str(script), '--runs', '1', '--frames', '15'], cwd=ROOT,
        capture_output=True, text=True, timeout=180, env=dict(os.environ))
    assert completed.returncode == 0, completed.stdout + completed.stderr
    out = completed.stdout
    assert out.count('subscriber, 15 frames at 30 Hz') == 2, out
    for publisher in ('stock', 'ours'):
        runs = [line for line in out.splitlines() if line.startswith(f'| 1 | {publisher} |')]
        assert len(runs) == 2, out
        summaries = [line for line in out.splitlines()
                     if line.startswith(f'| {publisher} | ') and ' of 1 |' in line]
        assert len(summaries) == 2, out
