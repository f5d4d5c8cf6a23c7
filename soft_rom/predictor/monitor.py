"""Windowed prediction error that expires with time and can never become NaN.

Each accepted measurement adds ``(stamp, |y - ŷ|², |y|², |y - y_ref|²)``; the window holds
at most ``error_window`` of them and none older than ``error_window_s`` before the newest
time seen. The relative errors are

.. math:: e = \\sqrt{\\sum \\|y - \\hat y\\|^2 / \\sum \\|y\\|^2}, \\qquad
          e_{dev} = \\sqrt{\\sum \\|y - \\hat y\\|^2 / \\sum \\|y - y_{ref}\\|^2}.

Non-finite squares are refused by :meth:`ErrorMonitor.push` (the caller drops measurements
outside the output envelope first, so the squares stay far from overflow). Running sums
are recomputed exactly whenever as many entries were pushed as the window holds, so
rounding cannot accumulate.
"""

from __future__ import annotations

from collections import deque
import math

from soft_rom.metrics import relative_error_from_squares

__all__ = ['ErrorMonitor']


class ErrorMonitor:
    """Ring of the last measurements' squared errors with time expiry.

    Parameters
    ----------
    size : int
        Most entries.
    horizon_ns : int
        Entries older than this before the newest time are dropped.
    """

    def __init__(self, size: int, horizon_ns: int) -> None:
        self.size = int(size)
        self.horizon_ns = int(horizon_ns)
        self.clear()

    def clear(self) -> None:
        """Forget every entry (``seen`` is kept false until the next push)."""
        self._q: deque[tuple[int, float, float, float]] = deque()
        self._se = self._sy = self._sd = 0.0
        self._pushed = 0
        self.seen = False
        self.last_ns: int | None = None

    def __len__(self) -> int:
        return len(self._q)

    def push(self, t_ns: int, e2: float, y2: float, d2: float) -> bool:
        """Add one measurement; returns False (nothing added) if a figure is not finite."""
        if not (math.isfinite(e2) and math.isfinite(y2) and math.isfinite(d2)):
            return False
        q = self._q
        q.append((t_ns, e2, y2, d2))
        self._se += e2
        self._sy += y2
        self._sd += d2
        while len(q) > self.size:
            self._pop()
        self.seen = True
        self.last_ns = t_ns if self.last_ns is None else max(self.last_ns, t_ns)
        self._pushed += 1
        if self._pushed >= self.size:
            self._resum()
        self.expire(t_ns)
        return True

    def _pop(self) -> None:
        _, e2, y2, d2 = self._q.popleft()
        self._se -= e2
        self._sy -= y2
        self._sd -= d2

    def _resum(self) -> None:
        self._se = math.fsum(e for _, e, _, _ in self._q)
        self._sy = math.fsum(y for _, _, y, _ in self._q)
        self._sd = math.fsum(d for _, _, _, d in self._q)
        self._pushed = 0

    def expire(self, now_ns: int | None) -> None:
        """Drop entries older than ``horizon_ns`` before ``now_ns``."""
        if now_ns is None:
            return
        q = self._q
        limit = now_ns - self.horizon_ns
        popped = False
        while q and q[0][0] < limit:
            self._pop()
            popped = True
        if popped:
            self._resum()

    def errors(self) -> tuple[float, float]:
        """``(absolute, deviation)`` relative errors (``nan`` with an empty window).

        Against a reference of norm 0 (a measured centerline exactly at ``y_ref``): 0 when
        the prediction is exact too, else ``inf`` (a prediction that moves while the body is
        at rest is not an error of 0).
        """
        if not self._q:
            return math.nan, math.nan
        se = max(self._se, 0.0)
        zero = 0.0 if se == 0.0 else math.inf
        return (relative_error_from_squares(se, self._sy, if_zero=zero),
                relative_error_from_squares(se, self._sd, if_zero=zero))
