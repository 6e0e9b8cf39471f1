"""The gains a chip network holds (``gain_schedule``: steady_state or switched, docs/decisions.md,
28): the chip (snn_estimator.spiking.chip) is handed these as its gain source, so it never runs a
filter itself."""

from __future__ import annotations

import numpy as np

from snn_estimator.catalog import FILTER_KINDS
from snn_estimator.spiking.chip import schedule_times

from .steady_state import steady_state_gain


def gain_trajectory(estimator_kind: str, model, config, dt: float, steps: int, make_twin) -> np.ndarray:
    """K(t_k) of the time-varying filter, (steps, n, m): for a linear model the gains that
    depend on P only (kalman, msif, msif_weighted) follow from P0 alone, whatever
    the measurements (run here with zero innovations). ``make_twin(kind, config)`` builds the
    non-spiking filter that computes them (the Estimator hands it over)."""
    twin = FILTER_KINDS[estimator_kind].twin or estimator_kind
    if FILTER_KINDS[twin].gain == 'sif':
        raise ValueError('gain_schedule switched needs a gain law computed from P (kalman, msif, '
                         'msif_weighted); the SIF gain of Eq. 7 follows the innovation')
    filt = make_twin(twin, config.replace(gain_schedule='time_varying', precision='float64',
                                          initial_state_dispersion=False, silenced_neurons=()))
    c = model.measurement_matrix
    u = np.zeros(model.n_input)
    gains = np.empty((steps, model.n_state, model.n_meas))
    for k in range(steps):
        filt.step(c @ filt.x_hat, u, dt)
        gains[k] = filt.gain
    return gains


def schedule_gains(estimator_kind: str, model, config, settings, dt: float, make_twin) -> list[np.ndarray]:
    """The gain of each weight set of a switched schedule: the mean of the time-varying K(t)
    over [t_j, t_j+1) for all but the last set, and K(t_last) for the last one, held for ever
    (at least the time-varying gain from then on: with the rendezvous' tiny Q_hat, K(t) decays
    like 1/t for minutes and its fixed point, the steady-state gain, is too small to remove
    what is left of a dispersed start). No switch times: the steady-state gain alone.
    ``make_twin``: see :func:`gain_trajectory`."""
    times = schedule_times(config)
    if not times:
        return [steady_state_gain(FILTER_KINDS[estimator_kind].gain, model, settings, dt)]
    trajectory = gain_trajectory(estimator_kind, model, config, dt, int(round(times[-1] / dt)) + 1, make_twin)
    bounds = [0] + [int(round(t / dt)) for t in times]
    gains = [trajectory[start:max(stop, start + 1)].mean(axis=0) for start, stop in zip(bounds, bounds[1:])]
    return gains + [trajectory[bounds[-1]]]
