"""The loop's blocks besides the estimator: the truth plant, the position sensor and the LQR.
The cw_plant, position_sensor and lqr_controller nodes wrap these (and load no numba); the
offline simulator (simulation.py) steps the same objects.

Random streams: component ``c`` of run ``b`` draws from ``default_rng([seed + b, c])``, c = 1
plant process noise, 2 sensor noise, 6 sensor dropouts (3 and 5 are the estimator's:
estimators.py).
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from snn_estimator.measurements import DROPOUT, NON_FINITE, REASONS, VALID, MeasurementModel
from snn_estimator.models import DT_CACHE_SIZE, StateSpaceModel
from snn_estimator.validation import as_matrix, as_vector, check_covariance

PLANT_STREAM = 1
SENSOR_STREAM = 2
DROPOUT_STREAM = 6
#: How the truth reads Eq. 1's process noise w (docs/decisions.md, 4):
#: spectral_density: continuous white noise of density Q, variance Q dt per step (default);
#: held_sample: w ~ N(0, Q) drawn once per step and held over it (what a simulator that adds
#: ``sqrt(Q) randn dt`` produces), variance ~ Q dt^2 per step.
TRUTH_NOISE_READINGS = ('spectral_density', 'held_sample')


def matrix_sqrt(covariance: np.ndarray) -> np.ndarray:
    """A square root L with L L^T = covariance (works for singular PSD matrices)."""
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    return vectors * np.sqrt(np.clip(values, 0.0, None))


class GaussianStream:
    """Per-run N(0, I) draws, taken from each run's generator in blocks.

    Drawing a block of k rows gives the same numbers as k single draws, so a single ROS node
    and an offline batch see the same noise for the same seed.
    """

    def __init__(self, seeds: Sequence[int], stream: int, width: int, block: int = 512):
        self._rngs = [np.random.default_rng([int(s), stream]) for s in seeds]
        self._width = width
        self._block = block
        self._buffer = np.empty((len(self._rngs), 0, width))
        self._next = 0

    def draw(self) -> np.ndarray:
        """One row per run, shape (runs, width)."""
        if self._next >= self._buffer.shape[1]:
            self._refill()
        row = self._buffer[:, self._next, :]
        self._next += 1
        return row

    def _refill(self) -> None:
        self._buffer = np.stack([g.standard_normal((self._block, self._width)) for g in self._rngs])
        self._next = 0

    def take(self, count: int) -> np.ndarray:
        """The next ``count`` rows per run, shape (runs, count, width), C-contiguous: exactly
        what ``count`` calls of :meth:`draw` would give (the compiled loop's noise)."""
        out = np.empty((len(self._rngs), count, self._width))
        filled = min(count, self._buffer.shape[1] - self._next)  # what is left of the block
        out[:, :filled] = self._buffer[:, self._next:self._next + filled]
        self._next += filled
        if filled < count:  # the rest straight from the generators: no block held
            for b, generator in enumerate(self._rngs):
                out[b, filled:] = generator.standard_normal((count - filled, self._width))
        return out


class Plant:
    """Truth propagation: exact (ZOH) for linear models, RK4 otherwise, plus process noise
    of spectral density Q (Van Loan discretisation)."""

    #: RK4 steps per sample for nonlinear truth models.
    substeps = 4

    def __init__(self, model: StateSpaceModel, x0, process_noise, seeds: Sequence[int] = (0,),
                 noise_reading: str = 'spectral_density'):
        if noise_reading not in TRUTH_NOISE_READINGS:
            raise ValueError(f"truth_noise must be one of {', '.join(TRUTH_NOISE_READINGS)}; "
                             f'got {noise_reading!r}')
        self.noise_reading = noise_reading
        self.model = model
        n = model.n_state
        self.runs = len(seeds)
        self.x = np.broadcast_to(as_vector(x0, n, 'x0'), (self.runs, n)).copy()
        self.q = check_covariance(as_matrix(process_noise, (n, n), 'process_noise (Q)'),
                                  'process_noise (Q)', allow_singular=True)
        self._noise = GaussianStream(seeds, PLANT_STREAM, n)
        self._sqrt_cache: dict[float, np.ndarray] = {}
        self.time = 0.0
        #: The control applied in the last step and the steps it had to be clipped in (never:
        #: the CW truth has no thrust limit; the Basilisk truth does).
        self.applied = np.zeros((self.runs, model.n_input))
        self.saturated_steps = np.zeros(self.runs, dtype=np.int64)

    def step(self, u, dt: float) -> np.ndarray:
        """Advance by ``dt`` with ``u`` held; returns x, shape (runs, n)."""
        u = np.asarray(u, dtype=float).reshape(self.runs, -1)
        root = self._sqrt_cache.get(dt)
        if root is None:
            if len(self._sqrt_cache) >= 64:  # bounded: steps off a grid give a new dt every step
                self._sqrt_cache.clear()
            root = matrix_sqrt(self.step_noise_covariance(dt))
            if len(self._sqrt_cache) >= DT_CACHE_SIZE:
                self._sqrt_cache.clear()
            self._sqrt_cache[dt] = root
        self.x = (self.model.transition(self.x, u, dt, 'exact', substeps=self.substeps)
                  + self._noise.draw() @ root.T)
        self.applied = u
        self.time += dt
        return self.x


    def step_noise_covariance(self, dt: float) -> np.ndarray:
        """Covariance of the process noise one step of ``dt`` adds to the state: Van Loan
        (``Q dt`` for a nonlinear model) for spectral_density; for held_sample, G Q G^T with
        G = integral_0^dt Phi(s) ds (``dt I`` for a nonlinear model), i.e. ~ Q dt^2."""
        if self.noise_reading == 'spectral_density':
            return self.model.process_noise_discrete(self.q, dt)
        n = self.model.n_state
        if self.model.is_linear:
            from snn_estimator.models import zoh_matrices
            _, g = zoh_matrices(self.model.jacobian(np.zeros(n), np.zeros(self.model.n_input)), np.eye(n), dt)
        else:
            g = dt * np.eye(n)
        return g @ self.q @ g.T


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
            z = model.normalize(model.h(x) + self._noise.draw() @ self._root.T)
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


def lqr_gain(model: StateSpaceModel, state_weight, input_weight) -> np.ndarray:
    """Continuous-time LQR gain K (u = -K x, Eq. 42) from python-control, for a linear model."""
    if not model.is_linear:
        raise ValueError('LQR design needs a linear model')
    n, m = model.n_state, model.n_input
    q = check_covariance(as_matrix(state_weight, (n, n), 'lqr_state_weight (Qc)'),
                         'lqr_state_weight (Qc)', allow_singular=True)
    r = check_covariance(as_matrix(input_weight, (m, m), 'lqr_input_weight (Rc)'),
                         'lqr_input_weight (Rc)')
    a = model.jacobian(np.zeros(n), np.zeros(m))
    import control  # imported here: python-control loads matplotlib, which no other core path needs
    try:
        gain, _, _ = control.lqr(a, model.input_matrix, q, r)
    except Exception as error:  # python-control raises several types for an unsolvable ARE
        raise ValueError(f'LQR design failed for these weights: {error}') from error
    return np.asarray(gain, dtype=float)


def lqr_control(gain: np.ndarray, x_hat) -> np.ndarray:
    """u = -K x_hat (Eq. 42), batched."""
    return -(np.asarray(x_hat, dtype=float) @ gain.T)
