"""Unit tests of the demo backend's guard (demo_buffer_backend/guard.py): a release never waits
for the lock, and none is lost."""
import threading

from demo_buffer_backend.guard import Guard


def test_a_release_runs_at_once_when_the_lock_is_free():
    guard, ran = Guard(), []
    guard.defer(ran.append, 1)
    assert ran == [1] and not guard.pending


def test_a_release_deferred_under_the_lock_runs_when_it_is_let_go():
    guard, ran = Guard(), []
    with guard:
        guard.defer(ran.append, 1)  # as a garbage collection inside the backend would
        assert ran == []
    assert ran == [1]


def test_a_release_from_another_thread_never_waits_for_the_holder():
    guard, ran = Guard(), []
    with guard:
        thread = threading.Thread(target=guard.defer, args=(ran.append, 'other'))
        thread.start()
        thread.join(timeout=5)
        assert not thread.is_alive() and ran == []
    assert ran == ['other']


def test_a_failing_release_does_not_stop_the_others():
    guard, ran = Guard(), []
    with guard:
        guard.defer(ran.append, 1)
        guard.defer(lambda _: 1 / 0, None)
        guard.defer(ran.append, 2)
    assert sorted(ran) == [1, 2]
