"""The sensors of the loop: Table 6's position sensor, a measurement model's sensor (limits,
dropouts) and several sensors fused on their own periods (random streams: truth.py); the
docking suite's two sensors.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from snn_estimator import defaults as D
from snn_estimator.measurements import DROPOUT, NON_FINITE, REASONS, VALID, MeasurementModel, make_model
from snn_estimator.models import StateSpaceModel
from snn_estimator.validation import as_matrix, check_covariance

from .truth import GaussianStream, matrix_sqrt

SENSOR_STREAM = 2


DROPOUT_STREAM = 6


class PositionSensor:
    """Noisy partial measurement ``z = C x + v``, v ~ N(0, R) per sample."""

    def __init__(self, model: StateSpaceModel, measurement_noise, seeds: Sequence[int] = (0,)):
        self.model = model
        m = model.n_meas
        self.r = check_covariance(as_matrix(measurement_noise, (m, m), 'measurement_noise (R)'),
                                  'measurement_noise (R)')
        self._root = matrix_sqrt(self.r)
        self._noise = GaussianStream(seeds, SENSOR_STREAM, m)

    def measure(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        return x @ self.model.measurement_matrix.T + self._noise.draw() @ self._root.T


class Measurement(NamedTuple):
    """One sample of a :class:`MeasurementSensor` for every run: ``z`` (runs, m), NaN where
    there is no measurement, and ``reason`` (runs,), a code of measurements.REASONS (0: valid)."""
    z: np.ndarray
    reason: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return self.reason == VALID

    def counts(self) -> dict[str, int]:
        """Samples without a measurement, by reason name (what a caller adds to its counters)."""
        codes = np.bincount(self.reason.astype(np.int64), minlength=len(REASONS))
        return {REASONS[code]: int(n) for code, n in enumerate(codes) if code != VALID and n}


class MeasurementSensor:
    """Noisy measurements ``z = h(x) + v``, v ~ N(0, R), of any measurement model, batched over
    runs, with validity (field of view, range limits: measurements.base) and random dropouts.

    The noise draws are PositionSensor's (stream 2, one row per sample whether or not the sample
    gives a measurement), so with the ``position`` model the numbers are PositionSensor's
    exactly, and a dropout or an invalid sample never shifts the noise of the later ones.
    Dropouts draw from their own stream (6), only when ``dropout_probability`` > 0. Angles are
    reported wrapped into [-pi, pi); a noisy range outside [min_range, max_range] is discarded.
    """

    def __init__(self, model: MeasurementModel, seeds: Sequence[int] = (0,), dropout_probability: float = 0.0):
        self.model = model
        self.r = model.noise
        self._root = matrix_sqrt(self.r)
        self._noise = GaussianStream(seeds, SENSOR_STREAM, model.dim)
        probability = float(dropout_probability)
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f'dropout_probability must be within [0, 1]; got {dropout_probability!r}')
        self.dropout_probability = probability
        self._dropouts = [np.random.default_rng([int(s), DROPOUT_STREAM]) for s in seeds]

    def measure(self, x) -> Measurement:
        x = np.asarray(x, dtype=float)
        model = self.model
        if model.has_limits:
            reason = model.validity(x).astype(np.int8)
            z = model.normalize(model.h(x) + self._draw(x))
            reason = np.where(reason == VALID, model.check_measured(z), reason).astype(np.int8)
        else:  # position: PositionSensor's two operations, and a finiteness check
            z = model.h(x) + self._noise.draw() @ self._root.T
            finite = np.isfinite(z).all(axis=-1)
            reason = (np.zeros(finite.shape, np.int8) if finite.all()
                      else np.where(finite, VALID, NON_FINITE).astype(np.int8))
        if self.dropout_probability > 0.0:
            lost = np.array([g.random() < self.dropout_probability for g in self._dropouts])
            reason[(reason == VALID) & lost] = DROPOUT
        if reason.any():
            z[reason != VALID] = np.nan
        return Measurement(z, reason)

    def _draw(self, x) -> np.ndarray:
        """One noise row per run: L v with L L^T = R, or R(x) per run where the model's noise
        depends on the state (a range noise growing with range: measurements.base)."""
        draw = self._noise.draw()
        if not self.model.state_dependent_noise:
            return draw @ self._root.T
        roots = np.linalg.cholesky(self.model.noise_at(x))
        return np.einsum('...ij,...j->...i', roots, draw)


#: Sensor i of a stacked measurement draws run b's noise with seed b + i * FUSED_SEED_OFFSET (over
#: ROS: the i-th sensor node's ``seed``), so two sensors never share noise draws.
FUSED_SEED_OFFSET = 1000


class FusedSensor:
    """The sensors of a :class:`snn_estimator.measurements.stacked.Stacked` measurement, each a
    :class:`MeasurementSensor` with its own limits, seeds (FUSED_SEED_OFFSET) and ``periods``
    (steps between two samples; 1: every step): ``z`` their samples side by side, NaN for a
    sensor that gave nothing this step; a run is valid when any sensor measured it. The
    reason of a run no sensor measured is the first sensor's."""

    def __init__(self, model, seeds: Sequence[int] = (0,), periods: Sequence[int] | None = None):
        self.model = model
        self.sensors = [MeasurementSensor(part, [int(s) + i * FUSED_SEED_OFFSET for s in seeds])
                        for i, part in enumerate(model.parts)]
        self.periods = [1] * len(self.sensors) if periods is None else [int(p) for p in periods]
        if len(self.periods) != len(self.sensors) or min(self.periods) < 1:
            raise ValueError(f'periods: one whole number of steps >= 1 per sensor, got {periods!r}')
        self.r = model.noise
        self.calls = 0
        self.counts = [np.zeros(len(seeds), dtype=np.int64) for _ in self.sensors]  # samples used, per sensor

    def measure(self, x) -> Measurement:
        x = np.asarray(x, dtype=float)
        z = np.full(x.shape[:-1] + (self.model.dim,), np.nan)
        reasons = []
        for i, (sensor, part, period) in enumerate(zip(self.sensors, self.model.slices, self.periods)):
            if self.calls % period:
                reasons.append(np.full(x.shape[:-1], DROPOUT, dtype=np.int8))
                continue
            sample = sensor.measure(x)
            z[..., part] = sample.z
            self.counts[i] += sample.valid
            reasons.append(sample.reason)
        self.calls += 1
        codes = np.stack(reasons, axis=-1)
        reason = np.where((codes == VALID).any(axis=-1), VALID, codes[..., 0]).astype(np.int8)
        return Measurement(z, reason)


class SamplePeriod:
    """A sensor's rate on a stream of truth stamps (ns): :meth:`due` is true for the first stamp
    at or after each multiple of ``period`` (s) counted from the first sample, so the average rate
    is 1/period whatever the truth's own steps (0: every stamp is a sample)."""

    def __init__(self, period: float):
        if not 0.0 <= float(period) < float('inf'):
            raise ValueError(f'measurement_period must be >= 0 s, got {period!r}')
        self.period_ns = int(round(float(period) * 1e9))
        self.next_ns: int | None = None

    def due(self, stamp_ns: int) -> bool:
        """Is ``stamp_ns`` a sample? (Advances the grid when it is.)"""
        if self.next_ns is not None and stamp_ns < self.next_ns:
            return False
        if self.period_ns:
            self.next_ns = (stamp_ns if self.next_ns is None else self.next_ns) + self.period_ns
            while self.next_ns <= stamp_ns:
                self.next_ns += self.period_ns
        return True

    def reset(self) -> None:
        """Start the grid again at the next stamp (the time base restarted)."""
        self.next_ns = None


def docking_sensors(field_of_view: bool = True, mounting_rotation=D.CLOSE_SENSOR_MOUNTING):
    """The docking suite's two sensors (defaults.DOCKING_LIDAR, DOCKING_CAMERA) on the chaser,
    turned by ``mounting_rotation`` (default defaults.CLOSE_SENSOR_MOUNTING: looking back at a
    target behind the chaser; the approach from behind uses the identity, boresight +V-bar):
    the LIDAR far (1.8 m - 3 km), the docking camera close (5 cm - 30 m; its field of view
    unless ``field_of_view`` is False). Each one's range limits hand the approach over: the
    LIDAR alone beyond 30 m, both between 30 m and 1.8 m, the camera alone inside."""
    lidar, camera = D.DOCKING_LIDAR, D.DOCKING_CAMERA
    mounting = {'mounting_rotation': tuple(mounting_rotation)}
    return (make_model('range_azimuth_elevation', lidar['noise'], range_noise_growth=lidar['range_noise_growth'],
                       min_range=lidar['min_range'], max_range=lidar['max_range'], **mounting),
            make_model('docking_camera', camera['noise'], min_range=camera['min_range'],
                       max_range=camera['max_range'],
                       **({'field_of_view': camera['field_of_view']} if field_of_view else {}), **mounting))


def design_noise(model, design_range: float) -> np.ndarray:
    """R_hat of a sensor whose noise grows with range: its R at ``design_range`` m on its
    boresight (Decision 46: the filters take one R per sensor)."""
    x = np.zeros(6)
    x[:3] = model.sign * (design_range * model.rotation[0] + model.offset)  # rho = (r, 0, 0)
    return model.noise_at(x)
