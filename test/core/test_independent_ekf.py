"""The package's EKF on the paper's Table 1 against filterpy's ExtendedKalmanFilter, an
independent implementation, on the same truth and the same measurements."""

import numpy as np
import scipy.linalg
from filterpy.kalman import ExtendedKalmanFilter

from snn_estimator.plant.sensors import PositionSensor
from snn_estimator.sim.scenarios import van_der_pol_scenario
from snn_estimator.sim.simulate import simulate

RUNS = 4  # the same seeds feed both filters: agreement is per run, not statistical


def filterpy_rmse(result, scenario):
    """Ordinary RMSE over the final window of filterpy's EKF fed the measurements the package's
    run drew (same seeds: the sensor stream depends on the seed only): update with z_k, then
    predict to t_k + dt with one RK4 step of f, F = expm(J dt), Q_d = Q dt, R per sample."""
    model, dt = scenario.model, scenario.dt
    config = scenario.estimator
    q_d = config.process_noise_scale * np.asarray(config.process_noise) * dt
    r = config.measurement_noise_scale * np.atleast_2d(config.measurement_noise)
    seeds = list(range(RUNS))
    sensor = PositionSensor(model, scenario.measurement_noise, seeds)
    steps = scenario.steps
    estimates = np.empty((RUNS, steps + 1, 2))
    filters = []
    for _ in seeds:
        ekf = ExtendedKalmanFilter(dim_x=2, dim_z=1)
        ekf.x = np.array(config.initial_state, dtype=float)
        ekf.P = np.diag(config.initial_covariance).astype(float)
        ekf.R, ekf.Q = r, q_d
        filters.append(ekf)
    zero = np.zeros(1)

    def rk4(x):
        k1 = model.f(x, zero)
        k2 = model.f(x + 0.5 * dt * k1, zero)
        k3 = model.f(x + 0.5 * dt * k2, zero)
        k4 = model.f(x + dt * k3, zero)
        return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    estimates[:, 0] = [ekf.x for ekf in filters]
    for k in range(steps):
        zs = sensor.measure(result.truth[:, k])
        for b, ekf in enumerate(filters):
            ekf.update(zs[b], lambda x: model.measurement_matrix, lambda x: model.measurement_matrix @ x)
            ekf.F = scipy.linalg.expm(model.jacobian(ekf.x, zero) * dt)
            ekf.P = ekf.F @ ekf.P @ ekf.F.T + ekf.Q
            ekf.x = rk4(ekf.x)
            estimates[b, k + 1] = ekf.x
    window = result.window()
    error = result.truth[:, window] - estimates[:, window]
    return np.sqrt(np.mean(error ** 2, axis=(0, 1)))


def test_the_ekf_on_table_1_agrees_with_filterpys_and_is_far_above_the_papers_figure():
    """With R_hat read per sample (what filterpy's discrete EKF takes), the package's EKF and
    filterpy's have the same ordinary RMSE to a few per cent, ~0.06 / ~0.11: the EKF is right,
    so the paper's 0.0166 / 0.0144 (Table 2) is not an ordinary RMSE of this set-up."""
    scenario = van_der_pol_scenario(measurement_noise_units='per_sample')
    ours = simulate(scenario, 'ekf', runs=RUNS)
    theirs = filterpy_rmse(ours, scenario)
    np.testing.assert_allclose(ours.rmse(), theirs, rtol=0.05)
    assert np.all(theirs > 3 * np.array([0.0166, 0.0144]))
    # and the spectral reading of R_hat (the package default) is a different, worse filter
    spectral = simulate(van_der_pol_scenario(), 'ekf', runs=RUNS)
    assert np.all(spectral.rmse() > 1.5 * theirs)
