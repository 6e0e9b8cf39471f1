"""Literal numpy implementations of the filters, for tests and the benchmark.

It forms the N x N weight matrices of Eq. 16-22 every step and integrates Eq. 15 with the
same forward-Euler scheme and spike rule as the compiled kernel, in plain numpy. It is slow
on purpose: it is the paper's algebra written out, so the fast kernel can be checked against
it (same spikes, same estimate) and timed beside it.
"""

from __future__ import annotations

import numpy as np

from .config import gain_noise_density
from .estimators import Estimator


class DenseSpikingFilter:
    """Single-run twin of a spiking :class:`Estimator`, sharing its decoder and initial state."""

    def __init__(self, estimator: Estimator):
        if not estimator.spiking or estimator.runs != 1:
            raise ValueError('needs a single-run spiking estimator')
        self.source = estimator
        self.model = estimator.model
        s = estimator.settings
        self.decoder = estimator._decoder[0].copy()
        self.scale = s.state_scale.copy()
        self.leak = s.leak_rate
        self.rule = s.spike_rule
        self.max_spikes = s.max_spikes_per_step
        self.thresholds = 0.5 * np.sum(self.decoder ** 2, axis=0)
        self.omega_f = -self.decoder.T @ self.decoder                      # Eq. 18
        self.r = estimator._r[0].copy()
        self.v = estimator._v[0].copy()
        self.P = estimator._p[0].copy()
        self.alive = estimator._alive[0].copy()
        self.gain_law = {0: 'kalman', 1: 'msif', 2: 'sif'}[estimator._gain_code]
        self.settings = s
        self.q_hat = s.q_hat
        self.r_hat = s.r_hat
        self.delta = s.boundary_layer
        self.method = s.discretization
        self.spikes = np.zeros(self.decoder.shape[1], dtype=np.int64)

    @property
    def x_hat(self) -> np.ndarray:
        return self.scale * (self.decoder @ self.r)                          # Eq. 12

    def gain(self, innovation: np.ndarray, dt: float) -> np.ndarray:
        c = self.model.measurement_matrix
        if self.gain_law == 'kalman':
            return self.P @ c.T @ np.linalg.inv(gain_noise_density(self.settings, dt))  # Eq. 5
        if self.gain_law == 'msif':
            p_zz = c @ self.P @ c.T + self.r_hat                              # Eq. 9 (corrected)
            return np.linalg.pinv(c) @ np.diag(np.minimum(np.diag(p_zz) / self.delta, 1.0))  # Eq. 8
        return np.linalg.pinv(c) @ np.diag(np.minimum(np.abs(innovation) / self.delta, 1.0))  # Eq. 7

    def step(self, z, u, dt: float) -> np.ndarray:
        model = self.model
        d, s_inv = self.decoder, 1.0 / self.scale
        x_hat = self.x_hat
        c = model.measurement_matrix
        k_gain = self.gain(z - c @ x_hat, dt)
        a_d, b_d = model.linearized_increment(x_hat, dt, self.method)
        a_scaled = s_inv[:, None] * a_d * self.scale[None, :]
        n = len(self.scale)
        f_weights = d.T @ (s_inv[:, None] * b_d)                               # Eq. 16
        omega_s = d.T @ (a_scaled + self.leak * np.eye(n)) @ d                 # Eq. 17
        omega_k = -d.T @ (s_inv[:, None] * k_gain) @ (c * self.scale[None, :]) @ d  # Eq. 19/21/23
        f_k = d.T @ (s_inv[:, None] * k_gain)                                  # Eq. 20/22/24
        if self.gain_law != 'sif':
            jac = model.jacobian(x_hat, u)
            self.P = self.P + dt * (jac @ self.P + self.P @ jac.T + self.q_hat
                                    - self.P @ c.T @ np.linalg.inv(gain_noise_density(self.settings, dt))
                                    @ c @ self.P)  # Eq. 6
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
        self.model = estimator.model
        s = estimator.settings
        self.x_hat = estimator._x_hat[0].copy()
        self.P = estimator._p[0].copy()
        self.gain_law = {0: 'kalman', 1: 'msif', 2: 'sif'}[estimator._gain_code]
        self.settings = s
        self.q_hat, self.r_hat, self.delta = s.q_hat, s.r_hat, s.boundary_layer
        self.method = s.discretization

    def step(self, z, u, dt: float) -> np.ndarray:
        c = self.model.measurement_matrix
        innovation = z - c @ self.x_hat
        r_density = gain_noise_density(self.settings, dt)  # the R of Eq. 5-6
        if self.gain_law == 'kalman':
            gain = self.P @ c.T @ np.linalg.inv(r_density)
        elif self.gain_law == 'msif':
            p_zz = c @ self.P @ c.T + self.r_hat
            gain = np.linalg.pinv(c) @ np.diag(np.minimum(np.diag(p_zz) / self.delta, 1.0))
        else:
            gain = np.linalg.pinv(c) @ np.diag(np.minimum(np.abs(innovation) / self.delta, 1.0))
        if self.gain_law != 'sif':
            jac = self.model.jacobian(self.x_hat, u)
            self.P = self.P + dt * (jac @ self.P + self.P @ jac.T + self.q_hat
                                    - self.P @ c.T @ np.linalg.inv(r_density) @ c @ self.P)
        self.x_hat = self.model.transition(self.x_hat, u, dt, self.method) + dt * gain @ innovation
        return self.x_hat
