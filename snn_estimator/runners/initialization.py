"""Initial state determination: the start of a filter that joins a running loop.

A filter that starts late (a replacement estimator after a crash) knows neither the state nor
its uncertainty. :func:`least_squares_start` fits the state to a window of position
measurements through the exact linear dynamics (the controls held between them known), and
returns it with its covariance, which is honest for linear-Gaussian data (the tests check its
NEES over Monte-Carlo runs). The window sets what the start knows about the unmeasured
velocity: :func:`window_standard_deviations` gives the position and velocity standard
deviations a window of a given length leaves (docs/decisions.md, 19).
"""

from __future__ import annotations

import numpy as np

from snn_estimator.models import StateSpaceModel


def least_squares_start(model: StateSpaceModel, stamps, measurements, controls,
                        measurement_covariance) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares state from a window of measurements (initial state determination).

    ``stamps`` (K,) in seconds, ``measurements`` (K, m) taken at them, ``controls`` (K, m_u) held
    from each stamp to the next, ``measurement_covariance`` R per sample. Fits the state at the
    first stamp through the exact linear dynamics and returns it propagated to the *last* stamp,
    i.e. using the first K - 1 measurements only, with its covariance (process noise neglected:
    its effect over the window must be small against R). The last measurement is left for the
    filter's next step. Linear models only; ValueError for too few or unordered stamps.
    """
    if not model.is_linear:
        raise ValueError('a least-squares start needs a linear model')
    stamps = np.asarray(stamps, dtype=float)
    z = np.asarray(measurements, dtype=float)
    u = np.asarray(controls, dtype=float)
    n, c = model.n_state, model.measurement_matrix
    if stamps.size < 2 or z.shape[0] != stamps.size or u.shape[0] != stamps.size:
        raise ValueError('need at least two stamps with one measurement and one control each')
    weight = np.linalg.inv(np.asarray(measurement_covariance, dtype=float))
    transition, offset = np.eye(n), np.zeros(n)
    normal, rhs = np.zeros((n, n)), np.zeros(n)
    for k in range(stamps.size):
        if k:
            step = float(stamps[k] - stamps[k - 1])
            if step <= 0.0:
                raise ValueError('stamps must increase')
            phi, gamma = model.discrete_matrices(round(step, 9))
            transition, offset = phi @ transition, phi @ offset + gamma @ u[k - 1]
        if k == stamps.size - 1:
            break
        rows = c @ transition
        normal += rows.T @ weight @ rows
        rhs += rows.T @ weight @ (z[k] - c @ offset)
    if np.linalg.matrix_rank(normal) < n:
        raise ValueError(f'{stamps.size - 1} measurements cannot determine the {n} states; use a longer window')
    covariance = np.linalg.inv(normal)
    first = covariance @ rhs
    last = transition @ first + offset
    propagated = transition @ covariance @ transition.T
    return last, 0.5 * (propagated + propagated.T)


def window_standard_deviations(model: StateSpaceModel, window: float, dt: float,
                               measurement_covariance) -> np.ndarray:
    """Standard deviation of each state of :func:`least_squares_start` over a window of
    ``window`` seconds sampled every ``dt`` (no data needed: the covariance depends only on the
    geometry)."""
    count = int(round(window / dt)) + 1
    stamps = dt * np.arange(count)
    zeros_z = np.zeros((count, model.n_meas))
    zeros_u = np.zeros((count, model.n_input))
    _, covariance = least_squares_start(model, stamps, zeros_z, zeros_u, measurement_covariance)
    return np.sqrt(np.diag(covariance))
