"""A process of our user cannot take a demo subscriber's frames away (test/harness/attacks.py).

Each case runs a genuine demo publisher and a demo subscriber in real processes over Fast DDS,
with a hostile process of the same user working against the subscriber's listener: its mapping
table filled first, its listen backlog filled, its connections kept full of junk, and what was
always refused (garbage, unsealed or writable memfds, files, pipes, sockets, /dev/zero, records
under the publisher's nonce, fake acknowledgments). Each asserts what the subscriber exists for
(every frame, zero-copy as without the attacker, no CRC failure) and that the attacker's
resources were released: the subscriber closed every connection it opened (which frees every
descriptor queued in them) and never read one. Latency under attack against the control run
is a figure of the harness's table (``.venv/bin/python test/harness/attacks.py``), not an assert.
"""
import pytest

from harness.attacks import run_case

#: Short runs (the harness's table uses 300 frames at 10 Hz).
FRAMES = 40
RATE_HZ = 20.0


@pytest.mark.parametrize('case', ['mappings_first', 'backlog', 'junk', 'rejected'])
def test_the_subscriber_gets_every_frame_zero_copy_and_the_attacker_nothing(case):
    outcome = run_case(case, frames=FRAMES, rate=RATE_HZ)
    detail = (f'{outcome.row()}\nproblems: {outcome.problems}\nattacker: {outcome.attacker}\n'
              f'subscriber: {outcome.subscriber_stats}\npublisher: {outcome.publisher_stats}')
    assert not outcome.problems, detail
    assert outcome.received == FRAMES and outcome.crc_failures == 0, detail
    assert outcome.zero_copy >= 0.95 * FRAMES, detail
    sub, pub = outcome.subscriber_stats, outcome.publisher_stats
    assert sub['rejected'] == 0, detail  # no descriptor of the publisher's was refused
    assert sub['handovers_rejected'] == 0, detail  # not one of the attacker's records was read
    assert pub['handovers_refused'] == pub['links_refused'] == 0, detail
    attacker = outcome.attacker
    assert attacker['connections'] > 0, detail
    assert attacker['closed_by_subscriber'] == attacker['connections'], detail
    assert sub['connections_refused'] >= attacker['connections'] - (case == 'rejected'), detail
    assert sub['mappings'] <= pub['segments_created'], detail  # nothing of the attacker's mapped
