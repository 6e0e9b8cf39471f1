"""Estimator configuration: one validated record shared by the ROS node and the offline tools."""

from __future__ import annotations

import dataclasses
from dataclasses import field
from typing import Any

import numpy as np

from . import defaults as D
from .models import StateSpaceModel
from .schema import FIELDS, GAIN_SCHEDULES, MEASUREMENT_NOISE_UNITS, NETWORK_DRIVES, SPIKE_RULES, field_docs  # noqa: F401


def _replace(self, **changes) -> 'EstimatorConfig':
    """A copy with some fields changed (unknown names raise TypeError)."""
    return dataclasses.replace(self, **changes)


def _field(spec):
    default = spec.default
    if isinstance(default, (list, dict, set)):
        return field(default_factory=lambda: type(default)(default))
    return field(default=default)


#: Everything a filter needs besides the model, one field per :data:`schema.FIELDS` entry with
#: its default. Matrices may be given as a matrix, a flat row-major list, a diagonal vector or a
#: scalar; ``state_scale`` None means S = I.
EstimatorConfig = dataclasses.make_dataclass(
    'EstimatorConfig', [(spec.name, Any, _field(spec)) for spec in FIELDS], frozen=True,
    namespace={'replace': _replace})
EstimatorConfig.__module__ = __name__
EstimatorConfig.__doc__ = ('Everything a filter needs besides the model (fields from '
                           'snn_estimator.schema.FIELDS):\n\n' + field_docs())


#: An :class:`EstimatorConfig` checked against a model, with arrays of the right shapes: every
#: schema field (``max_spikes_per_step`` 0 resolved to 1000 N, ``state_scale`` None to ones),
#: plus ``q_hat`` = process_noise_scale Q and ``r_hat`` = measurement_noise_scale R.
ResolvedConfig = dataclasses.make_dataclass(
    'ResolvedConfig', [(spec.name, Any) for spec in FIELDS] + [('q_hat', Any), ('r_hat', Any)], frozen=True)
ResolvedConfig.__module__ = __name__


def resolve(config: EstimatorConfig, model: StateSpaceModel, n_meas: int | None = None) -> ResolvedConfig:
    """Validate ``config`` for ``model`` field by field (schema.Field.check); raise ValueError
    naming the field and the fix. ``n_meas``: the measurement's size when a measurement model
    replaces the model's C (default: the model's)."""
    dims = {'n': model.n_state, 'm': model.n_meas if n_meas is None else int(n_meas)}
    values = {}
    for spec in FIELDS:
        value = getattr(config, spec.name)
        if spec.name == 'state_scale' and value is None:
            value = np.ones(dims['n'])
        values[spec.name] = spec.check(value, dims)
    neurons = values['neuron_count']
    silenced = values['silenced_neurons']
    if silenced and (silenced[0] < 0 or silenced[-1] >= neurons):
        raise ValueError(f'silenced_neurons must be indices in [0, {neurons - 1}], got {silenced}')
    values['max_spikes_per_step'] = values['max_spikes_per_step'] or 1000 * neurons
    named = getattr(model, 'dynamics_model', values['dynamics_model'])  # relative motion names itself
    if named != values['dynamics_model']:
        raise ValueError(f"dynamics_model is {values['dynamics_model']} but the filter is given the "
                         f'{named} model ({type(model).__name__}): set dynamics_model {named}, or build '
                         f"the model with models.relative_motion('{values['dynamics_model']}')")
    if values['boundary_layer_mode'] != 'fixed' and values['gain_schedule'] != 'time_varying':
        raise ValueError(f"boundary_layer_mode {values['boundary_layer_mode']} follows P each step: it needs "
                         f"gain_schedule time_varying, got {values['gain_schedule']}")
    return ResolvedConfig(**values, q_hat=values['process_noise_scale'] * values['process_noise'],
                          r_hat=values['measurement_noise_scale'] * values['measurement_noise'])


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


def sensor_boundary_layer(noise, units: str = D.SENSOR_BOUNDARY_LAYER_UNITS) -> tuple[float, ...]:
    """delta of Eq. 7-8 for a sensor of noise ``noise`` (R per sample in its model's units: the
    matrix, or its diagonal), per component, from Table 6 (delta = 0.1 for R = 1e-2 m^2;
    Decision 35): ``units`` 'sigma', one sensor sigma, sqrt(R_jj) (the units of z, as Eq. 7
    divides an innovation by it); 'variance', R_jj times Table 6's delta / R = 10 (the units of
    diag(P^zz), as Eq. 8 divides a variance by it). Both give Table 6's position sensor its 0.1."""
    noise = np.asarray(noise, dtype=float)
    variances = np.diag(noise) if noise.ndim == 2 else np.atleast_1d(noise)
    if units == 'sigma':
        return tuple(float(v) for v in np.sqrt(variances))
    if units != 'variance':
        raise ValueError(f"boundary layer units must be one of {', '.join(D.BOUNDARY_LAYER_UNITS)}; got {units!r}")
    # 15 digits: 10 x 1e-6 is 1e-05 in YAML and docs, not 9.999999999999999e-06
    return tuple(float(f'{D.SENSOR_BOUNDARY_LAYER_PER_VARIANCE * v:.15g}') for v in variances)
