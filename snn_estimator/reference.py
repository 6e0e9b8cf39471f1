"""Literal numpy implementations of the filters, for tests and the benchmark.

It forms the N x N weight matrices of Eq. 16-22 every step and integrates Eq. 15 with the
same forward-Euler scheme and spike rule as the compiled kernel, in plain numpy. It is slow
on purpose: it is the paper's algebra written out, so the fast kernel can be checked against
it (same spikes, same estimate) and timed beside it.
"""

from __future__ import annotations

import numpy as np

from . import gains
from .config import gain_noise_density
from .estimators import Estimator, steady_state_gain


def written_out_gain(source: Estimator, p: np.ndarray, innovation: np.ndarray, dt: float) -> np.ndarray:
    """The gain of ``source``'s kind from the formulas: its law's ``reference`` (Eq. 5, 7, 8-9
    and the remedies, written from the paper in snn_estimator.gains), or the steady state."""
    s = source.settings
    if source.constant_gain:
        return steady_state_gain(source.gain_law, source.model, s, dt)
    return gains.law(source.gain_law).reference(p, source.model.measurement_matrix, innovation,
                                                gain_noise_density(s, dt), s.r_hat, s.boundary_layer)


def written_out_covariance_step(source: Estimator, p: np.ndarray, jac: np.ndarray, gain: np.ndarray,
                                dt: float) -> np.ndarray:
    """One forward-Euler step of the covariance law of ``source`` (Eq. 6, or that of the gain)."""
    s = source.settings
    c = source.model.measurement_matrix
    density = gain_noise_density(s, dt)
    if source.covariance_law == 'riccati':
        return p + dt * (jac @ p + p @ jac.T + s.q_hat - p @ c.T @ np.linalg.inv(density) @ c @ p)  # Eq. 6
    if source.covariance_law == 'gain':
        closed = jac - gain @ c
        return p + dt * (closed @ p + p @ closed.T + s.q_hat + gain @ density @ gain.T)
    return p


class DenseSpikingFilter:
    """Single-run twin of a spiking :class:`Estimator`, sharing its decoder and initial state."""

    def __init__(self, estimator: Estimator):
        if not estimator.spiking or estimator.runs != 1:
            raise ValueError('needs a single-run spiking estimator')
        self.source = estimator
        self.model = estimator.model
        s = estimator.settings
        self.decoder = estimator.decoder.copy()
        self.scale = s.state_scale.copy()
        self.leak = s.leak_rate
        self.rule = s.spike_rule
        self.max_spikes = s.max_spikes_per_step
        self.thresholds = 0.5 * np.sum(self.decoder ** 2, axis=0)
        self.omega_f = -self.decoder.T @ self.decoder                      # Eq. 18
        self.r = estimator.rates.copy()
        self.v = estimator.potentials.copy()
        n = len(self.scale)
        self.P = estimator.P.copy() if estimator.has_covariance else np.zeros((n, n))
        self.alive = estimator.alive
        self.method = s.discretization
        self.spikes = np.zeros(self.decoder.shape[1], dtype=np.int64)

    @property
    def x_hat(self) -> np.ndarray:
        return self.scale * (self.decoder @ self.r)                          # Eq. 12

    def step(self, z, u, dt: float) -> np.ndarray:
        model = self.model
        d, s_inv = self.decoder, 1.0 / self.scale
        x_hat = self.x_hat
        c = model.measurement_matrix
        k_gain = written_out_gain(self.source, self.P, z - c @ x_hat, dt)
        a_d, b_d = model.linearized_increment(x_hat, dt, self.method)
        a_scaled = s_inv[:, None] * a_d * self.scale[None, :]
        n = len(self.scale)
        f_weights = d.T @ (s_inv[:, None] * b_d)                               # Eq. 16
        omega_s = d.T @ (a_scaled + self.leak * np.eye(n)) @ d                 # Eq. 17
        omega_k = -d.T @ (s_inv[:, None] * k_gain) @ (c * self.scale[None, :]) @ d  # Eq. 19/21/23
        f_k = d.T @ (s_inv[:, None] * k_gain)                                  # Eq. 20/22/24
        self.P = written_out_covariance_step(self.source, self.P, model.jacobian(x_hat, u), k_gain, dt)
        v_dot = -self.leak * self.v + f_weights @ u + (omega_s + omega_k) @ self.r + f_k @ z  # Eq. 15
        self.v = self.v + dt * v_dot
        self.r = self.r * (1.0 - self.leak * dt)                               # Eq. 11
        self.spikes[:] = 0
        self._fire()
        return self.x_hat

    def _fire(self) -> None:
        over = np.where(self.alive, self.v - self.thresholds, -np.inf)
        if self.rule == 'all_above':
            fired = over > 0.0
            self.spikes[fired] = 1
            self.r[fired] += 1.0
            self.v += self.omega_f @ fired.astype(float)
            return
        limit = 1 if self.rule == 'one_per_step' else self.max_spikes
        for _ in range(limit):
            best = int(np.argmax(over))
            if over[best] <= 0.0:
                break
            self.spikes[best] += 1
            self.r[best] += 1.0
            self.v += self.omega_f[:, best]
            over = np.where(self.alive, self.v - self.thresholds, -np.inf)


class DenseFilter:
    """Single-run numpy twin of a non-spiking :class:`Estimator` (Eq. 3-9), written out."""

    def __init__(self, estimator: Estimator):
        if estimator.spiking or estimator.runs != 1:
            raise ValueError('needs a single-run non-spiking estimator')
        self.source = estimator
        self.model = estimator.model
        self.x_hat = estimator.x_hat.copy()
        n = len(self.x_hat)
        self.P = estimator.P.copy() if estimator.has_covariance else np.zeros((n, n))
        self.method = estimator.settings.discretization

    def step(self, z, u, dt: float) -> np.ndarray:
        c = self.model.measurement_matrix
        innovation = z - c @ self.x_hat
        gain = written_out_gain(self.source, self.P, innovation, dt)
        self.P = written_out_covariance_step(self.source, self.P, self.model.jacobian(self.x_hat, u), gain, dt)
        self.x_hat = self.model.transition(self.x_hat, u, dt, self.method) + dt * gain @ innovation
        return self.x_hat
