"""Every node parameter, declared once: name, default, unit/meaning, range, read-only.

The tables here are the source of the ParameterDescriptors and of the defaults; config/*.yaml
repeats them with comments (a test keeps the two in step). Matrices are flat row-major lists
(1 value = scalar times identity, n values = diagonal, n*n values = full).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterUninitializedException
from rclpy.parameter import Parameter

from snn_estimator import EstimatorConfig
from snn_estimator.estimators import FILTER_KINDS
from snn_estimator.models import DEFAULT_ORBIT_RADIUS, EARTH_MU
from snn_estimator.config import MEASUREMENT_NOISE_UNITS, SPIKE_RULES

_DEFAULTS = EstimatorConfig()


@dataclass(frozen=True)
class Spec:
    """One parameter. ``default`` None means an array with no default (``kind`` gives its type)."""

    name: str
    default: Any
    description: str
    read_only: bool = True
    low: float | None = None
    high: float | None = None
    choices: Sequence[str] = ()
    kind: Parameter.Type | None = None

    def descriptor(self) -> ParameterDescriptor:
        text = self.description
        if self.choices:
            text += f" (one of: {' | '.join(self.choices)})"
        descriptor = ParameterDescriptor(name=self.name, description=text, read_only=self.read_only)
        if self.low is not None and not isinstance(self.default, bool):
            if isinstance(self.default, int):
                high = int(self.high) if self.high is not None else 2 ** 62
                descriptor.integer_range = [IntegerRange(from_value=int(self.low), to_value=high, step=1)]
            elif isinstance(self.default, float):
                high = float(self.high) if self.high is not None else 1e308
                descriptor.floating_point_range = [
                    FloatingPointRange(from_value=float(self.low), to_value=high, step=0.0)]
        return descriptor


def _floats(values) -> list:
    return [float(v) for v in values]


MODEL = (
    Spec('time_step', 0.1, 'Sample period of truth, measurement and estimator, s (Sec. 3.2: 0.1)',
         low=1e-6, high=3600.0),
    Spec('orbit_radius', DEFAULT_ORBIT_RADIUS,
         'Target orbit radius R_o, m; mean motion n = sqrt(mu/R_o^3) (Eq. 39). Not stated in '
         'the paper: 400 km LEO', low=1.0),
    Spec('gravitational_parameter', EARTH_MU,
         "Earth's mu, m^3/s^2 (Table 6: 398600 km^3/s^2)", low=1.0),
    Spec('frame_id', 'lvlh', "Frame of states and measurements: the target's LVLH frame"),
    Spec('child_frame_id', 'chaser', 'child_frame_id of the state messages'),
    Spec('diagnostics_period', 1.0, 'Simulated s between diagnostics messages (0: every step)', low=0.0),
)

PLANT = MODEL + (
    Spec('initial_state', _floats(_DEFAULTS.initial_state),
         'x0 = [x, y, z, vx, vy, vz], m and m/s (Table 6)'),
    Spec('process_noise', [1e-12],
         'Q, process-noise spectral density of the truth, (m/s^2)^2/Hz (Table 6: 1e-12 I6)'),
    Spec('seed', 0, 'Seed of the process noise (stream 1 of the seed; see README)', low=0),
    Spec('mode', 'lockstep', 'lockstep: step k+1 only after the control for step k arrived; '
         'realtime: step on a wall-clock timer', choices=('lockstep', 'realtime')),
    Spec('duration', 360.0, 'Simulated time to run, s (0: run until stopped)', low=0.0),
    Spec('real_time_factor', 1.0, 'realtime mode: simulated seconds per wall-clock second',
         low=1e-3, high=1e6),
    Spec('control_timeout', 1.0, 'lockstep: wall-clock s to wait for the control of a step '
         'before holding the last control (counted as a control timeout)', low=1e-3),
    Spec('start_time', 0.0, 'Simulated time of the first sample, s (below 2^31 s: a ROS time '
         'stamp counts whole seconds in an int32)', low=0.0, high=2.0 ** 31 - 3600.0),
    Spec('publish_clock', True, 'Publish /clock (the plant owns simulated time)'),
    Spec('exit_when_done', False, 'Exit the process after the last step (used by the demo)'),
    Spec('min_truth_subscribers', 0, "Publish the first state only once this many subscriptions "
         "match 'truth' (the demo: 2, sensor and recorder), so that a short run cannot end before a "
         'slow recorder has even matched it', low=0),
    Spec('paused', False, 'Hold simulated time (no steps, no /clock) until set false again',
         read_only=False),
)

SENSOR = MODEL + (
    Spec('measured_axes', [0, 1, 2], 'Position axes measured (0 x, 1 y, 2 z); the others are '
         'published as NaN'),
    Spec('measurement_noise', [1e-2], 'R, covariance of the position noise per sample, m^2 '
         '(Table 6: 1e-2 I3)'),
    Spec('seed', 0, 'Seed of the measurement noise (stream 2 of the seed)', low=0),
    Spec('time_jump_threshold', 1.0, 'Without a running /clock, a truth this far before the last '
         'one means the time base restarted: start over, s', low=0.0),
)

CONTROLLER = MODEL + (
    Spec('lqr_state_weight', [1.0], 'Qc of the LQR cost, per m^2 and (m/s)^2 (not in the paper)',
         read_only=False),
    Spec('lqr_input_weight', [1e5], 'Rc of the LQR cost, per (m/s^2)^2 (not in the paper)',
         read_only=False),
    Spec('gain', None, 'K (3x6, 18 values row-major) to use instead of designing it from Qc, Rc',
         read_only=False, kind=Parameter.Type.DOUBLE_ARRAY),
    Spec('cw_model', 'standard', 'CW matrix used for the LQR design',
         choices=('standard', 'as_published')),
    Spec('estimate_timeout', 0.5, 'Simulated s without a usable estimate before safe mode (zero '
         'thrust)', read_only=False, low=1e-9),
    Spec('max_input_age', 1.0, 'Estimates older than this behind the simulated clock, or stamped '
         'more than this plus two time steps ahead of it, are rejected, s', read_only=False, low=1e-9),
    Spec('time_jump_threshold', 1.0, 'Without a running /clock, an estimate this far before the '
         'last one means the time base restarted: start over, s', low=0.0),
)

ESTIMATOR = MODEL + (
    Spec('filter_type', 'snn_emsif', 'The estimator', choices=tuple(FILTER_KINDS)),
    Spec('cw_model', 'standard', "CW matrix of the filter's model: standard, or Eq. 41 as printed",
         choices=('standard', 'as_published')),
    Spec('measured_axes', [0, 1, 2], 'Position axes in the measurement (must match the sensor)'),
    Spec('neuron_count', _DEFAULTS.neuron_count, 'N, number of LIF neurons (Table 6: 200)',
         low=1, high=100000),
    Spec('leak_rate', _DEFAULTS.leak_rate, 'lambda, leak of v and r, 1/s (Eq. 10-11; Table 6: 0.001)',
         read_only=False, low=0.0),
    Spec('boundary_layer', [0.1], 'delta, sliding boundary layer per measured axis or one for '
         'all, m (Eq. 7-8, 21-24; Table 6: 0.1)', read_only=False),
    Spec('decoder_variance', _DEFAULTS.decoder_variance,
         'Variance of the decoder entries, D ~ N(0, var) (Sec. 3.2: 1/15)', low=1e-300),
    Spec('seed', 0, 'Seed of the decoder and membrane noise (stream 3 of the seed)', low=0),
    Spec('process_noise', [1e-12], "Q the filter's Q_hat is scaled from, (m/s^2)^2/Hz"),
    Spec('measurement_noise', [1e-2], "R the filter's R_hat is scaled from, m^2"),
    Spec('process_noise_scale', _DEFAULTS.process_noise_scale, 'Q_hat = scale * Q (Sec. 3.2: 0.9)',
         read_only=False, low=0.0),
    Spec('measurement_noise_scale', _DEFAULTS.measurement_noise_scale,
         'R_hat = scale * R (Sec. 3.2: 5)', read_only=False, low=1e-300),
    Spec('measurement_noise_units', _DEFAULTS.measurement_noise_units,
         'What R_hat is to the Kalman gain and Riccati equation (Eq. 5-6): spectral_density (as '
         'printed) or per_sample (variance of each sample: Eq. 5-6 use R_hat * time_step)',
         choices=MEASUREMENT_NOISE_UNITS),
    Spec('initial_covariance', _floats(_DEFAULTS.initial_covariance),
         'P0, initial error covariance, m^2 and (m/s)^2 (not in the paper)'),
    Spec('initial_state', _floats(_DEFAULTS.initial_state), 'x_hat0, m and m/s (Table 6: x0)'),
    Spec('spike_rule', _DEFAULTS.spike_rule, 'How neurons above threshold fire in one step',
         choices=SPIKE_RULES),
    Spec('state_scale', _floats(_DEFAULTS.state_scale), 'Diagonal of S: the network encodes '
         'x~ = S^-1 x (all 1: the literal network), m and m/s per unit'),
    Spec('discretization', _DEFAULTS.discretization, 'Stepping of the continuous equations',
         choices=('exact', 'euler')),
    Spec('membrane_noise', 0.0, 'eta, membrane noise, per sqrt(s) (Eq. 10; 0 = off)', read_only=False,
         low=0.0),
    Spec('max_spikes_per_step', 0, 'Cap on spikes per step for the greedy rule (0: 1000 N)', low=0),
    Spec('silenced_neurons', None, 'Indices of silenced (dead) neurons', read_only=False,
         kind=Parameter.Type.INTEGER_ARRAY),
    Spec('silenced_fraction', 0.0, 'Fraction of neurons silenced, chosen at random with the seed '
         '(added to silenced_neurons)', read_only=False, low=0.0, high=1.0),
    Spec('publish_spikes', True, 'Publish per-neuron spike counts on `spikes` every step'),
    Spec('initialization', 'auto', 'Start from the parameters, or from the newest estimate an '
         'earlier estimator left on `estimate` (hot swap) and replay the inputs since then; '
         'auto: the latter when one arrives within warm_start_wait',
         choices=('auto', 'parameters', 'last_estimate')),
    Spec('warm_start_wait', 0.5, 'auto initialization: wall-clock s after the first measurement to '
         'wait for the topics\' history (an earlier estimate, more measurements)', low=0.0),
    Spec('warm_start_min_samples', 20, 'auto initialization: with no earlier estimate but at least '
         'this many measurements in the history, start from a least-squares fit of the newest '
         'this many', low=2),
    Spec('max_input_age', 1.0, 'Measurements older than this behind the newest one received '
         '(stragglers), or stamped more than this plus two time steps ahead of the simulated '
         'clock, are rejected, s', read_only=False, low=1e-9),
    Spec('time_jump_threshold', 1.0, 'Without a running /clock, a measurement this far before the '
         'estimate time means the time base restarted (bag loop): the filter restarts, s', low=0.0),
    Spec('nis_threshold', 25.0, 'Normalised innovation squared above which a step counts as '
         'inconsistent (chi-square, 3 dof: p = 1.5e-5)', read_only=False, low=1e-9),
    Spec('nis_window', 10, 'Inconsistent steps in a row that trigger a re-initialisation from the '
         'measurement (0: never)', read_only=False, low=0),
)


def declare(node, specs: Sequence[Spec]) -> dict:
    """Declare ``specs`` on ``node``; return name -> value (None for unset arrays)."""
    values = {}
    for spec in specs:
        if spec.default is None:
            node.declare_parameter(spec.name, spec.kind, spec.descriptor())
            try:
                values[spec.name] = node.get_parameter(spec.name).value
            except ParameterUninitializedException:
                values[spec.name] = None
        else:
            values[spec.name] = node.declare_parameter(spec.name, spec.default, spec.descriptor()).value
        if spec.choices and values[spec.name] not in spec.choices:
            raise ValueError(f"parameter {spec.name} must be one of {' | '.join(spec.choices)}; "
                             f'got {values[spec.name]!r}')
    return values


def estimator_config(values: dict) -> EstimatorConfig:
    """The core configuration from the estimator node's parameter values."""
    return EstimatorConfig(
        neuron_count=values['neuron_count'], leak_rate=values['leak_rate'],
        boundary_layer=list(values['boundary_layer']), decoder_variance=values['decoder_variance'],
        seed=values['seed'], process_noise=list(values['process_noise']),
        measurement_noise=list(values['measurement_noise']),
        process_noise_scale=values['process_noise_scale'],
        measurement_noise_scale=values['measurement_noise_scale'],
        measurement_noise_units=values['measurement_noise_units'],
        initial_covariance=list(values['initial_covariance']),
        initial_state=list(values['initial_state']), spike_rule=values['spike_rule'],
        state_scale=list(values['state_scale']), discretization=values['discretization'],
        membrane_noise=values['membrane_noise'], max_spikes_per_step=values['max_spikes_per_step'],
        silenced_neurons=tuple(silenced_set(values, values['neuron_count'], values['seed'])))


def silenced_set(values: dict, neurons: int, seed: int) -> list[int]:
    """silenced_neurons plus a seeded random silenced_fraction of the N neurons."""
    explicit = [int(i) for i in (values.get('silenced_neurons') or [])]
    if any(i < 0 or i >= max(neurons, 1) for i in explicit):
        raise ValueError(f'silenced_neurons must be indices in [0, {neurons - 1}], got {explicit}')
    fraction = float(values.get('silenced_fraction') or 0.0)
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f'silenced_fraction must be in [0, 1], got {fraction}')
    order = np.random.default_rng([int(seed), 4]).permutation(neurons)
    return sorted(set(explicit) | {int(i) for i in order[:int(round(fraction * neurons))]})


def cw_model(values: dict, form: str = 'standard', measured_axes=(0, 1, 2)):
    """The CW model the parameters describe."""
    from snn_estimator import ClohessyWiltshire
    return ClohessyWiltshire(orbit_radius=values['orbit_radius'], mu=values['gravitational_parameter'],
                             form=form, measured_axes=tuple(measured_axes))


def markdown() -> str:
    """Parameter reference tables (README, between the 'parameters' markers)."""
    from .recorder_node import RECORDER

    def show(value) -> str:
        if value is None:
            return '(unset)'
        if isinstance(value, float):
            return f'{value:g}'
        if isinstance(value, list):
            return '[' + ', '.join(show(v) for v in value) + ']'
        return str(value)

    shared = {spec.name for spec in MODEL}
    lines = []
    for title, specs in (('all pipeline nodes', MODEL), ('cw_plant', PLANT), ('position_sensor', SENSOR),
                         ('lqr_controller', CONTROLLER), ('estimator', ESTIMATOR), ('recorder', RECORDER)):
        lines += [f'**{title}**', '', '| parameter | default | meaning |', '|---|---|---|']
        for spec in specs:
            if specs is not MODEL and spec.name in shared:
                continue
            choices = ' (' + ' \\| '.join(spec.choices) + ')' if spec.choices else ''
            runtime = '' if spec.read_only else ' **[runtime]**'
            lines.append(f'| `{spec.name}` | `{show(spec.default)}` | {spec.description}{choices}{runtime} |')
        lines.append('')
    return '\n'.join(lines)


if __name__ == '__main__':
    print(markdown())
