"""A worker thread fed by a bounded drop-oldest queue: a node hands slow work (fusion, board
detection) to it and its subscriptions stay free. When the work falls behind, the oldest waiting
items are dropped and counted, never queued without bound."""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any, Callable

from .errors import BadInput


class DropOldestWorker:
    """Calls ``handle(item)`` on its own thread for each submitted item, in order.

    ``ready()`` gates the work (items wait while it is false, e.g. until a calibration
    arrives); an exception from ``handle`` goes to ``on_error(item, exc)`` and the worker
    carries on with the next item."""

    def __init__(self, handle: Callable[[Any], None], capacity: int, name: str,
                 on_error: Callable[[Any, Exception], None] | None = None, ready: Callable[[], bool] = lambda: True):
        if capacity < 1:
            raise BadInput(f'capacity must be >= 1, got {capacity}')
        self.handle = handle
        self.on_error = on_error
        self.ready = ready
        self.queue: deque = deque(maxlen=capacity)
        self.dropped = self.done = self.errors = 0
        self._busy = False
        self._running = True
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, item) -> bool:
        """Queue ``item``; returns False when the oldest waiting item was dropped for it."""
        with self._cond:
            dropped = len(self.queue) == self.queue.maxlen
            if dropped:
                self.dropped += 1
            self.queue.append(item)
            self._cond.notify_all()
        return not dropped

    def poke(self) -> None:
        """Re-check ``ready()`` now (after what it depends on changed)."""
        with self._cond:
            self._cond.notify_all()

    @property
    def pending(self) -> int:
        with self._cond:
            return len(self.queue)

    def wait_idle(self, timeout: float) -> bool:
        """Until the queue is empty and nothing is being handled; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self.queue or self._busy:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.5))
        return True

    def stop(self, timeout: float = 10.0) -> None:
        """Stop after the item in hand (waiting items are discarded) and join the thread."""
        with self._cond:
            self._running = False
            self._cond.notify_all()
        self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._running and not (self.queue and self.ready()):
                    self._cond.wait(0.5)
                if not self._running:
                    return
                item = self.queue.popleft()
                self._busy = True
            try:
                self.handle(item)
                self.done += 1
            except Exception as e:   # the worker must outlive any one bad item
                self.errors += 1
                if self.on_error is not None:
                    self.on_error(item, e)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()
