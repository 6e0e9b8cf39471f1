"""The estimator's parameters, each written once: name, type, unit, range, paper equation,
whether it may change at runtime, default, meaning.

Everything else is derived from :data:`FIELDS`: :class:`~snn_estimator.config.EstimatorConfig`
(its fields and defaults), the validation of :func:`~snn_estimator.config.resolve`, the set
:attr:`Estimator.RETUNABLE <snn_estimator.filters.estimators.Estimator.RETUNABLE>`, the estimator's ROS
parameter table in ``scenario_nodes/parameter_tables.py`` (descriptors, ``read_only``), and from that
``config/*.yaml`` and ``docs/parameters.md``. Adding a parameter is one entry here (and the code
that uses it).

numpy only: the ROS parameter tables import this without the filters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from . import defaults as D
from .validation import as_matrix, as_vector, check_choice, check_covariance

SPIKE_RULES = ('greedy', 'one_per_step', 'all_above', 'synchronous')
#: What R_hat is to Eq. 5-6: the spectral density they take, or the variance of each sample.
MEASUREMENT_NOISE_UNITS = ('spectral_density', 'per_sample')
#: How the gain evolves: per step from P or the innovation (the paper), or held at its steady
#: state (constant network weights, what a neuromorphic chip holds).
GAIN_SCHEDULES = ('time_varying', 'steady_state', 'switched')
#: The MSIF gains' boundary layer (docs/decisions.md, 48): fixed, delta as given (Eq. 8: the
#: paper); variable, delta_j sized each step from P so that inside the layer the gain is the
#: sampled Kalman gain (Gadsden & Habibi's variable boundary layer), saturated outside it.
BOUNDARY_LAYER_MODES = ('fixed', 'variable')
#: The spiking network's arithmetic: float64, or Loihi's integer formats (snn_estimator/spiking/chip.py).
PRECISIONS = ('float64', 'loihi')
#: What the spiking network integrates as its prediction (docs/decisions.md, 13): linearized,
#: A(x_hat) x_hat + B u with A the Jacobian (Eq. 14, 17: the paper's network); nonlinear, f(x_hat, u)
#: (Eq. 3's drift, what the non-spiking twin integrates). The same for a linear model.
NETWORK_DRIVES = ('linearized', 'nonlinear')
#: What the spiking network codes (docs/decisions.md, 13b): state, the estimate itself (x_hat = S D r,
#: Eq. 12: the paper's network); deviation, the estimate's deviation from its model prediction
#: (x_hat = x_pred + S D r, x_pred advanced off the network by A_d x_hat + B_d u or f).
NETWORK_CODINGS = ('state', 'deviation')
#: How the continuous equations are stepped (models.DISCRETIZATIONS, repeated here so that
#: the parameter tables need not load the models; a test keeps them equal).
DISCRETIZATIONS = ('exact', 'euler')
#: The model the filter predicts with (models.DYNAMICS_MODELS, repeated for the same reason).
DYNAMICS_MODELS = ('cw', 'nonlinear_circular', 'ss_j2')

#: Value types. ``vector`` has ``size`` entries (n states or m measurements; a scalar is
#: broadcast), ``matrix`` is size x size (a matrix, a flat row-major list, a diagonal or a scalar),
#: ``indices`` a set of neuron indices, ``times`` an increasing list of times (s).
TYPES = ('integer', 'real', 'bool', 'choice', 'vector', 'matrix', 'indices', 'times')


@dataclass(frozen=True)
class Field:
    """One estimator parameter."""

    name: str
    type: str
    default: Any
    meaning: str
    unit: str = ''
    symbol: str = ''
    equation: str = ''
    #: Range: ``low`` <= value (< when ``strict``) <= ``high``; for vectors, every entry.
    low: float | None = None
    high: float | None = None
    strict: bool = False
    choices: tuple = ()
    #: May change between steps (Estimator.retune; a ROS parameter that is not read-only).
    runtime: bool = False
    #: vector/matrix: 'n' (states) or 'm' (measurements).
    size: str = ''
    #: matrix: may be singular (a semi-definite covariance).
    singular: bool = False

    @property
    def label(self) -> str:
        """How error messages name it: ``leak_rate (lambda, 1/s)``."""
        extra = ', '.join(part for part in (self.symbol, self.unit) if part)
        return f'{self.name} ({extra})' if extra else self.name

    @property
    def text(self) -> str:
        """Meaning, unit and equation in one line (ROS descriptors, YAML comments, docs)."""
        text = f'{self.symbol}, {self.meaning}' if self.symbol else self.meaning
        if self.unit:
            text += f', {self.unit}'
        return text + (f' ({self.equation})' if self.equation else '')

    def check(self, value, dims: dict):
        """``value`` checked and converted (a float, an array of the right shape, ...), or a
        ValueError naming the field and what to fix."""
        kind = self.type
        if kind == 'choice':
            return check_choice(value, self.choices, self.name)
        if kind == 'bool':
            return bool(value)
        if kind == 'indices':
            return tuple(sorted({int(i) for i in value or ()}))
        if kind == 'times':
            times = tuple(float(t) for t in value or ())
            if not all(np.isfinite(times)) or any(b <= a for a, b in zip(times, times[1:])):
                raise ValueError(f'{self.label} must be finite and increasing, got {list(times)}')
            self._check_range(np.array(times), list(times))
            return times
        if kind == 'integer':
            if isinstance(value, bool) or int(value) != value:
                raise ValueError(f'{self.label} must be an integer, got {value!r}')
            self._check_range(np.array([int(value)]), value)
            return int(value)
        if kind == 'real':
            number = float(value)
            if not np.isfinite(number):
                raise ValueError(f'{self.label} must be finite, got {value!r}')
            self._check_range(np.array([number]), value)
            return number
        size = dims[self.size]
        if kind == 'vector':
            array = as_vector(value, size, self.label)
            self._check_range(array, array.tolist())
            return array
        matrix = as_matrix(value, (size, size), self.label)
        return check_covariance(matrix, self.label, allow_singular=self.singular)

    def _check_range(self, values: np.ndarray, shown) -> None:
        low, high = self.low, self.high
        if low is not None and (np.any(values < low) or (self.strict and np.any(values == low))):
            raise ValueError(f'{self.label} must be {">" if self.strict else ">="} {low:g}, got {shown!r}')
        if high is not None and np.any(values > high):
            raise ValueError(f'{self.label} must be <= {high:g}, got {shown!r}')

    @property
    def parameter_default(self):
        """The default as a ROS parameter holds it: arrays as flat float lists, no indices as
        None (an integer array without a default)."""
        value = self.default
        if self.type in ('vector', 'matrix', 'times'):
            return [float(v) for v in np.ravel(value)]
        if self.type == 'indices':
            return list(value) or None
        return float(value) if self.type == 'real' else value

    def from_parameter(self, value):
        """A ROS parameter value back as the core takes it (arrays as lists, unset as default)."""
        if value is None:
            return self.default
        if self.type in ('vector', 'matrix'):
            return list(value)
        if self.type == 'indices':
            return tuple(int(i) for i in value)
        if self.type == 'times':
            return tuple(float(t) for t in value)
        return value


#: Every estimator parameter, in the order the tables list them. Defaults: the rendezvous
#: scenario (Table 6) with this package's numerical choices (docs/decisions.md).
FIELDS: tuple[Field, ...] = (
    Field('neuron_count', 'integer', D.RENDEZVOUS_NEURONS, 'number of LIF neurons', symbol='N',
          equation='Table 6: 200', low=1, high=100000),
    Field('leak_rate', 'real', D.RENDEZVOUS_LEAK_RATE, 'leak of the membrane potentials v and the '
          'filtered spike trains r', unit='1/s', symbol='lambda', equation='Eq. 10-11; Table 6: 0.001',
          low=0.0, runtime=True),
    Field('boundary_layer', 'vector', D.RENDEZVOUS_BOUNDARY_LAYER, 'sliding boundary layer of the '
          '(M)SIF gain, per measured axis or one for all, in the units of what the gain divides by it: '
          'diag(P^zz) for the MSIF gains (m^2 on position), |z - z_hat| for the SIF (m)', symbol='delta',
          equation='Eq. 7-8, 21-24; Table 6: 0.1', low=0.0, strict=True, size='m', runtime=True),
    Field('boundary_layer_mode', 'choice', 'fixed', 'the MSIF gains\' boundary layer: fixed, delta '
          '(Eq. 8, the paper); variable, delta_j = P^zz_jj dt (C P C^T + R_d)_jj / (C P C^T)_jj each '
          'step, so that inside the layer the correction is the Kalman gain of the sampled step '
          '(the weighted MSIF: K; the C^+ forms: C K) and outside it saturates as Eq. 8 does '
          '(Gadsden & Habibi 2013; docs/decisions.md, 48); time_varying gains only',
          equation='Eq. 8, 21-22 (variable: not in the paper)', choices=BOUNDARY_LAYER_MODES),
    Field('decoder_variance', 'real', D.RENDEZVOUS_DECODER_VARIANCE, 'Variance of the decoder '
          'entries, D ~ N(0, var)', equation='Sec. 3.2: 1/15', low=0.0, strict=True),
    Field('seed', 'integer', 0, 'Seed of the decoder, membrane noise and dispersed start (streams 3 '
          'and 5); run b of a batch uses seed + b', low=0),
    Field('process_noise', 'matrix', D.RENDEZVOUS_PROCESS_NOISE, 'true process-noise density the '
          "filter's Q_hat is scaled from", unit='(m/s^2)^2/Hz', symbol='Q', equation='Table 6: 1e-12 I6',
          size='n', singular=True),
    Field('measurement_noise', 'matrix', D.RENDEZVOUS_MEASUREMENT_NOISE, 'true measurement-noise covariance per '
          "sample the filter's R_hat is scaled from",
          unit='m^2', symbol='R', equation='Table 6: 1e-2 I3', size='m'),
    Field('process_noise_scale', 'real', D.RENDEZVOUS_PROCESS_NOISE_SCALE, 'Q_hat = scale * Q',
          equation='Sec. 3.2: 0.9', low=0.0, runtime=True),
    Field('measurement_noise_scale', 'real', D.RENDEZVOUS_MEASUREMENT_NOISE_SCALE, 'R_hat = scale * R',
          equation='Sec. 3.2: 5', low=0.0, strict=True, runtime=True),
    Field('measurement_noise_units', 'choice', 'spectral_density', 'What R_hat is to the Kalman gain '
          'and Riccati equation: spectral_density (as printed) or per_sample (variance of each '
          'sample: Eq. 5-6 use R_hat * time_step); the MSIF P^zz (Eq. 9) always uses R_hat per sample',
          choices=MEASUREMENT_NOISE_UNITS),
    Field('gain_schedule', 'choice', 'time_varying', 'time_varying: the gain follows P or the '
          'innovation every step (the paper); steady_state: held at its value at the fixed point '
          'of Eq. 6 (constant network weights; linear models only)', choices=GAIN_SCHEDULES),
    Field('network_drive', 'choice', 'linearized', "the spiking network's prediction: linearized, "
          'A(x_hat) x_hat + B u (Eq. 14, 17); nonlinear, f(x_hat, u) as the twin integrates (Eq. 3); '
          'the same for a linear model (docs/decisions.md, 13)', choices=NETWORK_DRIVES),
    Field('network_coding', 'choice', 'state', 'what the spiking network codes: state, the estimate '
          'x_hat = S D r (Eq. 12: the paper); deviation, the deviation from the model prediction, '
          'x_hat = x_pred + S D r with x_pred advanced off the network by A x_hat + B u (or f) and the '
          'network integrating only the correction K nu (Eq. 14-17 without A and B; far fewer spikes; '
          'float64 network only; docs/decisions.md, 13b)', choices=NETWORK_CODINGS),
    # the chip's network (snn_estimator/spiking/chip.py: formats from Davies et al. 2018 and Lava's
    # bit-accurate LIF model; docs/decisions.md and results/neuromorphic.md)
    Field('precision', 'choice', 'float64', "the spiking network's arithmetic: float64, or loihi "
          "(Loihi's integer formats with the bit widths below; needs gain_schedule steady_state or "
          'switched)', choices=PRECISIONS),
    Field('weight_bits', 'integer', 8, 'signed weight mantissa bits, one shared exponent per weight '
          'matrix (Loihi: 8); with spike_rule synchronous one per row of the state compartments\' weights, '
          'Omega_f held exactly (docs/decisions.md, 64-65)', low=2, high=24),
    Field('membrane_bits', 'integer', 24, 'bits of the membrane potentials and synaptic currents '
          '(Loihi: 24)', low=8, high=52),
    Field('decay_bits', 'integer', 12, 'bits of the decay constants (Loihi: 12)', low=4, high=24),
    Field('schedule_times', 'times', (1.0, 10.0, 100.0), 'switch times of gain_schedule switched: '
          'weight set j holds over [t_j, t_j+1)', unit='s', low=0.0),
    Field('initial_covariance', 'matrix', D.RENDEZVOUS_INITIAL_COVARIANCE, 'initial error '
          'covariance (not in the paper; docs/decisions.md, 6)', unit='m^2 and (m/s)^2', symbol='P0',
          size='n'),
    Field('initial_state', 'vector', D.RENDEZVOUS_X0, 'initial estimate', unit='m and m/s',
          symbol='x_hat0', equation='Table 6: x0', size='n'),
    # One default for core and ROS: x_hat0 is the estimate the user gives, so a filter starts
    # there (and the paper's tables, Table 6: x_hat0 = x0). Dispersing it is a simulation's
    # choice, where initial_state is the simulated truth: config/rendezvous.yaml (the demo's
    # scenario, whose plant starts at that same state) and the dispersed experiments turn it on
    # (docs/decisions.md, 15).
    Field('initial_state_dispersion', 'bool', False, 'Start each run from x_hat0 + L xi (L L^T = P0, '
          'xi ~ N(0, I) from the seed, stream 5), not from x_hat0: the filter does not know the '
          'truth (the paper starts at the truth: false)'),
    Field('spike_rule', 'choice', 'greedy', 'How neurons above threshold fire in one step: greedy (the '
          'largest overshoot first until none is above; a global comparison), one_per_step, all_above '
          '(all at once, once), synchronous (a chip\'s local rule over ticks_per_sample ticks; '
          'docs/decisions.md, 58)', choices=SPIKE_RULES),
    # the synchronous rule's parameters (docs/decisions.md, 58-59; defaults from results/neuromorphic.md)
    Field('ticks_per_sample', 'integer', D.SYNCHRONOUS_TICKS, 'spike_rule synchronous: chip ticks per step; '
          'each tick every neuron integrates 1/T of the step\'s input and fires on its own potential',
          symbol='T', low=1, high=100000, runtime=True),
    Field('threshold_widening', 'real', D.SYNCHRONOUS_WIDENING, 'spike_rule synchronous: thresholds '
          '(1 + w) ||D_i||^2 / 2 (Calaim et al. 2022: a wider box against ping-pong)', symbol='w',
          low=0.0, runtime=True),
    Field('refractory_ticks', 'integer', D.SYNCHRONOUS_REFRACTORY, 'spike_rule synchronous: ticks a neuron '
          'may not fire after a spike', symbol='R', low=0, runtime=True),
    Field('firing_slots', 'integer', D.SYNCHRONOUS_SLOTS, 'spike_rule synchronous: neuron i may fire only '
          'in the ticks t of the step with (t + i) mod K = 0 (1: every tick)', symbol='K', low=1,
          runtime=True),
    Field('state_scale', 'vector', D.RENDEZVOUS_STATE_SCALE, 'Diagonal of S: the network encodes '
          'x~ = S^-1 x (all 1: the literal network; docs/decisions.md, 10)', unit='m and m/s per unit',
          low=0.0, strict=True, size='n'),
    Field('discretization', 'choice', 'exact', 'Stepping of the continuous equations: exact (ZOH of '
          'the linearised drift) or euler', choices=DISCRETIZATIONS),
    Field('dynamics_model', 'choice', 'cw', "The filter's model of relative motion: cw (Clohessy-Wiltshire, "
          'Eq. 36-41), nonlinear_circular (two-body relative motion about a circular orbit, f and '
          'A(x_hat) each step; docs/decisions.md, 50-54) or ss_j2 (Schweighart-Sedwick linear J2 model, '
          'orbit-averaged, at the 51.6 deg default inclination; docs/decisions.md, 82)', equation='Eq. 3, 14, 17',
          choices=DYNAMICS_MODELS),
    Field('membrane_noise', 'real', 0.0, 'standard deviation of the membrane noise (0 = off)',
          unit='per sqrt(s)', symbol='eta', equation='Eq. 10', low=0.0, runtime=True),
    Field('max_spikes_per_step', 'integer', 0, 'Cap on spikes per step and run for the greedy rule '
          '(0: 1000 N)', low=0),
    Field('silenced_neurons', 'indices', (), 'Indices of silenced (dead) neurons', runtime=True),
)

BY_NAME = {f.name: f for f in FIELDS}
#: The fields that may change between steps.
RUNTIME = tuple(f.name for f in FIELDS if f.runtime)


def config_values(parameters: dict) -> dict:
    """Keyword arguments of EstimatorConfig from parameter values (ROS: flat lists, None for an
    unset array); names that are not fields are ignored."""
    return {f.name: f.from_parameter(parameters[f.name]) for f in FIELDS if f.name in parameters}


def field_docs() -> str:
    """A reST list of the fields, for EstimatorConfig's docstring."""
    lines = []
    for f in FIELDS:
        runtime = ' [runtime]' if f.runtime else ''
        lines.append(f'* ``{f.name}`` ({f.type}, default ``{f.default!r}``): {f.text}{runtime}')
    return '\n'.join(lines)
