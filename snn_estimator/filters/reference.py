"""Literal numpy implementations of the filters, for tests and the benchmark.

It forms the N x N weight matrices of Eq. 16-22 every step and integrates Eq. 15 with the
same forward-Euler scheme and spike rule as the compiled kernel, in plain numpy. It is slow
on purpose: it is the paper's algebra written out, so the fast kernel can be checked against
it (same spikes, same estimate) and timed beside it.

It is written from the paper and textbooks, not from the code it checks: the zero-order-hold
matrices come from scipy's matrix exponential (not models.zoh_matrices / linearized_increment),
the process noise of a step is a quadrature of its integral (not Van Loan's exponential), the
covariance step is the textbook two-stage Kalman step (Joseph update, then prediction) rather
than the kernel's one-stage predictor form, the nonlinear step is one classical RK4 step
written out, and the steady-state gain solves the discrete Riccati equation by the
structure-preserving doubling algorithm (not estimators.steady_state_gain and scipy's Schur
solver); the SIF's mean saturation is a numerical integral over the innovation density (not the
closed form).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.integrate
import scipy.linalg

from snn_estimator import gains
from snn_estimator.config import gain_noise_density
from snn_estimator.models import DT_CACHE_SIZE

from .estimators import Estimator


def zoh(a: np.ndarray, b: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(Phi, Gamma) = (e^{A dt}, int_0^dt e^{A s} ds B) from one exponential of [[A, B], [0, 0]] dt."""
    n, m = b.shape
    block = np.zeros((n + m, n + m))
    block[:n, :n], block[:n, n:] = a, b
    exp = scipy.linalg.expm(block * dt)
    return exp[:n, :n], exp[:n, n:]


def drift_matrices(model, x: np.ndarray, dt: float, method: str) -> tuple[np.ndarray, np.ndarray]:
    """(A_d, B_d) of the network's linearised drift: the Jacobian and B (Eq. 14, 16-17) for
    euler; their exact zero-order hold over the step, ((Phi - I)/dt, Gamma/dt), for exact."""
    n = model.n_state
    a = model.jacobian(np.zeros(n) if x is None else x, np.zeros(model.n_input))
    if method == 'euler':
        return a, model.input_matrix
    phi, gamma = zoh(a, model.input_matrix, dt)
    return (phi - np.eye(n)) / dt, gamma / dt


def rk4_step(f, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """One classical Runge-Kutta step of x' = f(x, u), u held."""
    k1 = f(x, u)
    k2 = f(x + 0.5 * dt * k1, u)
    k3 = f(x + 0.5 * dt * k2, u)
    k4 = f(x + dt * k3, u)
    return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def filter_transition(model, x: np.ndarray, u: np.ndarray, dt: float, method: str) -> np.ndarray:
    """The direct filters' prediction over dt: Euler of Eq. 3's f, or the exact (linear: ZOH;
    nonlinear: one RK4 step) solution."""
    if method == 'euler':
        return x + dt * model.f(x, u)
    if model.is_linear:
        phi, gamma = zoh(model.jacobian(np.zeros(model.n_state), np.zeros(model.n_input)), model.input_matrix, dt)
        return phi @ x + gamma @ u
    return rk4_step(model.f, x, u, dt)


def discrete_riccati_fixed_point(phi: np.ndarray, c: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """P with P = Phi P Phi^T + Q - Phi P C^T (C P C^T + R)^-1 C P Phi^T (the sampled step of
    Eq. 6 at rest, the one-step predictor's covariance), by the structure-preserving doubling
    algorithm (Chu, Fan, Lin & Wang 2004): A_{k+1} = A_k (I + G_k H_k)^-1 A_k, G_{k+1} = G_k +
    A_k (I + G_k H_k)^-1 G_k A_k^T, H_{k+1} = H_k + A_k^T H_k (I + G_k H_k)^-1 A_k from A_0 =
    Phi^T, G_0 = C^T R^-1 C, H_0 = Q; H_k -> P quadratically."""
    n = phi.shape[0]
    a, g, h = phi.T.copy(), c.T @ np.linalg.inv(r) @ c, q.copy()
    for _ in range(100):
        inverse = np.linalg.inv(np.eye(n) + g @ h)
        a_next = a @ inverse @ a
        g_next = g + a @ inverse @ g @ a.T
        h_next = h + a.T @ h @ inverse @ a
        converged = np.abs(h_next - h).max() <= 1e-15 * max(np.abs(h_next).max(), 1e-300)
        a, g, h = a_next, 0.5 * (g_next + g_next.T), 0.5 * (h_next + h_next.T)
        if converged:
            break
    return h


_NOISE_STEPS: dict = {}


def process_noise_step(a: np.ndarray, q: np.ndarray, dt: float) -> np.ndarray:
    """Q_d = int_0^dt e^{A s} Q e^{A^T s} ds, the covariance white noise of density Q adds over
    dt, by adaptive quadrature (the kernel takes Van Loan's exponential)."""
    key = (a.tobytes(), q.tobytes(), dt)
    cached = _NOISE_STEPS.get(key)
    if cached is None:
        integrand = lambda s: scipy.linalg.expm(a * s) @ q @ scipy.linalg.expm(a * s).T  # noqa: E731
        cached, _ = scipy.integrate.quad_vec(integrand, 0.0, dt, epsabs=0.0, epsrel=1e-12)
        cached = 0.5 * (cached + cached.T)
        if len(_NOISE_STEPS) >= DT_CACHE_SIZE:
            _NOISE_STEPS.clear()
        _NOISE_STEPS[key] = cached
    return cached


def sampled_step(source: Estimator, x_hat: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Phi, Q_d, R_d) of a step of ``dt`` from ``x_hat``: Phi = I + dt A_d (the ZOH of the
    Jacobian at x_hat, or I + A dt for euler), Q_d the process noise it adds (its integral for a
    linear model with exact discretization, else Q_hat dt) and R_d = R / dt, a sample's
    variance (R of Eq. 5-6)."""
    s, model = source.settings, source.model
    n = model.n_state
    a_d, _ = drift_matrices(model, x_hat, dt, s.discretization)
    if model.is_linear and s.discretization == 'exact':
        q_step = process_noise_step(model.jacobian(np.zeros(n), np.zeros(model.n_input)), s.q_hat, dt)
    else:
        q_step = s.q_hat * dt
    return np.eye(n) + dt * a_d, q_step, gain_noise_density(s, dt) / dt


def mean_saturation(sigma: float, delta: float) -> float:
    """E[min(|nu| / delta, 1)] for nu ~ N(0, sigma^2), by quadrature."""
    density = lambda x: math.exp(-0.5 * (x / sigma) ** 2) / (sigma * math.sqrt(2.0 * math.pi))  # noqa: E731
    inside, _ = scipy.integrate.quad(lambda x: 2.0 * x / delta * density(x), 0.0, delta, epsabs=0, epsrel=1e-13)
    outside = math.erfc(delta / (sigma * math.sqrt(2.0)))
    return inside + outside


def written_out_steady_state_gain(source: Estimator, dt: float) -> np.ndarray:
    """The constant gain of ``source``'s law at the fixed point of the sampled step of Eq. 6
    (Decision 28, 43), from the formulas: Kalman Phi P C^T (C P C^T + R_d)^-1 / dt (Eq. 5), MSIF
    C^+ sat(diag(C P C^T + R_hat)/delta) (Eq. 8-9), SIF C^+ E[sat(|nu|/delta)] over
    nu ~ N(0, C P C^T + R_hat) (Eq. 7), and the weighted law."""
    s, model = source.settings, source.model
    n = model.n_state
    c = model.measurement_matrix
    phi, q_step, r_sample = sampled_step(source, np.zeros(n), dt)
    p = discrete_riccati_fixed_point(phi, c, q_step, r_sample)
    kalman = phi @ p @ c.T @ np.linalg.inv(c @ p @ c.T + r_sample) / dt
    if source.gain_law == 'kalman':
        return kalman
    c_pinv = np.linalg.pinv(c)
    variance = np.diag(c @ p @ c.T + s.r_hat)
    if source.gain_law == 'sif':
        return c_pinv @ np.diag([mean_saturation(math.sqrt(v), d) for v, d in zip(variance, s.boundary_layer)])
    saturation = np.diag(np.minimum(variance / s.boundary_layer, 1.0))
    if source.gain_law == 'msif':
        return c_pinv @ saturation
    return p @ c.T @ np.linalg.inv(c @ p @ c.T) @ saturation  # msif_weighted


def measurement_terms(source: Estimator, x_hat: np.ndarray, z) -> tuple[np.ndarray, np.ndarray | None]:
    """(C, innovation) at ``x_hat``: the model's C and z - C x_hat, or with a measurement model
    its Jacobian H(x_hat) (Eq. 3-6: C = dh/dx at x_hat) and the wrapped residual z - h(x_hat)
    (Eq. 3-4); innovation None without z."""
    model = source.measurement
    if model is None:
        c = source.model.measurement_matrix
        return c, None if z is None else z - c @ x_hat
    c = model.jacobian(x_hat)
    return c, None if z is None else model.residual(z, model.h(x_hat))


def written_out_gain(source: Estimator, p: np.ndarray, innovation: np.ndarray, dt: float,
                     c: np.ndarray | None = None, x_hat: np.ndarray | None = None) -> np.ndarray:
    """The gain of ``source``'s kind from the formulas: its law's ``reference`` (Eq. 5, 7, 8-9
    and the remedies, written from the paper in snn_estimator.gains; the Kalman gain that of the
    sampled step from ``x_hat``), or the steady state. ``c``: the measurement Jacobian at the
    estimate (default: the model's C)."""
    s = source.settings
    if source.constant_gain:
        return written_out_steady_state_gain(source, dt)
    c = source.model.measurement_matrix if c is None else c
    phi, _, r_sample = sampled_step(source, np.zeros(len(p)) if x_hat is None else x_hat, dt)
    law = gains.law(source.gain_law)
    layer = {'mode': s.boundary_layer_mode} if getattr(law, 'VARIABLE_LAYER', False) else {}  # the MSIF laws (48)
    return law.reference(p, c, innovation, gains.SampledStep(phi, dt, r_sample), s.r_hat, s.boundary_layer, **layer)


def written_out_covariance_step(source: Estimator, p: np.ndarray, x_hat: np.ndarray, gain: np.ndarray,
                                dt: float, c: np.ndarray | None = None, measured: bool = True) -> np.ndarray:
    """One sampled step of the covariance law of ``source`` (Decision 43). Eq. 6 (riccati):
    the Kalman update of a sample of variance R_d in Joseph's form, P+ = (I - K_d C) P
    (I - K_d C)^T + K_d R_d K_d^T, K_d = P C^T (C P C^T + R_d)^-1, then the prediction
    Phi P+ Phi^T + Q_d. The gain's (gain): the error e' = (Phi - dt K C) e + dt K v - w of the
    step x' = Phi x + Gamma u + dt K (z - C x), so P' = (Phi - dt K C) P (Phi - dt K C)^T +
    dt^2 K R_d K^T + Q_d. Without a measurement: Phi P Phi^T + Q_d."""
    c = source.model.measurement_matrix if c is None else c
    phi, q_step, r_sample = sampled_step(source, x_hat, dt)
    n = len(p)
    if not measured or source.covariance_law == 'none':
        return p if source.covariance_law == 'none' else phi @ p @ phi.T + q_step
    if source.covariance_law == 'riccati':
        k_d = p @ c.T @ np.linalg.inv(c @ p @ c.T + r_sample)
        joseph = (np.eye(n) - k_d @ c) @ p @ (np.eye(n) - k_d @ c).T + k_d @ r_sample @ k_d.T
        return phi @ joseph @ phi.T + q_step
    closed = phi - dt * gain @ c
    return closed @ p @ closed.T + dt * dt * gain @ r_sample @ gain.T + q_step


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
        self.refractory_left = estimator.network.refractory_left[0].copy()
        # network_coding deviation: the network codes x_hat - x_pred, the prediction runs beside it
        self.deviation = s.network_coding == 'deviation'
        self.x_pred = estimator.prediction.copy() if self.deviation else np.zeros(n)

    @property
    def x_hat(self) -> np.ndarray:
        return self.x_pred + self.scale * (self.decoder @ self.r)            # Eq. 12 (+ x_pred)

    def step(self, z, u, dt: float) -> np.ndarray:
        model = self.model
        d, s_inv = self.decoder, 1.0 / self.scale
        x_hat = self.x_hat
        c, innovation = measurement_terms(self.source, x_hat, z)
        k_gain = written_out_gain(self.source, self.P, innovation, dt, c, x_hat)
        a_d, b_d = drift_matrices(model, x_hat, dt, self.method)
        if self.source.settings.network_drive == 'nonlinear':  # f(x_hat, u) instead of A(x_hat) x_hat
            a_d = np.zeros_like(a_d)
            nonlinear = (filter_transition(model, x_hat, u, dt, self.method) - x_hat) / dt
            b_d = np.zeros_like(b_d)
        else:
            nonlinear = np.zeros(len(self.scale))
        a_scaled = s_inv[:, None] * a_d * self.scale[None, :]
        n = len(self.scale)
        f_weights = d.T @ (s_inv[:, None] * b_d)                               # Eq. 16
        omega_s = d.T @ (a_scaled + self.leak * np.eye(n)) @ d                 # Eq. 17
        omega_k = -d.T @ (s_inv[:, None] * k_gain) @ (c * self.scale[None, :]) @ d  # Eq. 19/21/23
        f_k = d.T @ (s_inv[:, None] * k_gain)                                  # Eq. 20/22/24
        self.P = written_out_covariance_step(self.source, self.P, x_hat, k_gain, dt, c)
        # Eq. 14's K (z - h(x_hat)) with a nonlinear h: F_k takes the linear measurement that
        # gives the same innovation against C x_hat
        z_linear = innovation + c @ x_hat
        if self.deviation:  # the prediction leaves the network: no F u, no A in Omega_s, no f
            z_linear = z_linear - c @ self.x_pred                               # F_k reads z - C x_pred
            self.x_pred = self.x_pred + dt * (a_d @ x_hat + b_d @ u + nonlinear)
            f_weights, nonlinear = np.zeros_like(f_weights), np.zeros_like(nonlinear)
            omega_s = d.T @ (self.leak * np.eye(n)) @ d
        self.spikes[:] = 0
        if self.rule == 'synchronous':  # Eq. 15 without its leak, spread over the ticks
            self._ticks(dt * (f_weights @ u + (omega_s + omega_k) @ self.r + f_k @ z_linear
                              + d.T @ (s_inv * nonlinear)), dt)
            return self.x_hat
        v_dot = (-self.leak * self.v + f_weights @ u + (omega_s + omega_k) @ self.r + f_k @ z_linear  # Eq. 15
                 + d.T @ (s_inv * nonlinear))
        self.v = self.v + dt * v_dot
        self.r = self.r * (1.0 - self.leak * dt)                               # Eq. 11
        self._fire()
        return self.x_hat

    def _ticks(self, current: np.ndarray, dt: float) -> None:
        """The synchronous rule, written out: T ticks, each leaking v and r by (1 - lambda
        dt)^(1/T) and adding current / T; then every eligible neuron (live, not refractory, in
        its slot (t + i) mod K = 0) above (1 + w) T_i fires, all at once, with no comparison
        across neurons; their Omega_f columns act after the tick."""
        s = self.source.settings
        ticks, slots, refractory = s.ticks_per_sample, s.firing_slots, s.refractory_ticks
        thresholds = (1.0 + s.threshold_widening) * self.thresholds
        decay = (1.0 - self.leak * dt) ** (1.0 / ticks)
        index = np.arange(len(self.v))
        for tick in range(ticks):
            self.v = self.v * decay + current * (1.0 / ticks)
            self.r = self.r * decay
            fired = self.alive & (self.refractory_left == 0) & ((tick + index) % slots == 0) & (self.v > thresholds)
            room = self.max_spikes - int(self.spikes.sum())
            if fired.sum() > room:  # the cap: a tick's later neurons do not fire
                fired[np.flatnonzero(fired)[room:]] = False
            self.refractory_left = np.where(fired, refractory, np.maximum(self.refractory_left - 1, 0))
            self.spikes += fired
            self.r = self.r + fired
            self.v = self.v + self.omega_f @ fired.astype(float)

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
        """One step; ``z`` None: no measurement (K = 0)."""
        c, innovation = measurement_terms(self.source, self.x_hat, z)
        if z is None:
            gain = np.zeros((self.x_hat.size, c.shape[0]))
            innovation = np.zeros(c.shape[0])
        else:
            gain = written_out_gain(self.source, self.P, innovation, dt, c, self.x_hat)
        self.P = written_out_covariance_step(self.source, self.P, self.x_hat, gain, dt, c, measured=z is not None)
        self.x_hat = filter_transition(self.model, self.x_hat, u, dt, self.method) + dt * gain @ innovation
        return self.x_hat
