"""The constant gain of a law at the fixed point of the sampled step of Eq. 6 (``gain_schedule:
steady_state``, docs/decisions.md, 28 and 43): what a chip can hold, and the last weight set of a
switched schedule."""

from __future__ import annotations

import numpy as np
import scipy.linalg

from snn_estimator import gains
from snn_estimator.config import ResolvedConfig, gain_noise_density
from snn_estimator.models import StateSpaceModel


def steady_state_gain(gain_law: str, model: StateSpaceModel, settings: ResolvedConfig,
                      dt: float) -> np.ndarray:
    """The constant gain of ``gain_law`` at the fixed point P_ss of the sampled step of Eq. 6
    (the discrete algebraic Riccati equation of the one-step predictor, P = Phi P Phi^T + Q_d -
    Phi P C^T (C P C^T + R_d)^-1 C P Phi^T; docs/decisions.md, 43), by the law's ``steady_state``
    (snn_estimator.gains). Linear models only. ValueError when the Riccati equation has no
    stabilising solution (e.g. Q_hat = 0 with undamped modes)."""
    if not model.is_linear:
        raise ValueError('a steady-state gain needs a linear model')
    law = gains.law(gain_law)
    n = model.n_state
    c = model.measurement_matrix
    a_d, _ = model.linearized_increment(None, dt, settings.discretization)
    phi = np.eye(n) + dt * a_d
    q_step = (model.process_noise_discrete(settings.q_hat, dt) if settings.discretization == 'exact'
              else settings.q_hat * dt)
    r_sample = gain_noise_density(settings, dt) / dt
    try:
        p_ss = scipy.linalg.solve_discrete_are(phi.T, c.T, q_step, r_sample)
    except (np.linalg.LinAlgError, ValueError) as error:
        raise ValueError(f'no steady-state gain: the Riccati equation of Eq. 6 has no stabilising '
                         f'solution for this Q_hat and R ({error}); raise process_noise_scale or '
                         'use gain_schedule time_varying') from None
    step = gains.SampledStep(phi, dt, r_sample)
    return law.steady_state(gains.SteadyState(p_ss, c, np.linalg.pinv(c), r_sample, settings.r_hat,
                                              settings.boundary_layer, gains.sampled_kalman(p_ss, c, step)))
