"""A spiking LQR: u = -K (x_hat - setpoint) computed by a spike-coding network.

The network (Boerlin et al. 2013, the autoencoder form of Eq. 13 with A = 0) represents its
input c = S^-1 (x_hat - setpoint) with N LIF neurons, c ~ D r, and the controller reads the
command from the filtered trains through the weights -K S D (3 x N): u = -K S D r. Per
control period (the same factored form and greedy rule as the estimator's network,
snn_estimator.spiking.chip)::

    x_read <- (1 - lambda dt) x_read,   e <- (1 - lambda dt) e + c_k - (1 - lambda dt) c_k-1
    spikes (greedy): while some D_i^T e > T_i = ||D_i||^2 / 2, the largest fires:
                     e -= D_i, x_read += D_i
    u_k = -K S x_read

so D r tracks c to within the coding error the thresholds allow (|D_i^T e| <= T_i for every
live neuron) and u differs from -K (x_hat - setpoint) by K S e. The decoder D ~ N(0, var)
comes from its own seed stream (6). Batched over runs like the estimators.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.optimize import nnls

from snn_estimator import defaults as D

CONTROLLER_TYPES = ('lqr', 'snn_lqr')
CONTROLLER_STREAM = 6  # rng stream of the controller network's decoder
#: Defaults: N neurons, leak 1/s, decoder variance, state scale (m and m/s per unit).
DEFAULT_NEURONS = 100
DEFAULT_LEAK = 0.001
DEFAULT_DECODER_VARIANCE = 1.0 / 15.0
DEFAULT_SCALE = D.RENDEZVOUS_STATE_SCALE


class SpikingLQR:
    """u = -K (x - setpoint) through a spike-coding network of ``neurons`` LIF neurons.

    ``gain`` K (nu x n); ``scale`` S (n,), the network encodes S^-1 (x - setpoint); ``leak``
    lambda (1/s); ``seeds`` one per run (decoder stream 6). :meth:`control` takes (runs, n) or
    (n,) and returns u of the same leading shape.
    """

    def __init__(self, gain, neurons: int = DEFAULT_NEURONS, leak: float = DEFAULT_LEAK,
                 scale=DEFAULT_SCALE, decoder_variance: float = DEFAULT_DECODER_VARIANCE,
                 seeds=(0,), max_spikes: int = 0):
        gain = np.array(gain, dtype=float, ndmin=2)
        if isinstance(neurons, bool) or int(neurons) != neurons or neurons < 1:
            raise ValueError(f'snn_lqr_neurons must be a positive integer, got {neurons!r}')
        if not (math.isfinite(leak) and leak >= 0.0):
            raise ValueError(f'snn_lqr_leak must be a finite number >= 0 (1/s), got {leak!r}')
        scale = np.asarray(scale, dtype=float)
        if scale.shape != (gain.shape[1],) or np.any(scale <= 0.0):
            raise ValueError(f'scale must be {gain.shape[1]} positive numbers, got {scale.tolist()}')
        if not np.isfinite(gain).all():
            raise ValueError('gain (K) must be finite')
        self.gain, self.neurons, self.leak, self.scale = gain, int(neurons), float(leak), scale
        self.seeds = [int(s) for s in seeds]
        runs, n = len(self.seeds), gain.shape[1]
        self.decoder = np.stack([np.random.default_rng([s, CONTROLLER_STREAM]).normal(
            0.0, math.sqrt(decoder_variance), (n, self.neurons)) for s in self.seeds])
        self._read = np.ascontiguousarray(self.decoder.transpose(0, 2, 1))
        self._gram = np.ascontiguousarray(np.einsum('bik,bjk->bij', self._read, self._read))
        self._thresholds = 0.5 * np.einsum('bii->bi', self._gram)
        self._max_spikes = int(max_spikes) or 1000 * self.neurons
        self._e = np.zeros((runs, n))
        self._x_read = np.zeros((runs, n))
        self._previous = np.zeros((runs, n))
        self._spikes = np.zeros((runs, self.neurons), dtype=np.int64)
        self.total_spikes = np.zeros(runs, dtype=np.int64)
        self.started = False

    @property
    def readout(self) -> np.ndarray:
        """The weights from the trains to the command, -K S D, (runs, nu, N)."""
        return -np.einsum('uk,bkn->bun', self.gain * self.scale[None, :], self.decoder)

    @property
    def spikes(self) -> np.ndarray:
        """Spikes per neuron of the last control, (runs, N)."""
        return self._spikes.copy()

    def reset(self, error=None) -> None:
        """Encode ``error`` = x - setpoint (default 0) at once: rates r >= 0 by NNLS, the rest
        of the coding error left in e."""
        runs, n = self._e.shape
        target = np.zeros((runs, n)) if error is None else np.broadcast_to(
            np.asarray(error, dtype=float).reshape(-1, n), (runs, n)) / self.scale
        for b in range(runs):
            rates, _ = nnls(self.decoder[b], target[b], maxiter=50 * self.neurons)
            self._x_read[b] = self.decoder[b] @ rates
            self._e[b] = target[b] - self._x_read[b]
        self._previous[:] = target
        self.started = True

    def control(self, error, dt: float) -> np.ndarray:
        """One control period: u = -K S D r after the network has tracked ``error`` = x_hat -
        setpoint (m, m/s) over ``dt`` s. The first call encodes it (no transient)."""
        error = np.asarray(error, dtype=float)
        single = error.ndim == 1
        error = error.reshape(-1, self._e.shape[1])
        if error.shape[0] != self._e.shape[0]:
            raise ValueError(f'expected {self._e.shape[0]} runs of {self._e.shape[1]} states, got {error.shape}')
        if not np.isfinite(error).all():
            raise ValueError('x_hat - setpoint must be finite')
        if not (math.isfinite(dt) and dt > 0.0 and self.leak * dt < 1.0):
            raise ValueError(f'dt must be > 0 with snn_lqr_leak * dt < 1, got dt = {dt}')
        if not self.started:
            self.reset(error)
        target = np.ascontiguousarray(error / self.scale)
        counts = track(1.0 - self.leak * dt, self._max_spikes, target, self._previous, self._read, self._gram,
                       self._thresholds, self._e, self._x_read, self._spikes)
        self.total_spikes += counts
        self._previous[:] = target
        u = -(self._x_read * self.scale) @ self.gain.T
        return u[0] if single else u


@numba.njit(cache=True)
def track(decay, max_spikes, target, previous, read, gram, thresholds, e, x_read, spikes):
    """One period of every run (see the module docstring); returns the spikes per run."""
    runs, n = e.shape
    neurons = read.shape[1]
    counts = np.zeros(runs, dtype=np.int64)
    v = np.empty(neurons)
    for b in range(runs):
        for k in range(n):
            x_read[b, k] *= decay
            e[b, k] = decay * e[b, k] + target[b, k] - decay * previous[b, k]
        for i in range(neurons):
            acc = 0.0
            for k in range(n):
                acc += read[b, i, k] * e[b, k]
            v[i] = acc
            spikes[b, i] = 0
        count = 0
        while count < max_spikes:
            best = -1
            best_over = 0.0
            for i in range(neurons):
                over = v[i] - thresholds[b, i]
                if over > best_over:
                    best_over = over
                    best = i
            if best < 0:
                break
            spikes[b, best] += 1
            count += 1
            for k in range(n):
                e[b, k] -= read[b, best, k]
                x_read[b, k] += read[b, best, k]
            for j in range(neurons):
                v[j] -= gram[b, best, j]
        counts[b] = count
    return counts
