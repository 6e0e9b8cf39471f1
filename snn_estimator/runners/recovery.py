"""When and where a filter starts again mid-flight: from the data, never the parameters'
initial state.

When (:class:`RestartTrigger`): a reset on request, at the next measurement's step, or a
normalised innovation squared (NIS) above ``nis_threshold`` for ``nis_window`` steps in a row.
(A non-finite state or a covariance the step cannot keep restarts it at once: the runner's
step catches them.)

Where from (:class:`Recovery`): a filter that lost the truth, or is reset on request, restarts
from what the loop measured, in this order:

1. a least-squares fit of the recent measurements (``initial_fit_window`` seconds, the controls
   used between them; :func:`snn_estimator.runners.initialization.least_squares_start`): the prior at
   the current step, with its covariance;
2. else (too few measurements) the measured states from the current measurement and the
   others from the last estimate that was consistent with its measurement, propagated with
   the controls used since, its covariance inflated by ``TRUST_INFLATION``;
3. else (nothing was consistent yet) the measured states from the measurement, the others
   kept where finite, P0.

Resets that follow each other closely (``storm_count`` within ``storm_window`` simulated s) are a
reset storm: counted and reported (the filter cannot follow this loop: a wrong model, R, or
control input), never silently repeated.
"""

from __future__ import annotations

from collections import deque
from typing import Callable

import numpy as np

from .gates import NS, seconds_to_ns
from .initialization import least_squares_start

#: Factor on the covariance of the last trusted estimate when a restart starts from it.
TRUST_INFLATION = 10.0
#: Fewest measurements a least-squares restart fits.
MIN_FIT_MEASUREMENTS = 5


class RestartTrigger:
    """Says when a running filter must start again from the data (see the module docstring)."""

    def __init__(self):
        self._inconsistent_steps = 0  # NIS over the threshold, in a row
        self._requested: tuple[str, str] | None = None

    @property
    def requested(self) -> tuple[str, str] | None:
        """(why, 'reset') of a reset requested for the next measurement's step, else None."""
        return self._requested

    @property
    def consistent(self) -> bool:
        """The last innovation checked was within the threshold (or none was since a restart)."""
        return self._inconsistent_steps == 0

    def request(self, why: str) -> None:
        """A reset on request: the next measurement's step restarts the filter."""
        self._requested = (why, 'reset')

    def check(self, nis: float, threshold: float, window: int) -> tuple[str, str] | None:
        """Count a step's NIS: (why, 'inconsistent_innovation') once it was over ``threshold``
        for ``window`` steps in a row (``window`` 0: never), else None."""
        self._inconsistent_steps = self._inconsistent_steps + 1 if nis > threshold else 0
        if self._inconsistent_steps >= window > 0:
            return (f'normalised innovation squared {nis:.1f} > {threshold} for {self._inconsistent_steps} steps',
                    'inconsistent_innovation')
        return None

    def forget_inconsistency(self) -> None:
        """Start counting inconsistent steps afresh (the state was set)."""
        self._inconsistent_steps = 0

    def clear(self) -> None:
        """The filter restarted: nothing requested, nothing inconsistent."""
        self._inconsistent_steps = 0
        self._requested = None

    def snapshot(self) -> tuple:
        """What a step changes here, for :meth:`restore` (a step taken again)."""
        return self._inconsistent_steps, self._requested

    def restore(self, snapshot: tuple) -> None:
        self._inconsistent_steps, self._requested = snapshot


class Recovery:
    """Remembers the recent data of a running filter and says where it restarts from."""

    def __init__(self, estimator, measurement_covariance, window: float, time_step: float,
                 storm_count: int = 3, storm_window: float = 30.0,
                 log: Callable[[str, str], None] | None = None):
        self.estimator = estimator
        self.measurement_covariance = np.asarray(measurement_covariance, dtype=float)
        self.time_step = time_step
        self._window_ns = seconds_to_ns(window)
        self.storm_count, self._storm_window_ns = storm_count, seconds_to_ns(storm_window)
        self._log = log or (lambda level, message: None)
        self._data: deque = deque()  # (stamp, z or None, u) of the steps taken, oldest first
        self._trusted = None  # (stamp, x, P) of the last estimate consistent with its measurement
        self._resets: deque = deque()
        self.storms = 0
        self.in_storm = False

    def clear(self) -> None:
        """Forget everything (a new time base)."""
        self._data.clear()
        self._resets.clear()
        self._trusted = None
        self.in_storm = False

    def snapshot(self) -> tuple:
        """What the steps change (data, trusted estimate, resets, storms), for :meth:`restore`
        (a step taken again: snn_estimator.runners.provisional)."""
        return deque(self._data), self._trusted, deque(self._resets), self.storms, self.in_storm

    def restore(self, snapshot: tuple) -> None:
        data, self._trusted, resets, self.storms, self.in_storm = snapshot
        self._data, self._resets = deque(data), deque(resets)

    def record(self, stamp_ns: int, z: np.ndarray | None, u: np.ndarray) -> None:
        """The step from ``stamp_ns`` used measurement ``z`` (None: predicted over) and control ``u``."""
        self._data.append((stamp_ns, None if z is None else np.array(z, dtype=float), np.array(u, dtype=float)))
        while self._data and self._data[0][0] < stamp_ns - self._window_ns:
            self._data.popleft()

    def trusted(self, stamp_ns: int) -> None:
        """The estimate at ``stamp_ns`` (before its update) was consistent with its measurement."""
        est = self.estimator
        self._trusted = (stamp_ns, np.array(est.x_hat, dtype=float),
                         None if est.P is None else np.array(est.P, dtype=float))

    def restart_state(self, stamp_ns: int, z: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None, str]:
        """(x, P, source) at ``stamp_ns`` before the update with ``z`` (the measurement of this
        step, or None), from the data (see the module docstring)."""
        fitted = self._fit(stamp_ns, z)
        if fitted is not None:
            return (*fitted, 'least_squares')
        est = self.estimator
        if self._trusted is not None:
            x, covariance = self._propagate_trusted(stamp_ns)
            source = 'last_trusted'
        else:
            x = np.array(est.x_hat, dtype=float)
            x = np.where(np.isfinite(x), x, est.settings.initial_state)
            covariance, source = est.settings.initial_covariance, 'measurement'
        if z is not None and est.relinearises:  # the position, when the sample determines it
            position = est.measurement.position_of(z)
            if position is not None and np.isfinite(position).all():
                x[:3] = position
        elif z is not None:  # the measured states from the measurement, the others as above
            c = est.model.measurement_matrix if est.measurement is None else est.measurement.linear_matrix
            measured = np.flatnonzero(np.abs(c).sum(axis=0))
            x[measured] = np.linalg.pinv(c)[measured] @ z
        return x, covariance, source

    def _fit(self, stamp_ns: int, z: np.ndarray | None):
        rows = [(t, m, u) for t, m, u in self._data if m is not None and t < stamp_ns]
        if (len(rows) < MIN_FIT_MEASUREMENTS or not self.estimator.model.is_linear
                or self.estimator.relinearises):
            return None
        stamps = [t for t, _, _ in rows] + [stamp_ns]
        measurements = [m for _, m, _ in rows] + [z if z is not None else rows[-1][1]]  # the last is not fitted
        controls = [u for _, _, u in rows] + [rows[-1][2]]
        try:
            return least_squares_start(self.estimator.model, np.asarray(stamps) / NS, measurements, controls,
                                       self.measurement_covariance)
        except (ValueError, np.linalg.LinAlgError) as error:
            self._log('warning', f'no least-squares restart: {error}')
            return None

    def _propagate_trusted(self, stamp_ns: int):
        start, x, covariance = self._trusted
        x = np.array(x, dtype=float)
        model = self.estimator.model
        for t, _, u in self._data:
            if start <= t < stamp_ns:
                x = model.transition(x, u, self.time_step)
        inflated = (TRUST_INFLATION * covariance if covariance is not None
                    else self.estimator.settings.initial_covariance)
        return x, inflated

    def note_reset(self, stamp_ns: int) -> bool:
        """Count a reset at ``stamp_ns``; True when it makes (or continues) a reset storm."""
        self._resets.append(stamp_ns)
        while self._resets and self._resets[0] < stamp_ns - self._storm_window_ns:
            self._resets.popleft()
        storm = len(self._resets) >= self.storm_count
        if storm and not self.in_storm:
            self.storms += 1
            self._log('error', f'reset storm: {len(self._resets)} re-initialisations within '
                      f'{self._storm_window_ns / NS:.0f} s (t = {stamp_ns / NS:.1f} s): the filter cannot follow '
                      'this loop (model, measurement noise, controls?)')
        self.in_storm = storm
        return storm
