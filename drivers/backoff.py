"""Exponential backoff between reconnect attempts, shared by the drivers and the device workers.

After ``k`` consecutive failures since the last success the next wait is::

    d_k = min(initial * factor**k, maximum)        k = 0, 1, 2, ...

(exact for ``factor = 2``, to float rounding otherwise). :meth:`Backoff.failed` returns
``d_k`` and moves to ``d_{k+1}``; :meth:`Backoff.reset` (a success) returns to ``d_0``. The
cap applies from the first delay on, so ``maximum < initial`` gives ``maximum`` every time.
:meth:`Backoff.wait` sleeps ``d_k`` on a :class:`threading.Event` and returns as soon as the
event is set, so closing a driver never waits out a long delay.

Usage::

    backoff = Backoff(0.5, 10.0)
    while not stop.is_set():
        if not try_connect():
            if backoff.wait(stop):   # True: stop was set during the wait
                break
            continue
        backoff.reset()
"""

from __future__ import annotations

import threading


class Backoff:
    """Delays ``min(initial * factor**k, maximum)`` after ``k`` failures; reset on success."""

    def __init__(self, initial: float, maximum: float, factor: float = 2.0) -> None:
        if not initial > 0.0 or not maximum > 0.0:
            raise ValueError(
                f"backoff delays must be > 0, got initial={initial}, maximum={maximum}"
            )
        if not factor >= 1.0:
            raise ValueError(f"backoff factor must be >= 1, got {factor}")
        self.initial = float(initial)
        self.maximum = float(maximum)
        self.factor = float(factor)
        self._delay = min(self.initial, self.maximum)

    @property
    def delay(self) -> float:
        """The delay the next failure waits, s (``d_k``)."""
        return self._delay

    def failed(self) -> float:
        """Count a failure: the delay to wait now (``d_k``); the next one is ``d_{k+1}``."""
        d = self._delay
        self._delay = min(d * self.factor, self.maximum)
        return d

    def reset(self) -> None:
        """Count a success: the next failure waits ``d_0`` again."""
        self._delay = min(self.initial, self.maximum)

    def wait(self, stop: threading.Event) -> bool:
        """Count a failure and wait its delay, or less if ``stop`` is set; True if it was set."""
        return stop.wait(self.failed())
