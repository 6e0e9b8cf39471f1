"""How a filter joins a loop: the state it starts from. No ROS.

:meth:`snn_estimator.runners.filter_runner.FilterRunner.start` tries, as the start mode allows
(:data:`snn_estimator.catalog.START_MODES`; 'auto' in this order):

1. ``last_estimate``: an earlier estimator's newest estimate (a hot swap; the measurements since
   are then replayed) with its covariance if it is one (:meth:`StartUp.usable_covariance`);
2. ``history``: a least-squares fit of a full ``initial_fit_window`` of the measurement history
   (a restart after a crash; :func:`snn_estimator.runners.initialization.least_squares_start`,
   linear measurements z = C x only), the controls between them known or in force;
3. ``parameters``: the configured initial state at the first measurement, queued or next
   (:attr:`StartUp.waiting`).

This module sets the estimator's state; the runner queues, drops and replays the measurements.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np

from .gates import NS
from .initialization import least_squares_start


@dataclass
class History:
    """What the topics held when the filter joined: stamp (ns) -> value."""

    measurements: Mapping[int, np.ndarray]
    controls: Mapping[int, np.ndarray]
    #: Estimates an earlier estimator published: stamp -> (x, covariance or None).
    estimates: Mapping[int, tuple]


class StartUp:
    """Sets the estimator to the state a start begins from, and says whether the filter waits
    for its first measurement to start from the parameters."""

    def __init__(self, estimator, measurement_covariance, log: Callable[[str, str], None] | None = None):
        self._estimator = estimator
        self._measurement_covariance = np.asarray(measurement_covariance, dtype=float)
        self._log = log or (lambda level, message: None)
        self._waiting = False

    @property
    def waiting(self) -> bool:
        """The next measurement starts the filter from the parameters."""
        return self._waiting

    def wait_for_first_measurement(self) -> None:
        self._waiting = True

    def begun(self) -> None:
        """The filter started (whichever way)."""
        self._waiting = False

    def usable_covariance(self, blocks: np.ndarray | None) -> np.ndarray | None:
        """A received covariance if it is one (finite, symmetric, positive definite on each
        published block), else P0; None for a filter without a covariance."""
        if not self._estimator.has_covariance:
            return None
        p0 = self._estimator.settings.initial_covariance
        if blocks is None:
            return p0
        blocks = np.asarray(blocks, dtype=float)
        n = blocks.shape[0]
        half = n // 2
        if (np.all(np.isfinite(blocks)) and np.allclose(blocks, blocks.T)
                and np.all(np.linalg.eigvalsh(blocks[:half, :half]) > 0)
                and np.all(np.linalg.eigvalsh(blocks[half:, half:]) > 0)):
            return blocks
        return p0

    def from_estimate(self, x: np.ndarray, covariance: np.ndarray | None) -> bool:
        """Set the estimator to an earlier estimator's estimate (hot swap); False (logged) if it
        cannot be represented."""
        self._estimator.reset()
        try:
            self._estimator.set_state(x, self.usable_covariance(covariance))
        except ValueError as error:
            self._log('warning', f'cannot warm start from the earlier estimate: {error}')
            return False
        return True

    def fit_window(self, measured: Sequence[int], window_ns: int, dt_ns: int) -> list[int] | None:
        """The stamps (sorted) a least-squares start fits: the newest ``window_ns`` of the
        ``measured`` stamps; None when they do not span a full window (the filter did not join
        a running loop) or the filter's measurement is not z = C x."""
        if not measured or self._estimator.relinearises:
            return None
        newest = max(measured)
        stamps = sorted(t for t in measured if t >= newest - window_ns)
        if (newest - stamps[0]) < window_ns - dt_ns // 2:
            return None
        return stamps

    def from_fit(self, stamps: Sequence[int], measurements: Sequence[np.ndarray],
                 controls: Sequence[np.ndarray]) -> bool:
        """Set the estimator to the least-squares fit of ``measurements`` at ``stamps`` (ns; the
        controls held from each), at the newest stamp, whose measurement is left for the filter's
        next step; False (logged) if there is no fit."""
        estimator = self._estimator
        try:
            x, covariance = least_squares_start(estimator.model, np.asarray(stamps) / NS, measurements,
                                                controls, self._measurement_covariance)
            estimator.reset()
            estimator.set_state(x, covariance if estimator.has_covariance else None)
        except (ValueError, np.linalg.LinAlgError) as error:
            self._log('warning', f'no least-squares start from the history: {error}')
            return False
        return True
