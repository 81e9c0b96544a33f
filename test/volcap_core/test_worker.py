"""The drop-oldest worker: bounded queue under load, errors survived, readiness gate, clean
shutdown."""
import threading
import time

import pytest

from volcap_core.worker import DropOldestWorker


def test_a_slow_worker_drops_the_oldest_waiting_items_and_handles_the_newest():
    release = threading.Event()
    handled = []

    def handle(item):
        release.wait(5)
        handled.append(item)

    w = DropOldestWorker(handle, capacity=2, name='test-worker')
    try:
        assert w.submit(0)
        deadline = time.monotonic() + 5
        while w.pending and time.monotonic() < deadline:   # item 0 is taken and blocks the worker
            time.sleep(0.01)
        results = [w.submit(k) for k in range(1, 6)]
        assert results == [True, True, False, False, False]
        assert w.dropped == 3 and w.pending == 2
        release.set()
        assert w.wait_idle(5)
        assert handled == [0, 4, 5]
    finally:
        w.stop()


def test_errors_are_reported_and_the_worker_carries_on():
    errors = []

    def handle(item):
        if item == 'bad':
            raise ValueError('broken frame set')

    w = DropOldestWorker(handle, 4, 'test-worker', on_error=lambda item, e: errors.append((item, str(e))))
    try:
        for item in ('good', 'bad', 'good'):
            w.submit(item)
        assert w.wait_idle(5)
        assert errors == [('bad', 'broken frame set')] and w.done == 2 and w.errors == 1
    finally:
        w.stop()


def test_items_wait_until_ready():
    ready = threading.Event()
    handled = []
    w = DropOldestWorker(handled.append, 4, 'test-worker', ready=ready.is_set)
    try:
        w.submit(1)
        assert not w.wait_idle(0.3) and handled == []
        ready.set()
        w.poke()
        assert w.wait_idle(5) and handled == [1]
    finally:
        w.stop()


def test_stop_ends_the_thread_and_discards_waiting_items():
    started = threading.Event()
    handled = []

    def handle(item):
        started.set()
        time.sleep(0.2)
        handled.append(item)

    w = DropOldestWorker(handle, 8, 'test-worker')
    for k in range(5):
        w.submit(k)
    assert started.wait(5)
    w.stop(timeout=5)
    assert not w._thread.is_alive()
    assert handled == [0]        # the item in hand is finished; the waiting ones are not started


def test_capacity_must_be_positive():
    with pytest.raises(ValueError):
        DropOldestWorker(print, 0, 'test-worker')
