"""The truth plant: the model with process noise (exact ZOH), and the seeded Gaussian streams
every block draws from.

Random streams: component ``c`` of run ``b`` draws from ``default_rng([seed + b, c])``, c = 1
plant process noise, 2 sensor noise, 6 sensor dropouts (snn_estimator.plant.sensors; 3 and 5
are the estimator's: snn_estimator.spiking.network, snn_estimator.filters).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from snn_estimator.models import DT_CACHE_SIZE, StateSpaceModel
from snn_estimator.validation import as_matrix, as_vector, check_covariance

PLANT_STREAM = 1


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
