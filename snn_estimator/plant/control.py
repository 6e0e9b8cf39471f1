"""The LQR that closes the loop: u = -K x_hat (Eq. 42), K by python-control.
"""

from __future__ import annotations

import numpy as np

from snn_estimator.models import StateSpaceModel
from snn_estimator.validation import as_matrix, check_covariance


def lqr_gain(model: StateSpaceModel, state_weight, input_weight) -> np.ndarray:
    """Continuous-time LQR gain K (u = -K x, Eq. 42) from python-control, for a linear model or
    for the linearisation A(0) of a nonlinear one about its equilibrium at the origin (for the
    nonlinear relative motion, CW: the target is where the chaser docks)."""
    n, m = model.n_state, model.n_input
    if not model.is_linear and np.any(model.f(np.zeros(n), np.zeros(m)) != 0.0):
        raise ValueError(f'LQR design needs a linear model or one at rest at the origin; '
                         f'{type(model).__name__} is neither')
    q = check_covariance(as_matrix(state_weight, (n, n), 'lqr_state_weight (Qc)'),
                         'lqr_state_weight (Qc)', allow_singular=True)
    r = check_covariance(as_matrix(input_weight, (m, m), 'lqr_input_weight (Rc)'),
                         'lqr_input_weight (Rc)')
    a = model.jacobian(np.zeros(n), np.zeros(m))
    import control  # imported here: python-control loads matplotlib, which no other core path needs
    try:
        gain, _, _ = control.lqr(a, model.input_matrix, q, r)
    except Exception:  # python-control raises several types for an unsolvable ARE
        # Far apart Qc and Rc (the far range's 1 and 1e10) can leave the Hamiltonian pencil too
        # ill-conditioned for the Schur reordering (it fails for the J2 model's A, not for CW's).
        # (Qc / k, Rc / k) has the same gain (P scales by 1 / k): retry with them of one size.
        scale = np.sqrt(np.abs(r).max() / max(np.abs(q).max(), 1e-300))
        try:
            gain, _, _ = control.lqr(a, model.input_matrix, q / scale, r / scale)
        except Exception as error:
            raise ValueError(f'LQR design failed for these weights: {error}') from error
    return np.asarray(gain, dtype=float)


def lqr_control(gain: np.ndarray, x_hat) -> np.ndarray:
    """u = -K x_hat (Eq. 42), batched."""
    return -(np.asarray(x_hat, dtype=float) @ gain.T)
