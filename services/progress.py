"""A progress line on stderr for long runs (only when stderr is a terminal, or forced)."""

from __future__ import annotations

import sys
import time


class Progress:
    """``update(done, total)`` redraws one line on stderr at most 10 times a second."""

    def __init__(self, label: str, stream=None, force: bool = False) -> None:
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = force or self.stream.isatty()
        self.start = time.monotonic()
        self._last = 0.0
        self._drawn = False

    def update(self, done: int, total: int, label: str | None = None, base: int = 0) -> None:
        """Redraw the line with done/total, the elapsed time and the remaining time extrapolated
        from the rate so far; skipped within 0.1 s of the last redraw unless done >= total.
        ``base``: items that were done before this run started (a resumed job), left out of
        the rate. No-op when disabled.
        """
        if not self.enabled:
            return
        now = time.monotonic()
        if done < total and now - self._last < 0.1:
            return
        self._last = now
        elapsed = now - self.start
        frac = done / total if total else 1.0
        run_frac = (done - base) / (total - base) if total > base else 1.0
        eta = elapsed / run_frac - elapsed if run_frac > 0 else 0.0
        bar = "#" * int(30 * frac)
        self.stream.write(f"\r{label or self.label}: [{bar:<30}] {done}/{total} {elapsed:5.0f}s eta {eta:4.0f}s ")
        self.stream.flush()
        self._drawn = True

    def close(self) -> None:
        """End the line (newline) if one was drawn."""
        if self._drawn:
            self.stream.write("\n")
            self.stream.flush()
        self._drawn = False
