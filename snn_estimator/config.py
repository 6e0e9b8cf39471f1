"""Estimator configuration: one validated record shared by the ROS node and the offline tools."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import defaults as D
from .models import DISCRETIZATIONS, StateSpaceModel
from .validation import as_matrix, as_vector, check_choice, check_covariance, check_positive

SPIKE_RULES = ('greedy', 'one_per_step', 'all_above')
#: What R_hat is to Eq. 5-6: the spectral density they take, or the variance of each sample.
MEASUREMENT_NOISE_UNITS = ('spectral_density', 'per_sample')
#: How the gain evolves: per step from P or the innovation (the paper), or held at its steady
#: state (constant network weights, what a neuromorphic chip holds).
GAIN_SCHEDULES = ('time_varying', 'steady_state', 'switched')


@dataclass(frozen=True)
class EstimatorConfig:
    """Everything a filter needs besides the model. Defaults: the rendezvous scenario (Table 6)
    with this package's numerical choices (docs/decisions.md).

    Matrices may be given as a matrix, a flat row-major list, a diagonal vector or a scalar.
    """

    #: N, number of LIF neurons (Table 6: 200).
    neuron_count: int = D.RENDEZVOUS_NEURONS
    #: lambda, leak of membrane potentials and filtered spike trains, 1/s (Eq. 10-11; Table 6).
    leak_rate: float = D.RENDEZVOUS_LEAK_RATE
    #: delta, sliding boundary layer of the (M)SIF gain, one per measurement or a scalar (Eq. 7-8).
    boundary_layer: Any = D.RENDEZVOUS_BOUNDARY_LAYER
    #: Variance of the decoder entries, D ~ N(0, var) (Sec. 3.2: 1/15).
    decoder_variance: float = D.RENDEZVOUS_DECODER_VARIANCE
    #: Seed of the decoder (and membrane noise); run b of a batch uses seed + b.
    seed: int = 0
    #: Q, true process-noise spectral density (Table 6: 1e-12 I6); the filter uses scale * Q.
    process_noise: Any = D.RENDEZVOUS_PROCESS_NOISE
    #: R, true measurement-noise covariance per sample (Table 6: 1e-2 I3); the filter uses scale * R.
    measurement_noise: Any = D.RENDEZVOUS_MEASUREMENT_NOISE
    #: Q_hat = process_noise_scale * Q (Sec. 3.2: 0.9).
    process_noise_scale: float = D.RENDEZVOUS_PROCESS_NOISE_SCALE
    #: R_hat = measurement_noise_scale * R (Sec. 3.2: 5).
    measurement_noise_scale: float = D.RENDEZVOUS_MEASUREMENT_NOISE_SCALE
    #: R_hat in Eq. 5-6 (Kalman gain, Riccati): spectral_density uses it as printed; per_sample
    #: reads it as the variance of each sample and uses the sampled-data density R_hat dt. The
    #: MSIF's P^zz (Eq. 9) and the sensor always use the per-sample R.
    measurement_noise_units: str = 'spectral_density'
    #: P0, initial estimation-error covariance (not stated in the paper; docs/decisions.md, 6).
    initial_covariance: Any = D.RENDEZVOUS_INITIAL_COVARIANCE
    #: x_hat0, initial estimate (Table 6: equal to x0).
    initial_state: Any = D.RENDEZVOUS_X0
    #: Start each run from x_hat0 + L xi, L L^T = P0, xi ~ N(0, I) from the run's seed (stream
    #: 5), instead of x_hat0 itself: a filter that does not know the truth (the paper's Table 6
    #: starts at x_hat0 = x0, which hides how the filters converge).
    initial_state_dispersion: bool = False
    #: How neurons above threshold fire within one step: greedy | one_per_step | all_above.
    spike_rule: str = 'greedy'
    #: Diagonal of S: the network encodes x~ = S^-1 x (None: S = I, the paper's literal network).
    state_scale: Any = D.RENDEZVOUS_STATE_SCALE
    #: How the continuous equations are stepped: exact (ZOH of the linearised drift) | euler.
    discretization: str = 'exact'
    #: Standard deviation of the membrane noise eta, per sqrt(s) (Eq. 10; 0 = off).
    membrane_noise: float = 0.0
    #: Safety cap on spikes per step and run for the greedy rule (0: 1000 N).
    max_spikes_per_step: int = 0
    #: Indices of silenced (dead) neurons.
    silenced_neurons: tuple = field(default_factory=tuple)
    #: time_varying (the paper: K from P or the innovation every step) | steady_state (K held at
    #: its value at the fixed point of Eq. 6; linear models only).
    gain_schedule: str = 'time_varying'
    # -- the chip's network (snn_estimator/chip.py; validated there) --
    #: float64 | loihi: the spiking network in Loihi's integer formats (bit widths below).
    precision: str = 'float64'
    #: Signed weight mantissa bits, one shared exponent per weight matrix (Loihi: 8).
    weight_bits: int = 8
    #: Bits of the membrane potential and the synaptic currents (Loihi: 24).
    membrane_bits: int = 24
    #: Bits of the decay constants (Loihi: 12).
    decay_bits: int = 12
    #: Switch times of gain_schedule switched, s: weight set j holds over [t_j, t_j+1).
    schedule_times: tuple = (1.0, 10.0, 100.0)

    def replace(self, **changes) -> 'EstimatorConfig':
        """A copy with some fields changed (unknown names raise TypeError)."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class ResolvedConfig:
    """An :class:`EstimatorConfig` checked against a model, with arrays of the right shapes."""

    neuron_count: int
    leak_rate: float
    boundary_layer: np.ndarray
    decoder_variance: float
    seed: int
    q_hat: np.ndarray
    r_hat: np.ndarray
    measurement_noise_units: str
    initial_covariance: np.ndarray
    initial_state: np.ndarray
    initial_state_dispersion: bool
    spike_rule: str
    state_scale: np.ndarray
    discretization: str
    membrane_noise: float
    max_spikes_per_step: int
    silenced_neurons: tuple
    gain_schedule: str


def resolve(config: EstimatorConfig, model: StateSpaceModel) -> ResolvedConfig:
    """Validate ``config`` for ``model``; raise ValueError naming the field and the fix."""
    n, m = model.n_state, model.n_meas
    if isinstance(config.neuron_count, bool) or int(config.neuron_count) != config.neuron_count \
            or config.neuron_count <= 0:
        raise ValueError(f'neuron_count (N) must be a positive integer, got {config.neuron_count!r}')
    neurons = int(config.neuron_count)
    leak = check_positive(config.leak_rate, 'leak_rate (lambda, 1/s)', strict=False)
    delta = as_vector(config.boundary_layer, m, 'boundary_layer (delta)')
    if np.any(delta <= 0.0):
        raise ValueError(f'boundary_layer (delta) must be > 0, got {delta.tolist()}')
    variance = check_positive(config.decoder_variance, 'decoder_variance')
    q = check_covariance(as_matrix(config.process_noise, (n, n), 'process_noise (Q)'),
                         'process_noise (Q)', allow_singular=True)
    r = check_covariance(as_matrix(config.measurement_noise, (m, m), 'measurement_noise (R)'),
                         'measurement_noise (R)')
    q_scale = check_positive(config.process_noise_scale, 'process_noise_scale', strict=False)
    r_scale = check_positive(config.measurement_noise_scale, 'measurement_noise_scale')
    p0 = check_covariance(as_matrix(config.initial_covariance, (n, n), 'initial_covariance (P0)'),
                          'initial_covariance (P0)')
    x0 = as_vector(config.initial_state, n, 'initial_state (x_hat0)')
    rule = check_choice(config.spike_rule, SPIKE_RULES, 'spike_rule')
    if config.state_scale is None:
        scale = np.ones(n)
    else:
        scale = as_vector(config.state_scale, n, 'state_scale')
        if np.any(scale <= 0.0):
            raise ValueError(f'state_scale entries must be > 0, got {scale.tolist()}')
    method = check_choice(config.discretization, DISCRETIZATIONS, 'discretization')
    units = check_choice(config.measurement_noise_units, MEASUREMENT_NOISE_UNITS, 'measurement_noise_units')
    noise = check_positive(config.membrane_noise, 'membrane_noise', strict=False)
    cap = int(config.max_spikes_per_step)
    if cap < 0:
        raise ValueError(f'max_spikes_per_step must be >= 0 (0 = 1000 N), got {cap}')
    silenced = tuple(sorted({int(i) for i in config.silenced_neurons}))
    if silenced and (silenced[0] < 0 or silenced[-1] >= neurons):
        raise ValueError(f'silenced_neurons must be indices in [0, {neurons - 1}], got {silenced}')
    schedule = check_choice(config.gain_schedule, GAIN_SCHEDULES, 'gain_schedule')
    seed = int(config.seed)
    if seed < 0:
        raise ValueError(f'seed must be >= 0, got {seed}')
    return ResolvedConfig(
        neuron_count=neurons, leak_rate=leak, boundary_layer=delta, decoder_variance=variance,
        seed=seed, q_hat=q_scale * q, r_hat=r_scale * r, measurement_noise_units=units,
        initial_covariance=p0,
        initial_state=x0, initial_state_dispersion=bool(config.initial_state_dispersion), spike_rule=rule,
        state_scale=scale, discretization=method,
        membrane_noise=noise, max_spikes_per_step=cap or 1000 * neurons, silenced_neurons=silenced,
        gain_schedule=schedule)


def gain_noise_density(settings: ResolvedConfig, dt: float) -> np.ndarray:
    """The R of Eq. 5-6 (a spectral density): R_hat as printed, or R_hat dt when R_hat is the
    variance of each sample (then, while C P C^T << R_hat, a step of Eq. 5 moves the estimate
    as far as a discrete Kalman update with variance R_hat would; Estimator.check_time_step
    refuses a P0 that one Euler step of Eq. 6 would overshoot)."""
    if settings.measurement_noise_units == 'per_sample':
        return settings.r_hat * dt
    return settings.r_hat


def silenced_neurons(neurons: int, seed: int, fraction: float = 0.0, explicit=()) -> list[int]:
    """``explicit`` neuron indices plus a fraction of the N neurons chosen at random with the
    seed (stream 4): the one rule the ROS estimator's silenced_fraction and the campaigns use,
    so the same seed silences the same neurons everywhere."""
    explicit = [int(i) for i in explicit or ()]
    if any(i < 0 or i >= max(neurons, 1) for i in explicit):
        raise ValueError(f'silenced_neurons must be indices in [0, {neurons - 1}], got {explicit}')
    fraction = float(fraction or 0.0)
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f'silenced_fraction must be in [0, 1], got {fraction}')
    order = np.random.default_rng([int(seed), 4]).permutation(neurons)
    return sorted(set(explicit) | {int(i) for i in order[:int(round(fraction * neurons))]})
