"""Several sensors' samples of one stamp assembled into one stacked measurement, no ROS.

An estimator fed by several sensors (measurements.stacked) gets each sensor's sample of a
stamp on its own topic, in any order. :class:`SampleAssembler` collects them per stamp and
hands a stamp on once every sensor has reported it (a sample, or "nothing measured": a sensor
in the loop reports every truth stamp, between two of its samples too), or once a later stamp
is complete (a sensor's report was lost), or after ``wait`` wall seconds (see :meth:`expired`).
A stamp handed on is z stacked with NaN for the sensors that gave nothing, or None when none
did. A report for a stamp already handed on is a repeat (a lockstep resend) or late.

A per-sensor Mahalanobis gate (``gates``, chi-square thresholds, 0: none) is applied by the
caller, which has the filter (:func:`gate`).
"""

from __future__ import annotations

import time
from typing import Callable, Sequence

import numpy as np

#: Stamps handed on whose reporters are remembered (a resend comes within a few steps).
REMEMBERED = 64


class SampleAssembler:
    """Per-stamp assembly of the parts of a stacked measurement (module docstring)."""

    def __init__(self, model, wait: float = 0.25, wall_clock: Callable[[], float] = time.monotonic):
        self.model = model
        self.wait = float(wait)
        self._wall = wall_clock
        self._parts: dict[int, dict[int, np.ndarray | None]] = {}  # stamp -> sensor -> sample
        self._first_seen: dict[int, float] = {}
        self.newest_handed: int | None = None
        self.incomplete = 0  # stamps handed on without every sensor's report
        self._reported: dict[int, frozenset] = {}  # recent stamps handed on -> the sensors that reported

    def offer(self, sensor: int, stamp_ns: int, z: np.ndarray | None) -> tuple[str, list]:
        """Sensor ``sensor``'s report for ``stamp_ns`` (z None: nothing measured). Returns
        (what it was: 'new' | 'repeat' (it came before) | 'late' (its stamp went on without it),
        the stamps now ready as (stamp, z or None), in order)."""
        if self.newest_handed is not None and stamp_ns <= self.newest_handed and stamp_ns not in self._parts:
            return ('repeat' if sensor in self._reported.get(stamp_ns, ()) else 'late'), []
        parts = self._parts.setdefault(stamp_ns, {})
        self._first_seen.setdefault(stamp_ns, self._wall())
        if sensor in parts:
            return 'repeat', []
        parts[sensor] = None if z is None else np.asarray(z, dtype=float)
        ready = []
        if len(parts) == len(self.model.parts):  # complete: it, and every older one as it is
            for stamp in sorted(s for s in self._parts if s <= stamp_ns):
                ready.append(self._hand_on(stamp))
        return 'new', ready

    def expired(self) -> list:
        """The stamps waiting longer than ``wait`` for a report, handed on as they are."""
        now = self._wall()
        late = [s for s in sorted(self._parts) if now - self._first_seen[s] >= self.wait]
        if not late:
            return []
        return [self._hand_on(s) for s in sorted(s for s in self._parts if s <= late[-1])]

    @property
    def pending(self) -> int:
        return len(self._parts)

    def clear(self) -> None:
        """Forget everything (the time base restarted)."""
        self._parts.clear()
        self._first_seen.clear()
        self._reported.clear()
        self.newest_handed = None

    def _hand_on(self, stamp_ns: int) -> tuple[int, np.ndarray | None]:
        parts = self._parts.pop(stamp_ns)
        del self._first_seen[stamp_ns]
        self._reported[stamp_ns] = frozenset(parts)
        if len(self._reported) > REMEMBERED:
            del self._reported[min(self._reported)]
        if len(parts) < len(self.model.parts):
            self.incomplete += 1
        self.newest_handed = stamp_ns if self.newest_handed is None else max(self.newest_handed, stamp_ns)
        if all(z is None for z in parts.values()):
            return stamp_ns, None
        z = np.full(self.model.dim, np.nan)
        for sensor, sample in parts.items():
            if sample is not None:
                z[self.model.slices[sensor]] = sample
        return stamp_ns, z


def gate(estimator, model, z: np.ndarray, measurement_covariance, gates: Sequence[float]) -> tuple[np.ndarray, list]:
    """``z`` with the parts whose normalised innovation squared against the current estimate
    exceeds their sensor's gate (0: no gate) set to NaN, and the indices of those sensors."""
    gated = []
    for i, (part, threshold) in enumerate(zip(model.slices, gates)):
        if threshold <= 0.0 or not np.isfinite(z[part]).all():
            continue
        alone = np.full(model.dim, np.nan)
        alone[part] = z[part]
        nis = float(estimator.innovation_nis(alone, measurement_covariance)[0])
        if nis > threshold:
            gated.append(i)
    if gated:
        z = z.copy()
        for i in gated:
            z[model.slices[i]] = np.nan
    return z, gated
