"""The spiking network of a batch of runs (Eq. 10-18): decoder, Gram matrix, thresholds, live
neurons, filtered spike trains r, potentials v and spike counts, plus encoding a state into it
and the weights of Eq. 16-22. The step itself is compiled (snn_estimator.filters.kernels)."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy.optimize import nnls

NETWORK_STREAM = 3  # rng stream id of the decoder and membrane noise (README, "Time and seeds")


def network_rng(seed: int) -> np.random.Generator:
    """The generator of a network's decoder and membrane noise for one run."""
    return np.random.default_rng([int(seed), NETWORK_STREAM])


class Network:
    """Arrays of ``runs`` networks of ``neurons`` LIF neurons coding ``n`` states (N = 0: the
    empty arrays a non-spiking filter hands the kernel)."""

    def __init__(self, seeds: Sequence[int], n: int, neurons: int, variance: float, silenced: Sequence[int]):
        runs = len(seeds)
        self.decoder = np.empty((runs, n, neurons))
        for b, seed in enumerate(seeds):  # D ~ N(0, var) per run
            self.decoder[b] = network_rng(seed).normal(0.0, math.sqrt(variance), (n, neurons))
        self.noise_rngs = [np.random.default_rng([seed, NETWORK_STREAM, 1]) for seed in seeds]
        self.gram = np.ascontiguousarray(np.einsum('bki,bkj->bij', self.decoder, self.decoder))
        self.thresholds = 0.5 * np.einsum('bki,bki->bi', self.decoder, self.decoder)  # T_i = ||D_i||^2 / 2
        self.r = np.zeros((runs, neurons))
        self.v = np.zeros((runs, neurons))
        self.alive = np.ones((runs, neurons), dtype=np.bool_)
        self.alive[:, list(silenced)] = False
        self.spikes = np.zeros((runs, neurons), dtype=np.int64)
        self.total_spikes = np.zeros(runs, dtype=np.int64)
        #: x_pred of network_coding deviation (x_hat = x_pred + S D r); zero for the paper's coding
        self.reference = np.zeros((runs, n))
        self.zero_noise = np.zeros((runs, neurons))
        #: ticks each neuron must still wait before it may fire again (spike_rule synchronous)
        self.refractory_left = np.zeros((runs, neurons), dtype=np.int64)

    @property
    def arrays(self) -> dict:
        """The kernel's network arguments by name (kernels.NETWORK)."""
        return {'decoder': self.decoder, 'gram': self.gram, 'thresholds': self.thresholds, 'alive': self.alive,
                'r': self.r, 'v': self.v, 'spikes': self.spikes, 'total_spikes': self.total_spikes,
                'reference': self.reference, 'refractory_left': self.refractory_left}

    def kernel_tuple(self) -> tuple:
        """The same arrays as the kernel's NETWORK tuple, in its order (the fire kernel's argument)."""
        return (self.decoder, self.gram, self.thresholds, self.alive, self.r, self.v, self.spikes,
                self.total_spikes, self.reference, self.refractory_left)

    def clear(self) -> None:
        self.r[:] = 0.0
        self.v[:] = 0.0
        self.spikes[:] = 0
        self.total_spikes[:] = 0
        self.reference[:] = 0.0
        self.refractory_left[:] = 0

    def noise(self, sigma: float) -> np.ndarray:
        """Membrane noise of one step for every run, N(0, sigma^2) per neuron."""
        neurons = self.r.shape[1]
        return np.stack([g.normal(0.0, sigma, neurons) for g in self.noise_rngs])

    def encode(self, run: int, target: np.ndarray) -> np.ndarray:
        """Set run ``run`` to represent ``target`` (scaled units): rates r >= 0 by NNLS over
        the live neurons, potentials v = D^T (target - D r) (zero coding error). Returns D r;
        ValueError (nothing changed) if the network overflows."""
        alive = self.alive[run]
        decoder = self.decoder[run]
        rates = np.zeros(decoder.shape[1])
        if np.any(alive):
            rates[alive], _ = nnls(decoder[:, alive], target, maxiter=50 * decoder.shape[1])
        with np.errstate(over='ignore', invalid='ignore'):
            decoded = decoder @ rates
            potentials = decoder.T @ (target - decoded)
        if not (np.isfinite(decoded).all() and np.isfinite(potentials).all()):
            raise ValueError(f'cannot encode {np.asarray(target).tolist()}: the network overflows')
        self.r[run] = rates
        self.v[run] = potentials
        self.refractory_left[run] = 0
        return decoded

    def retire(self, runs: np.ndarray) -> None:
        """Silence every neuron of the runs marked in ``runs`` for good, their rates and
        potentials zero (a run that diverged: it fires no more)."""
        self.alive[runs] = False
        self.r[runs] = 0.0
        self.v[runs] = 0.0

    def lose(self, wanted: np.ndarray) -> None:
        """Silence exactly the neurons marked in ``wanted`` (others revive): a newly silenced
        neuron's r_i and the synaptic input it sent (r_i times its Omega_f column) vanish."""
        for b in range(self.r.shape[0]):
            newly_dead = wanted & self.alive[b]
            if np.any(newly_dead):
                lost = self.r[b, newly_dead]
                self.v[b] += self.gram[b][:, newly_dead] @ lost
                self.r[b, newly_dead] = 0.0
            self.alive[b] = ~wanted


def weights(decoder: np.ndarray, scale: np.ndarray, a_d: np.ndarray, b_d: np.ndarray, gain: np.ndarray,
            c: np.ndarray, leak: float, thresholds: np.ndarray, coding: str = 'state') -> dict:
    """The network's matrices (Eq. 16-22) in scaled units: ``F = D^T S^-1 B_d``,
    ``Omega_s = D^T (S^-1 A_d S + lambda I) D``, ``Omega_f = -D^T D``,
    ``Omega_k = -D^T S^-1 K C S D``, ``F_k = D^T S^-1 K``, thresholds. With ``coding``
    deviation the prediction runs off the network: ``F = 0``, ``Omega_s = lambda D^T D``, and
    F_k reads z - C x_pred instead of z (docs/decisions.md, 13b)."""
    d = decoder
    if coding == 'deviation':
        a_d, b_d = np.zeros_like(a_d), np.zeros_like(b_d)
    a_scaled = a_d / scale[:, None] * scale[None, :]
    k_scaled = gain / scale[:, None]
    c_scaled = c * scale[None, :]
    return {
        'F': d.T @ (b_d / scale[:, None]),
        'Omega_s': d.T @ (a_scaled + leak * np.eye(len(scale))) @ d,
        'Omega_f': -d.T @ d,
        'Omega_k': -d.T @ k_scaled @ c_scaled @ d,
        'F_k': d.T @ k_scaled,
        'thresholds': thresholds.copy(),
        'decoder': d.copy(),
        'neurons': d.shape[1],
    }
