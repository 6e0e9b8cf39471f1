"""Filters and the spiking network against the paper's formulas and independent computations."""

import warnings

import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

from snn_estimator import (
    FILTER_KINDS,
    TWIN_OF,
    EstimatorConfig,
    gains,
    make_estimator,
    rendezvous_scenario,
    simulate,
    van_der_pol_scenario,
)
from snn_estimator.filters import kernels
from snn_estimator.filters.reference import DenseSpikingFilter
from snn_estimator.models import VanDerPol
from snn_estimator.plant.control import lqr_control, lqr_gain
from snn_estimator.plant.sensors import PositionSensor
from snn_estimator.plant.truth import Plant

SPIKING = [kind for kind, spec in FILTER_KINDS.items() if spec.spiking]


def van_loan(a: np.ndarray, q: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(Phi, Q_d): e^{A dt} and the covariance white noise of density Q adds over dt, from one
    exponential of [[-A, Q], [0, A^T]] dt (Van Loan 1978), written here for the tests."""
    n = a.shape[0]
    block = scipy.linalg.expm(np.block([[-a, q], [np.zeros((n, n)), a.T]]) * dt)
    phi = block[n:, n:].T
    return phi, phi @ block[:n, n:]


def sampled_kalman_step(p, c, phi, q_d, r_d):
    """The textbook discrete Kalman step of a sample of variance r_d: K_d, then P' = Phi ((I -
    K_d C) P (I - K_d C)^T + K_d R_d K_d^T) Phi^T + Q_d (Joseph update, then prediction)."""
    k_d = p @ c.T @ np.linalg.inv(c @ p @ c.T + r_d)
    i_kc = np.eye(len(p)) - k_d @ c
    return k_d, phi @ (i_kc @ p @ i_kc.T + k_d @ r_d @ k_d.T) @ phi.T + q_d


def rendezvous_inputs(steps=300, seed=0):
    """Measurements and controls of a closed-loop rendezvous driven by the EMSIF."""
    scenario = rendezvous_scenario()
    model = scenario.model
    plant = Plant(model, scenario.x0, scenario.process_noise, [seed])
    sensor = PositionSensor(model, scenario.measurement_noise, [seed])
    gain = lqr_gain(model, scenario.lqr_state_weight, scenario.lqr_input_weight)
    driver = make_estimator('emsif', scenario.estimator, model)
    zs, us = [], []
    for _ in range(steps):
        u = lqr_control(gain, driver.x_hat)
        z = sensor.measure(plant.x)[0]
        driver.step(z, u, scenario.dt)
        plant.step(u, scenario.dt)
        zs.append(z)
        us.append(u)
    return scenario, np.array(zs), np.array(us)


# ---------------------------------------------------------------- the weights of Eq. 16-22
def test_network_weights_equal_the_papers_formulas():
    scenario = rendezvous_scenario('as_published')  # S = I and forward Euler: the literal network
    model = scenario.model
    estimator = make_estimator('snn_ekf', scenario.estimator, model)
    _, zs, us = rendezvous_inputs(steps=5)
    for z, u in zip(zs, us):
        p_before = estimator.P.copy()
        estimator.step(z, u, 0.1)
    w = estimator.weights(dt=0.1)
    d = estimator.decoder
    a, b, c = model.system_matrix(model.mean_motion), model.input_matrix, model.measurement_matrix
    lam = scenario.estimator.leak_rate
    dt, phi = 0.1, np.eye(6) + 0.1 * a  # forward Euler (as_published): Phi = I + A dt
    k_d = p_before @ c.T @ np.linalg.inv(c @ p_before @ c.T + estimator.settings.r_hat / dt)
    kalman_gain = phi @ k_d / dt  # Eq. 5 as the sampled step's gain (Decision 43)
    np.testing.assert_allclose(w['F'], d.T @ b, atol=1e-15)                                # Eq. 16
    np.testing.assert_allclose(w['Omega_s'], d.T @ (a + lam * np.eye(6)) @ d, atol=1e-14)  # Eq. 17
    np.testing.assert_allclose(w['Omega_f'], -d.T @ d, atol=1e-15)                         # Eq. 18
    np.testing.assert_allclose(w['Omega_k'], -d.T @ kalman_gain @ c @ d, rtol=1e-9, atol=1e-14)  # Eq. 19
    np.testing.assert_allclose(w['F_k'], d.T @ kalman_gain, rtol=1e-9, atol=1e-14)          # Eq. 20
    np.testing.assert_allclose(w['thresholds'], 0.5 * np.sum(d * d, axis=0))               # T_i


@pytest.mark.parametrize('kind', ['snn_ekf', 'snn_emsif', 'snn_emsif_star'])
def test_the_kernels_step_is_eq_15_with_the_published_weights_in_scaled_units(kind):
    """weights() are the matrices the compiled step actually applies: with the default scaled
    network (S != I, exact steps) one kernel step equals v' = (1 - lambda dt) v + dt (F u +
    (Omega_s + Omega_k) r + F_k z) + Omega_f s and r' = (1 - lambda dt) r + s (Eq. 11, 15)."""
    scenario, zs, us = rendezvous_inputs(steps=40)
    estimator = make_estimator(kind, scenario.estimator)
    assert not np.allclose(estimator.settings.state_scale, 1.0)
    lam, dt = estimator.settings.leak_rate, 0.1
    checked = 0
    for z, u in zip(zs, us):
        v0, r0 = estimator.potentials.copy(), estimator.rates.copy()
        estimator.step(z, u, dt)
        w = estimator.weights(dt=dt)  # CW: A_d is constant; the gain is the one just used
        s = estimator.spikes.astype(float)
        expected_v = ((1 - lam * dt) * v0 + dt * (w['F'] @ u + (w['Omega_s'] + w['Omega_k']) @ r0 + w['F_k'] @ z)
                      + w['Omega_f'] @ s)
        np.testing.assert_allclose(estimator.potentials, expected_v, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(estimator.rates, (1 - lam * dt) * r0 + s, rtol=1e-12, atol=1e-12)
        checked += int(s.sum() > 0)
    assert checked > 5  # steps with spikes were among them


def test_decoder_is_drawn_with_the_configured_variance():
    config = EstimatorConfig(neuron_count=4000, decoder_variance=0.25)
    estimator = make_estimator('snn_emsif', config)
    assert estimator.decoder.shape == (6, 4000)
    assert np.var(estimator.decoder) == pytest.approx(0.25, rel=0.03)
    assert abs(np.mean(estimator.decoder)) < 0.01


def test_msif_gain_uses_the_innovation_covariance_and_saturates():
    scenario = rendezvous_scenario()
    c = scenario.model.measurement_matrix
    for delta, saturated in [(1e-3, True), (10.0, False)]:
        estimator = make_estimator('emsif', scenario.estimator.replace(boundary_layer=delta))
        p_before = estimator.P.copy()
        estimator.step(np.array([70.1, 29.9, -5.0]), np.zeros(3), 0.1)
        p_zz = c @ p_before @ c.T + estimator.settings.r_hat                  # Eq. 9, corrected
        expected = np.linalg.pinv(c) @ np.diag(np.minimum(np.diag(p_zz) / delta, 1.0))  # Eq. 8
        np.testing.assert_allclose(estimator.gain, expected, rtol=1e-12)
        if saturated:
            np.testing.assert_allclose(estimator.gain, np.linalg.pinv(c))
        else:
            assert np.all(np.diag(estimator.gain[:3]) < 1.0)


def test_sif_gain_follows_the_innovation_eq_23_24():
    estimator = make_estimator('snn_emsif_star', EstimatorConfig(boundary_layer=(0.1, 0.2, 0.4)))
    x_hat = estimator.x_hat.copy()
    z = x_hat[:3] + np.array([0.05, -0.5, 0.1])
    estimator.step(z, np.zeros(3), 0.1)
    np.testing.assert_allclose(np.diag(estimator.gain[:3]), [0.5, 1.0, 0.25], rtol=1e-9)
    assert np.all(estimator.gain[3:] == 0.0)
    assert estimator.P is None


def test_kalman_gain_and_covariance_are_the_sampled_step_of_eq_5_and_6():
    """K = Phi K_d / dt and P' = Phi P+ Phi^T + Q_d, P+ the Joseph update with R_d = R_hat / dt
    (R_hat a density, Eq. 5-6; Decision 43), and x' = Phi x + Gamma u + dt K (z - C x)."""
    scenario = rendezvous_scenario()
    model = scenario.model
    estimator = make_estimator('ekf', scenario.estimator)
    p = estimator.P.copy()
    x = estimator.x_hat.copy()
    z, u, dt = np.array([70.2, 29.8, -5.1]), np.array([0.01, 0.0, -0.01]), 0.1
    estimator.step(z, u, dt)
    a, c = model.system_matrix(model.mean_motion), model.measurement_matrix
    phi, q_d = van_loan(a, estimator.settings.q_hat, dt)
    k_d, expected_p = sampled_kalman_step(p, c, phi, q_d, estimator.settings.r_hat / dt)
    gain = phi @ k_d / dt
    np.testing.assert_allclose(estimator.gain, gain, rtol=1e-10)
    np.testing.assert_allclose(estimator.P, expected_p, rtol=1e-10, atol=1e-20)
    phi_zoh, gamma = model.discrete_matrices(dt)
    np.testing.assert_allclose(estimator.x_hat, phi_zoh @ x + gamma @ u + dt * gain @ (z - c @ x), rtol=1e-12)


def test_the_ekf_tends_to_the_continuous_filter_of_eq_3_to_6_as_dt_goes_to_zero(double_integrator):
    """The paper's filter is continuous (Eq. 3-6: x' = f + P C^T R^-1 (z - C x), P' = A P + P A^T
    + Q - P C^T R^-1 C P). The sampled step with R_d = R / dt (Decision 43) must tend to it:
    with z and u held over each step, as the sampled filter holds them, and solved to 1e-11 by
    an ODE solver, the largest gap of the estimate and of P over 4 s falls linearly with dt."""
    model = double_integrator
    q, r = 0.5, 0.2
    config = EstimatorConfig(neuron_count=1, process_noise=q, measurement_noise=r,
                             process_noise_scale=1.0, measurement_noise_scale=1.0,
                             initial_covariance=(1.0, 1.0), initial_state=(0.0, 0.0),
                             boundary_layer=1.0, state_scale=None)
    a, b, c = np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([0.0, 1.0]), np.array([[1.0, 0.0]])

    def continuous(t, y, z, u):  # Eq. 3 and 6 with z and u held
        x, p = y[:2], y[2:].reshape(2, 2)
        gain = p @ c.T / r
        x_dot = a @ x + b * u + gain @ (z - c @ x)
        p_dot = a @ p + p @ a.T + q * np.eye(2) - gain @ c @ p
        return np.concatenate([x_dot, p_dot.ravel()])

    gaps = []
    for dt in (0.02, 0.01, 0.005):
        estimator = make_estimator('ekf', config, model)
        exact = np.concatenate([np.zeros(2), np.eye(2).ravel()])
        gap = 0.0
        for k in range(int(round(4.0 / dt))):
            t = k * dt
            z, u = np.array([np.sin(t)]), -np.sin(t)
            estimator.step(z, np.array([u]), dt)
            exact = scipy.integrate.solve_ivp(continuous, (t, t + dt), exact, args=(z, u), rtol=1e-11,
                                              atol=1e-13).y[:, -1]
            gap = max(gap, np.abs(estimator.x_hat - exact[:2]).max(),
                      np.abs(estimator.P - exact[2:].reshape(2, 2)).max())
        gaps.append(gap)
    assert gaps[0] < 0.05
    assert 0.4 < gaps[1] / gaps[0] < 0.6 and 0.4 < gaps[2] / gaps[1] < 0.6  # first order in dt


def test_the_ekf_is_the_discrete_kalman_predictor_with_van_loans_q_and_r_over_dt(double_integrator):
    """At any dt, Eq. 3-6 stepped (Decision 43) is the discrete Kalman filter of a sample of
    variance R_d = R / dt with Q_d the exact process noise of the step: run beside the textbook
    filter (update, then predict), to the rounding."""
    model = double_integrator
    q, r = 0.5, 0.2
    config = EstimatorConfig(neuron_count=1, process_noise=q, measurement_noise=r,
                             process_noise_scale=1.0, measurement_noise_scale=1.0,
                             initial_covariance=(1.0, 1.0), initial_state=(0.0, 0.0),
                             boundary_layer=1.0, state_scale=None)
    for dt in (0.5, 0.01):
        estimator = make_estimator('ekf', config, model)
        x_prior, p_prior = np.zeros(2), np.eye(2)
        phi, gamma = model.discrete_matrices(dt)
        _, q_d = van_loan(np.array([[0.0, 1.0], [0.0, 0.0]]), q * np.eye(2), dt)
        c = model.measurement_matrix
        for k in range(int(round(4.0 / dt))):
            t = k * dt
            z, u = np.array([np.sin(t)]), np.array([-np.sin(t)])  # truth: p = sin t
            estimator.step(z, u, dt)
            gain, p_next = sampled_kalman_step(p_prior, c, phi, q_d, np.array([[r / dt]]))
            x_prior, p_prior = phi @ (x_prior + gain @ (z - c @ x_prior)) + gamma @ u, p_next
            np.testing.assert_allclose(estimator.x_hat, x_prior, rtol=1e-11, atol=1e-12)
            np.testing.assert_allclose(estimator.P, p_prior, rtol=1e-11, atol=1e-14)


# ---------------------------------------------------------------- the network
@pytest.mark.parametrize('kind', SPIKING)
def test_estimate_is_the_decoded_filtered_spike_train(kind):
    scenario, zs, us = rendezvous_inputs(steps=100)
    estimator = make_estimator(kind, scenario.estimator)
    scale = np.asarray(scenario.estimator.state_scale)
    for z, u in zip(zs, us):
        estimator.step(z, u, 0.1)
        np.testing.assert_allclose(estimator.x_hat, scale * (estimator.decoder @ estimator.rates),
                                   rtol=1e-12, atol=1e-12)                     # Eq. 12
    assert np.all(estimator.rates >= 0.0)


def test_initial_rates_are_non_negative_and_decode_to_the_initial_estimate():
    for preset in ('default', 'as_published'):
        scenario = rendezvous_scenario(preset)
        estimator = make_estimator('snn_emsif', scenario.estimator, runs=3)
        assert np.all(estimator.rates >= 0.0)
        np.testing.assert_allclose(estimator.x_hat, np.broadcast_to(scenario.x0, (3, 6)), atol=1e-9)
        # zero coding error: no neuron starts above threshold
        assert np.all(estimator.potentials <= estimator.thresholds)


@pytest.mark.parametrize('kind', SPIKING)
@pytest.mark.parametrize('rule', ['greedy', 'one_per_step', 'all_above'])
def test_compiled_network_equals_the_dense_paper_network(kind, rule):
    assert_compiled_equals_dense(kind, spike_rule=rule, neuron_count=60)


def assert_compiled_equals_dense(kind, **changes):
    """Same spikes and estimates, step by step, over a closed-loop rendezvous input."""
    scenario, zs, us = rendezvous_inputs(steps=150)
    fast = make_estimator(kind, scenario.estimator.replace(**changes))
    dense = DenseSpikingFilter(fast)
    for z, u in zip(zs, us):
        fast.step(z, u, 0.1)
        dense.step(z, u, 0.1)
        np.testing.assert_array_equal(fast.spikes, dense.spikes)
        np.testing.assert_allclose(fast.x_hat, dense.x_hat, rtol=1e-9, atol=1e-12)
    assert fast.total_spikes > 0


@pytest.mark.parametrize('kind', ['snn_ekf', 'snn_emsif'])
def test_compiled_network_equals_the_dense_network_with_a_per_sample_r_hat(kind):
    assert_compiled_equals_dense(kind, measurement_noise_units='per_sample', neuron_count=60)


def test_a_per_sample_r_hat_enters_eq_5_and_6_as_r_hat_dt_and_eq_9_as_it_is():
    """EKF: per_sample R_hat is exactly the spectral density R_hat dt. MSIF: the innovation
    covariance P^zz keeps the per-sample R_hat, and its covariance step takes R_hat as a
    sample's variance (the density R_hat dt over dt)."""
    scenario, zs, us = rendezvous_inputs(steps=200)
    dt = scenario.dt
    base = scenario.estimator
    per_sample = make_estimator('ekf', base.replace(measurement_noise_units='per_sample'))
    density = make_estimator('ekf', base.replace(measurement_noise_scale=base.measurement_noise_scale * dt))
    for z, u in zip(zs, us):
        per_sample.step(z, u, dt)
        density.step(z, u, dt)
    np.testing.assert_allclose(per_sample.x_hat, density.x_hat, rtol=1e-12)
    np.testing.assert_allclose(per_sample.P, density.P, rtol=1e-12, atol=1e-20)
    msif = make_estimator('emsif', base.replace(measurement_noise_units='per_sample'))
    p0, c = msif.P.copy(), scenario.model.measurement_matrix
    msif.step(zs[0], us[0], dt)
    r_hat = msif.settings.r_hat
    p_zz = c @ p0 @ c.T + r_hat
    np.testing.assert_allclose(msif.gain, np.linalg.pinv(c) @ np.diag(np.minimum(np.diag(p_zz) / 0.1, 1.0)),
                               rtol=1e-12)
    a = scenario.model.system_matrix(scenario.model.mean_motion)
    phi, q_d = van_loan(a, msif.settings.q_hat, dt)
    _, expected_p = sampled_kalman_step(p0, c, phi, q_d, r_hat)  # R_d = (R_hat dt) / dt
    np.testing.assert_allclose(msif.P, expected_p, rtol=1e-10, atol=1e-20)


def test_a_large_p0_or_a_long_step_keeps_p_positive_definite():
    """dt C P0 C^T R^-1 above 1 made the old Euler step of Eq. 6 indefinite, so such a P0 or step
    was refused; the sampled step (Decision 43) takes it: P stays positive definite, and it is
    the textbook Kalman step."""
    scenario, zs, us = rendezvous_inputs(steps=5)
    model, c = scenario.model, scenario.model.measurement_matrix
    a = model.system_matrix(model.mean_motion)
    per_sample = make_estimator('ekf', scenario.estimator.replace(  # R_hat = 0.05 m^2 per sample
        measurement_noise_units='per_sample', initial_covariance=(0.1, 0.1, 0.1, 1e-4, 1e-4, 1e-4)))
    for dt in (0.1, 5.0):
        p = per_sample.P.copy()
        per_sample.step(zs[0], us[0], dt)
        phi, q_d = van_loan(a, per_sample.settings.q_hat, dt)
        np.testing.assert_allclose(per_sample.P, sampled_kalman_step(p, c, phi, q_d, per_sample.settings.r_hat)[1],
                                   rtol=1e-9, atol=1e-18)
        assert np.linalg.eigvalsh(per_sample.P).min() > 0.0


@pytest.mark.parametrize('changes', [{}, {'network_coding': 'deviation'},
                                     {'network_coding': 'deviation', 'network_drive': 'nonlinear'},
                                     {'spike_rule': 'synchronous', 'ticks_per_sample': 20, 'firing_slots': 2}],
                         ids=['paper', 'deviation', 'deviation_f_drive', 'synchronous'])
def test_compiled_network_equals_the_dense_network_on_the_nonlinear_van_der_pol(changes):
    """The paper's coding, the deviation coding (test_network_coding.py) on either drive, and the
    synchronous rule."""
    scenario = van_der_pol_scenario(**changes)
    rng = np.random.default_rng(3)
    fast = make_estimator('snn_emsif', scenario.estimator, scenario.model)
    dense = DenseSpikingFilter(fast)
    for k in range(300):
        z = np.array([2.0 * np.cos(0.01 * k) + 0.1 * rng.normal()])
        fast.step(z, np.zeros(1), 0.01)
        dense.step(z, np.zeros(1), 0.01)
        np.testing.assert_array_equal(fast.spikes, dense.spikes)
        np.testing.assert_allclose(fast.x_hat, dense.x_hat, rtol=1e-9, atol=1e-12)
    assert fast.total_spikes > 0


def test_spike_rules_do_what_they_say():
    scenario, zs, us = rendezvous_inputs(steps=200)
    for rule in ('greedy', 'one_per_step', 'all_above'):
        estimator = make_estimator('snn_emsif', scenario.estimator.replace(spike_rule=rule))
        for z, u in zip(zs, us):
            estimator.step(z, u, 0.1)
            if rule == 'one_per_step':
                assert estimator.spike_count <= 1
            elif rule == 'all_above':
                assert estimator.spikes.max() <= 1
            else:  # greedy leaves no live neuron above threshold
                assert np.all(estimator.potentials <= estimator.thresholds + 1e-12)


# ---------------------------------------------------------------- the synchronous (local) rule
@pytest.mark.parametrize('kind', ['snn_ekf', 'snn_emsif_weighted'])
@pytest.mark.parametrize('changes', [{}, {'refractory_ticks': 2, 'firing_slots': 3, 'ticks_per_sample': 20},
                                     {'network_coding': 'deviation', 'state_scale': (1e-3,) * 3 + (1e-5,) * 3}])
def test_compiled_synchronous_rule_equals_the_dense_network_spike_for_spike(kind, changes):
    assert_compiled_equals_dense(kind, spike_rule='synchronous', neuron_count=60, **changes)


@pytest.mark.parametrize('kind', ['snn_ekf', 'snn_emsif'])
def test_synchronous_rule_with_one_tick_and_no_remedy_is_the_all_above_rule(kind):
    scenario, zs, us = rendezvous_inputs(steps=100)
    local = make_estimator(kind, scenario.estimator.replace(
        spike_rule='synchronous', ticks_per_sample=1, threshold_widening=0.0, refractory_ticks=0, firing_slots=1))
    all_above = make_estimator(kind, scenario.estimator.replace(spike_rule='all_above'))
    for z, u in zip(zs, us):
        local.step(z, u, 0.1)
        all_above.step(z, u, 0.1)
        np.testing.assert_array_equal(local.spikes, all_above.spikes)
        np.testing.assert_array_equal(local.x_hat, all_above.x_hat)
    assert local.total_spikes > 0


def test_the_synchronous_rules_tick_settings_retune_between_steps_as_if_built_with_them():
    scenario, zs, us = rendezvous_inputs(steps=80)
    tick = {'ticks_per_sample': 30, 'threshold_widening': 0.5, 'refractory_ticks': 2, 'firing_slots': 3}
    config = scenario.estimator.replace(spike_rule='synchronous', neuron_count=60)
    retuned = make_estimator('snn_ekf', config)
    built = make_estimator('snn_ekf', config.replace(**tick))
    retuned.retune(**tick)
    for z, u in zip(zs, us):
        retuned.step(z, u, 0.1)
        built.step(z, u, 0.1)
        np.testing.assert_array_equal(retuned.spikes, built.spikes)
    np.testing.assert_array_equal(retuned.x_hat, built.x_hat)
    assert built.total_spikes > 0


def test_synchronous_rule_compares_no_neurons_two_above_threshold_in_a_tick_both_fire():
    """A step without input (r = 0, z = 0, u = 0) from potentials that put neurons 0 and 1,
    which code the same direction, above threshold: the synchronous rule fires both in the
    first tick (each from its own potential); greedy fires the larger only (its spike takes the
    other below threshold). Neuron 2, below its threshold, stays silent under both."""
    scenario = rendezvous_scenario()
    config = scenario.estimator.replace(neuron_count=3, ticks_per_sample=4, threshold_widening=0.0, firing_slots=1)
    fired = {}
    for rule in ('synchronous', 'greedy'):
        estimator = make_estimator('snn_ekf', config.replace(spike_rule=rule))
        net = estimator.network
        net.decoder[0] = 0.0
        net.decoder[0, 0, :] = (1.0, 1.0, 0.1)
        net.gram[0] = net.decoder[0].T @ net.decoder[0]
        net.thresholds[0] = 0.5 * np.sum(net.decoder[0] ** 2, axis=0)   # 0.5, 0.5, 0.005
        net.r[0] = 0.0
        net.v[0] = (0.6, 0.7, 0.0)
        estimator.state.x_hat[0] = 0.0
        estimator.step(np.zeros(3), np.zeros(3), 0.1)
        fired[rule] = estimator.spikes.copy()
    np.testing.assert_array_equal(fired['synchronous'], [1, 1, 0])
    np.testing.assert_array_equal(fired['greedy'], [0, 1, 0])


def test_synchronous_rule_fires_each_neuron_only_in_its_slot_and_after_its_refractory_ticks():
    scenario, zs, us = rendezvous_inputs(steps=60)
    ticks, slots = 12, 4
    config = scenario.estimator.replace(spike_rule='synchronous', ticks_per_sample=ticks, firing_slots=slots,
                                        refractory_ticks=slots, neuron_count=40)
    estimator = make_estimator('snn_ekf', config)
    for z, u in zip(zs, us):
        estimator.step(z, u, 0.1)
        # slots: at most ticks / slots spikes per neuron per step; refractory >= slots: every other slot
        assert estimator.spikes.max() <= ticks // slots // 2 + 1
    assert estimator.total_spikes > 0


@pytest.mark.slow
def test_a_fine_decoder_reproduces_the_non_spiking_twin():
    scenario = rendezvous_scenario()
    default = scenario.estimator
    fine = default.replace(state_scale=np.asarray(default.state_scale) / 10.0)
    for kind in SPIKING:
        twin = simulate(scenario, TWIN_OF[kind], config=fine)
        gaps = [np.abs(simulate(scenario, kind, config=config).estimate - twin.estimate).max(axis=(0, 1))
                for config in (default, fine)]
        assert np.all(gaps[1][:3] < 1e-3) and np.all(gaps[1][3:] < 1e-5), (kind, gaps[1])  # m, m/s
        assert np.all(gaps[1] < 0.3 * gaps[0]), (kind, gaps)  # finer coding, closer to the twin


def test_silencing_half_the_neurons_keeps_the_estimate_bounded_and_it_recovers():
    scenario = rendezvous_scenario()
    intact = simulate(scenario, 'snn_emsif')
    dead = list(range(0, 200, 2))
    damaged = simulate(scenario, 'snn_emsif', events={1000: lambda est: est.silence(dead)})
    after = damaged.error[0, 1000:]
    assert np.all(np.isfinite(after))
    assert np.abs(after[:, :3]).max() < 0.2 and np.abs(after[:, 3:]).max() < 0.02
    ratio = damaged.rmse() / intact.rmse()
    assert np.all(ratio < 2.0), ratio
    assert damaged.final_range()[0] < 0.1


def test_silenced_neurons_never_fire():
    scenario, zs, us = rendezvous_inputs(steps=200)
    estimator = make_estimator('snn_emsif', scenario.estimator.replace(silenced_neurons=(0, 1, 2)))
    estimator.silence([0, 1, 2, 7])
    for z, u in zip(zs, us):
        estimator.step(z, u, 0.1)
        assert np.all(estimator.spikes[[0, 1, 2, 7]] == 0)
    assert estimator.silenced == (0, 1, 2, 7)


# ---------------------------------------------------------------- determinism and batches
def test_same_seed_gives_identical_results_and_another_seed_does_not():
    scenario = rendezvous_scenario()
    first = simulate(scenario, 'snn_emsif', seed=4)
    second = simulate(scenario, 'snn_emsif', seed=4)
    other = simulate(scenario, 'snn_emsif', seed=5)
    np.testing.assert_array_equal(first.estimate, second.estimate)
    np.testing.assert_array_equal(first.raster, second.raster)
    assert not np.array_equal(first.estimate, other.estimate)


def test_each_run_of_a_batch_equals_the_single_run_with_its_seed():
    scenario = rendezvous_scenario()
    batch = simulate(scenario, 'snn_ekf', runs=3, seed=10)
    single = simulate(scenario, 'snn_ekf', runs=1, seed=11)
    np.testing.assert_allclose(batch.estimate[1], single.estimate[0], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(batch.spikes_per_step[1], single.spikes_per_step[0])


@pytest.mark.parametrize('kind, coding', [('snn_ekf', 'state'), ('snn_ekf', 'deviation'), ('emsif_weighted', 'state')])
def test_restart_puts_the_chosen_runs_back_at_their_start_and_leaves_the_others(kind, coding):
    """A restarted run equals the same run of a new estimator stepped alike from then on, spike
    for spike; the other runs are not touched."""
    scenario, zs, us = rendezvous_inputs(steps=40)
    config = scenario.estimator.replace(initial_state_dispersion=True, network_coding=coding)
    estimator = make_estimator(kind, config, runs=3, seeds=[4, 5, 6])
    fresh = make_estimator(kind, config, runs=3, seeds=[4, 5, 6])
    for z, u in zip(zs[:20], us[:20]):
        estimator.step(np.tile(z, (3, 1)), np.tile(u, (3, 1)), 0.1)
    before = (estimator.x_hat.copy(), estimator.P.copy())
    totals = np.array(estimator.total_spikes) if estimator.spiking else None
    estimator.restart([1])
    np.testing.assert_array_equal(estimator.x_hat[[0, 2]], before[0][[0, 2]])
    np.testing.assert_array_equal(estimator.P[[0, 2]], before[1][[0, 2]])
    np.testing.assert_array_equal(estimator.x_hat[1], fresh.x_hat[1])
    np.testing.assert_array_equal(estimator.P[1], np.diag(config.initial_covariance))
    if estimator.spiking:
        np.testing.assert_array_equal(estimator.rates[1], fresh.rates[1])
        np.testing.assert_array_equal(estimator.potentials[1], fresh.potentials[1])
        np.testing.assert_array_equal(estimator.total_spikes, totals)
    for z, u in zip(zs[20:], us[20:]):
        estimator.step(np.tile(z, (3, 1)), np.tile(u, (3, 1)), 0.1)
        fresh.step(np.tile(z, (3, 1)), np.tile(u, (3, 1)), 0.1)
        np.testing.assert_array_equal(estimator.x_hat[1], fresh.x_hat[1])
        if estimator.spiking:
            np.testing.assert_array_equal(estimator.spikes[1], fresh.spikes[1])


@pytest.mark.parametrize('kind', ['ekf', 'emsif_weighted'])
def test_a_state_that_becomes_non_finite_is_reported_after_every_run_took_the_step(kind):
    """The compiled step checks the new estimate of each run: one that overflows raises
    FloatingPointError once every run is stepped (the other run as if alone). With fast-math the
    check made right after the arithmetic was folded away and a NaN estimate went unreported."""
    estimator, alone = make_estimator(kind, runs=2), make_estimator(kind)
    estimator.set_state(np.array([[70.0, 30.0, -5.0, 0.0, 0.0, 0.0], [1e308, 1e308, 1e308, 0.0, 0.0, 0.0]]))
    alone.set_state(np.array([70.0, 30.0, -5.0, 0.0, 0.0, 0.0]))
    with np.errstate(all='ignore'), pytest.raises(FloatingPointError, match='non-finite'):
        estimator.step(np.array([[70.0, 30.0, -5.0], [1e308, -1e308, 1e308]]), np.zeros((2, 3)), 0.1)
    alone.step(np.array([70.0, 30.0, -5.0]), np.zeros(3), 0.1)
    np.testing.assert_array_equal(estimator.x_hat[0], alone.x_hat)
    assert not np.isfinite(estimator.x_hat[1]).all()


def test_non_finite_input_is_refused_and_changes_nothing():
    estimator = make_estimator('snn_emsif')
    before = (estimator.x_hat.copy(), estimator.P.copy(), estimator.rates.copy())
    for z, u in [([np.nan, 0, 0], [0, 0, 0]), ([0, 0, 0], [np.inf, 0, 0])]:
        with pytest.raises(ValueError, match='finite'):
            estimator.step(np.array(z, dtype=float), np.array(u, dtype=float), 0.1)
    for dt in (0.0, -0.1, np.nan, np.inf):
        with pytest.raises(ValueError, match='dt'):
            estimator.step(np.zeros(3), np.zeros(3), dt)
    np.testing.assert_array_equal(estimator.x_hat, before[0])
    np.testing.assert_array_equal(estimator.P, before[1])
    np.testing.assert_array_equal(estimator.rates, before[2])
    assert estimator.steps == 0


def test_reset_and_set_state_re_encode_the_network():
    estimator = make_estimator('snn_emsif')
    for _ in range(20):
        estimator.step(np.array([70.0, 30.0, -5.0]), np.zeros(3), 0.1)
    target = np.array([1.0, 2.0, 3.0, 0.01, 0.02, 0.03])
    estimator.set_state(target, P=np.eye(6))
    np.testing.assert_allclose(estimator.x_hat, target, atol=1e-9)
    np.testing.assert_array_equal(estimator.P, np.eye(6))
    estimator.reset()
    np.testing.assert_allclose(estimator.x_hat, EstimatorConfig().initial_state, atol=1e-9)
    assert estimator.total_spikes == 0


def test_a_state_the_network_cannot_represent_is_refused_quietly_and_changes_nothing():
    """x_hat / S overflows for 1e305 m on the 1e-4 velocity scale: a ValueError, no numpy
    RuntimeWarning on the way, and the previous estimate kept."""
    estimator = make_estimator('snn_emsif')
    before = estimator.x_hat.copy()
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        with pytest.raises(ValueError, match='cannot encode'):
            estimator.set_state(np.array([0.0, 0.0, 0.0, 1e305, 0.0, 0.0]))
    np.testing.assert_array_equal(estimator.x_hat, before)


# ---------------------------------------------------------------- bad configuration
@pytest.mark.parametrize('changes, message', [
    ({'neuron_count': 0}, 'neuron_count'),
    ({'neuron_count': -5}, 'neuron_count'),
    ({'neuron_count': 2.5}, 'neuron_count'),
    ({'leak_rate': -0.1}, 'leak_rate'),
    ({'boundary_layer': 0.0}, 'boundary_layer'),
    ({'boundary_layer': (0.1, -0.1, 0.1)}, 'boundary_layer'),
    ({'boundary_layer': (0.1, 0.1)}, 'boundary_layer'),
    ({'decoder_variance': 0.0}, 'decoder_variance'),
    ({'initial_state': (1.0, 2.0)}, 'initial_state'),
    ({'initial_covariance': [1.0] * 35}, 'initial_covariance'),
    ({'initial_covariance': (1.0, 1.0, 1.0, 1.0, 1.0, -1.0)}, 'positive definite'),
    ({'measurement_noise': 0.0}, 'measurement_noise'),
    ({'process_noise': -1.0}, 'process_noise'),
    ({'measurement_noise_scale': 0.0}, 'measurement_noise_scale'),
    ({'state_scale': (1.0, 1.0, 1.0, 1.0, 1.0, 0.0)}, 'state_scale'),
    ({'spike_rule': 'fastest'}, 'spike_rule'),
    ({'discretization': 'rk45'}, 'discretization'),
    ({'measurement_noise_units': 'variance'}, 'measurement_noise_units'),
    ({'silenced_neurons': (200,)}, 'silenced_neurons'),
    ({'initial_state': (np.nan, 0, 0, 0, 0, 0)}, 'finite'),
    ({'ticks_per_sample': 0}, 'ticks_per_sample'),
    ({'firing_slots': 0}, 'firing_slots'),
    ({'threshold_widening': -0.5}, 'threshold_widening'),
    ({'refractory_ticks': -1}, 'refractory_ticks'),
    ({'spike_rule': 'synchronous', 'precision': 'loihi', 'gain_schedule': 'steady_state',
      'network_coding': 'deviation'}, 'float64 network only'),
])
def test_bad_configuration_raises_a_value_error_saying_what_to_fix(changes, message):
    with pytest.raises(ValueError, match=message):
        make_estimator('snn_emsif', EstimatorConfig().replace(**changes))


def test_unknown_kind_and_large_leak_steps_are_refused():
    with pytest.raises(ValueError, match='unknown filter kind'):
        make_estimator('ukf')
    estimator = make_estimator('snn_ekf', EstimatorConfig(leak_rate=20.0))
    with pytest.raises(ValueError, match='leak_rate'):
        estimator.step(np.zeros(3), np.zeros(3), 0.1)


def test_a_non_symmetric_covariance_is_refused():
    p0 = np.eye(6)
    p0[0, 1] = 0.5
    with pytest.raises(ValueError, match='symmetric'):
        make_estimator('ekf', EstimatorConfig(initial_covariance=p0))


def test_any_model_implementing_the_interface_works(double_integrator):
    config = EstimatorConfig(neuron_count=40, process_noise=1e-4, measurement_noise=1e-2,
                             process_noise_scale=1.0, measurement_noise_scale=1.0,
                             initial_covariance=(1.0, 1.0), initial_state=(0.5, 0.0),
                             boundary_layer=0.1, state_scale=(0.01, 0.01))
    estimator = make_estimator('snn_ekf', config, double_integrator)
    for _ in range(500):
        estimator.step(np.array([0.0]), np.array([0.0]), 0.01)
    assert abs(estimator.x_hat[0]) < 0.05


@pytest.mark.parametrize('drive', ['linearized', 'nonlinear'])
def test_van_der_pol_network_integrates_the_drive_it_is_set_to(drive):
    """network_drive linearized: one step of the network moves the estimate by dt A(x_hat) x_hat
    (Eq. 14; A the Jacobian of Eq. 27); nonlinear: by its twin's f step. With mu = 0.5 at
    x = (1.5, 1) the two differ by dt 2 mu x1^2 x2 = 0.0225, far above the spike quantum."""
    model = VanDerPol(mu=0.5)
    x = np.array([1.5, 1.0])
    dt, u = 0.01, np.zeros(1)
    config = van_der_pol_scenario().estimator.replace(
        network_drive=drive, neuron_count=400, state_scale=(1e-3, 1e-3), initial_state=tuple(x),
        boundary_layer=1e9)  # a vanishing gain: the step is the prediction alone
    estimator = make_estimator('snn_emsif', config, model)
    np.testing.assert_allclose(estimator.x_hat, x, atol=2e-3)
    start = estimator.x_hat.copy()
    estimator.step(model.h(start), u, dt)  # nu = 0
    linearized = start + dt * model.jacobian(start, u) @ start
    nonlinear = model.transition(start, u, dt)
    assert np.abs(linearized - nonlinear).max() > 0.02
    expected, other = (linearized, nonlinear) if drive == 'linearized' else (nonlinear, linearized)
    np.testing.assert_allclose(estimator.x_hat, expected, atol=2e-3)
    assert np.abs(estimator.x_hat - other).max() > 0.015


@pytest.mark.parametrize('units', ['spectral_density', 'per_sample'])
@pytest.mark.parametrize('kind', ['ekf', 'emsif', 'esif', 'emsif_weighted'])
@pytest.mark.parametrize('schedule', ['time_varying', 'steady_state'])
def test_compiled_direct_filters_equal_the_written_out_equations(kind, units, schedule):
    from snn_estimator.filters.reference import DenseFilter
    scenario, zs, us = rendezvous_inputs(steps=200)
    fast = make_estimator(kind, scenario.estimator.replace(measurement_noise_units=units,
                                                           gain_schedule=schedule))
    dense = DenseFilter(fast)
    for z, u in zip(zs, us):
        fast.step(z, u, 0.1)
        dense.step(z, u, 0.1)
    np.testing.assert_allclose(fast.x_hat, dense.x_hat, rtol=1e-10)
    if fast.P is not None:
        np.testing.assert_allclose(fast.P, dense.P, rtol=1e-9, atol=1e-15)  # the two CARE solutions agree to ~1e-16


@pytest.mark.parametrize('kind', ['ekf', 'snn_emsif'])
def test_predict_without_a_measurement_propagates_the_model_only(kind):
    scenario = rendezvous_scenario()
    model = scenario.model
    estimator = make_estimator(kind, scenario.estimator)
    x, p = estimator.x_hat.copy(), estimator.P.copy()
    u = np.array([0.01, 0.0, -0.02])
    estimator.predict(u, 0.1)
    phi, gamma = model.discrete_matrices(0.1)
    tolerance = 1e-12 if kind == 'ekf' else 5e-3  # spike quantisation of the network
    np.testing.assert_allclose(estimator.x_hat, phi @ x + gamma @ u, atol=tolerance)
    phi, q_d = van_loan(model.system_matrix(model.mean_motion), estimator.settings.q_hat, 0.1)
    np.testing.assert_allclose(estimator.P, phi @ p @ phi.T + q_d, rtol=1e-12, atol=1e-20)
    assert np.all(estimator.gain == 0.0)


def test_retune_changes_gain_settings_between_steps_and_refuses_bad_values():
    estimator = make_estimator('emsif')
    estimator.retune(boundary_layer=1e-3, measurement_noise_scale=1.0)
    estimator.step(np.array([70.1, 30.0, -5.0]), np.zeros(3), 0.1)
    np.testing.assert_allclose(np.diag(estimator.gain[:3]), 1.0)  # saturated with the small delta
    before = (estimator.config, estimator.settings)
    for bad in ({'boundary_layer': -1.0}, {'leak_rate': -0.5}, {'measurement_noise_scale': 0.0}):
        with pytest.raises(ValueError):
            estimator.retune(**bad)
        assert (estimator.config, estimator.settings) == before
    with pytest.raises(ValueError, match='cannot change'):
        estimator.retune(neuron_count=10)


def test_normalised_innovation_squared():
    estimator = make_estimator('ekf')
    p = estimator.P
    z = estimator.x_hat[:3] + np.array([0.1, 0.0, 0.0])
    r = 1e-2 * np.eye(3)
    expected = 0.1 ** 2 / (p[0, 0] + 1e-2)
    assert estimator.innovation_nis(z, r)[0] == pytest.approx(expected)


def test_compiled_innovation_nis_matches_the_textbook_formula_per_run():
    """The compiled kernel against nu^T inv(C P C^T + R) nu written out with numpy, for a batch
    of runs with different (full, correlated) covariances, with and without P."""
    from snn_estimator.filters import kernels
    rng = np.random.default_rng(7)
    runs, n, m = 4, 6, 3
    c = rng.normal(size=(m, n))
    x_hat = rng.normal(size=(runs, n))
    roots = rng.normal(size=(runs, n, n))
    p = roots @ roots.transpose(0, 2, 1) + 0.1 * np.eye(n)
    root = rng.normal(size=(m, m))
    r = root @ root.T + 0.5 * np.eye(m)
    z = rng.normal(size=(runs, m))
    for has_covariance in (True, False):
        got = kernels.innovation_nis(z, x_hat, c, p, r, has_covariance)
        for b in range(runs):
            nu = z[b] - c @ x_hat[b]
            s = c @ p[b] @ c.T + r if has_covariance else r
            assert got[b] == pytest.approx(nu @ np.linalg.inv(s) @ nu, rel=1e-10)
    with pytest.raises(ValueError, match='3x3'):
        make_estimator('ekf').innovation_nis(np.zeros(3), np.eye(2))


# ---------------------------------------------------------------- remedies for partial measurements
def test_the_weighted_msif_gain_keeps_the_sliding_rows_and_corrects_the_velocity():
    """K = P C^T (C P C^T)^-1 sat(diag(Pzz)/delta): C K is the paper's MSIF sat on the measured
    axes, and the unmeasured rows are P_vp P_pp^-1 times it (with C = [I 0])."""
    scenario, zs, us = rendezvous_inputs(steps=3)
    weighted = make_estimator('emsif_weighted', scenario.estimator)
    p = weighted.P.copy()
    weighted.step(zs[0], us[0], 0.1)
    c = weighted.model.measurement_matrix
    pzz = c @ p @ c.T + weighted.settings.r_hat
    sat = np.minimum(np.diag(pzz) / weighted.settings.boundary_layer, 1.0)
    np.testing.assert_allclose(c @ weighted.gain, np.diag(sat), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(weighted.gain[3:], p[3:, :3] @ np.linalg.inv(p[:3, :3]) @ np.diag(sat),
                               rtol=1e-12, atol=1e-15)
    literal = make_estimator('emsif', scenario.estimator)
    literal.step(zs[0], us[0], 0.1)
    assert np.all(literal.gain[3:] == 0.0)  # Eq. 8 with C^+ never corrects a velocity


def test_the_gain_covariance_is_that_of_the_gain_used_and_equals_eq_6_for_the_kalman_gain():
    """P' = (Phi - dt K C) P (Phi - dt K C)^T + dt^2 K R_d K^T + Q_d, the covariance of the gain
    used; with the Kalman gain of the step it is the Kalman step (Eq. 6 sampled, Decision 43)."""
    from snn_estimator.filters.reference import written_out_covariance_step
    scenario = rendezvous_scenario()
    ekf = make_estimator('ekf', scenario.estimator)
    weighted = make_estimator('emsif_weighted', scenario.estimator)
    p = np.diag([0.02, 0.03, 0.01, 2e-4, 1e-4, 3e-4]) + 1e-5
    c = scenario.model.measurement_matrix
    phi, _ = van_loan(scenario.model.system_matrix(scenario.model.mean_motion), ekf.settings.q_hat, 0.1)
    kalman = phi @ p @ c.T @ np.linalg.inv(c @ p @ c.T + ekf.settings.r_hat / 0.1) / 0.1
    riccati = written_out_covariance_step(ekf, p, np.zeros(6), kalman, 0.1)
    assert weighted.covariance_law == 'gain'
    np.testing.assert_allclose(written_out_covariance_step(weighted, p, np.zeros(6), kalman, 0.1), riccati,
                               rtol=1e-10)


@pytest.mark.parametrize('kind', ['ekf', 'emsif', 'esif', 'emsif_weighted'])
@pytest.mark.parametrize('process_noise_scale', [0.9, 1e3])
def test_the_steady_state_gain_equals_the_written_out_fixed_point_of_eq_6(kind, process_noise_scale):
    """steady_state_gain (scipy's Schur DARE solver, the SIF's closed-form mean saturation)
    against reference.py's own solution (the doubling algorithm, quadrature), for every gain
    law, with the paper's Q_hat and a larger one; the fixed point of the sampled step of Eq. 6
    (Decision 43) is checked by its residual too."""
    from snn_estimator.filters.estimators import steady_state_gain
    from snn_estimator.filters.reference import discrete_riccati_fixed_point, written_out_steady_state_gain
    scenario = rendezvous_scenario(process_noise_scale=process_noise_scale)
    estimator = make_estimator(kind, scenario.estimator)
    s, model = estimator.settings, scenario.model
    c, a = model.measurement_matrix, model.jacobian(np.zeros(6), np.zeros(3))
    phi, q_d = van_loan(a, s.q_hat, 0.1)
    r_d = s.r_hat / 0.1
    p = discrete_riccati_fixed_point(phi, c, q_d, r_d)
    _, following = sampled_kalman_step(p, c, phi, q_d, r_d)
    assert np.abs(following - p).max() < 1e-9 * np.abs(p).max()
    k_d = p @ c.T @ np.linalg.inv(c @ p @ c.T + r_d)
    assert np.all(np.abs(np.linalg.eigvals(phi @ (np.eye(6) - k_d @ c))) < 1.0)  # stabilising
    gain = steady_state_gain(estimator.gain_law, model, s, 0.1)
    np.testing.assert_allclose(gain, written_out_steady_state_gain(estimator, 0.1), rtol=1e-6, atol=1e-12)


def test_a_constant_gain_network_has_constant_weights_equal_to_the_steady_state_gain():
    from snn_estimator.filters.estimators import steady_state_gain
    scenario, zs, us = rendezvous_inputs(steps=20)
    config = scenario.estimator.replace(gain_schedule='steady_state')
    estimator = make_estimator('snn_emsif_weighted', config)
    before = estimator.weights(dt=0.1)
    for z, u in zip(zs, us):
        estimator.step(z, u, 0.1)
    after = estimator.weights(dt=0.1)
    for name in ('F', 'Omega_s', 'Omega_f', 'Omega_k', 'F_k'):
        np.testing.assert_array_equal(before[name], after[name])
    gain = steady_state_gain('msif_weighted', scenario.model, estimator.settings, 0.1)
    np.testing.assert_allclose(estimator.gain, gain, rtol=1e-12)
    scale = estimator.settings.state_scale
    np.testing.assert_allclose(after['F_k'], estimator.decoder.T @ (gain / scale[:, None]), rtol=1e-12)


def test_a_constant_gain_needs_a_linear_model():
    with pytest.raises(ValueError, match='linear model'):
        make_estimator('ekf', van_der_pol_scenario().estimator.replace(gain_schedule='steady_state'),
                       VanDerPol())


def test_a_dispersed_start_is_drawn_from_p0_per_seed_and_the_same_alone_or_in_a_batch():
    config = EstimatorConfig(initial_state_dispersion=True)
    batch = make_estimator('ekf', config.replace(seed=10), runs=400)
    alone = make_estimator('ekf', config.replace(seed=13))
    np.testing.assert_array_equal(batch.batch_x_hat[3], alone.x_hat)
    errors = batch.batch_x_hat - np.array(config.initial_state)
    sigma = np.sqrt(np.array(config.initial_covariance))
    np.testing.assert_allclose(errors.std(axis=0) / sigma, 1.0, atol=0.12)  # 400 draws: ~3.5 % sd
    assert np.abs(errors.mean(axis=0) / sigma).max() < 0.2
    alone.step(np.array([70.0, 30.0, -5.0]), np.zeros(3), 0.1)
    alone.reset()
    np.testing.assert_array_equal(alone.x_hat, batch.batch_x_hat[3])  # the same draw again


def test_innovation_nis_is_infinite_not_a_crash_when_the_innovation_covariance_is_singular():
    # C P C^T + R singular (here R = -C P C^T): the ROS estimator's per-step NIS check raised
    # LinAlgError out of its subscription callback and the node died
    estimator = make_estimator('ekf')
    estimator.set_state(np.zeros(6), np.eye(6))
    assert np.isinf(estimator.innovation_nis(np.ones(3), -np.eye(3))[0])


@pytest.mark.parametrize('covariance, message', [
    (np.diag([-1e-2, -1e-2, -1e-2, 1.0, 1.0, 1.0]), 'positive definite'),
    (np.eye(6) + np.triu(np.ones((6, 6)), 1), 'symmetric'),
    (np.full((6, 6), np.inf), 'finite')])
def test_a_covariance_that_is_none_is_refused_with_its_reason_and_nothing_changes(covariance, message):
    """The covariance step keeps P positive definite (Decision 43), so it must start so: set_state
    and reset refuse anything else, naming what is wrong."""
    estimator = make_estimator('ekf')
    before = (estimator.x_hat.copy(), estimator.P.copy())
    with pytest.raises(ValueError, match=message):
        estimator.set_state(np.zeros(6), covariance)
    with pytest.raises(ValueError, match=message):
        estimator.reset(np.zeros(6), covariance)
    np.testing.assert_array_equal(estimator.x_hat, before[0])
    np.testing.assert_array_equal(estimator.P, before[1])


@pytest.mark.parametrize('kind', ['ekf', 'snn_emsif_weighted'])
def test_the_kernels_entry_point_sees_any_input_as_the_dispatcher_would(kind):
    """After the first step the kernel is called through its compiled entry point (no per-call
    type dispatch), which reads arrays as the first call's types: integer, non-contiguous and
    read-only inputs must still give exactly what clean float arrays give."""
    config = EstimatorConfig(neuron_count=30)
    clean, odd = make_estimator(kind, config), make_estimator(kind, config)
    wide = np.zeros((3, 6))
    readonly = np.zeros(3)
    readonly.flags.writeable = False
    for k in range(40):
        z = np.array([70.0 - k, 30.0, -5.0])
        wide[:, 0] = z
        inputs = (z, wide[:, 0], [70 - k, 30, -5])[k % 3]  # plain first, then a non-contiguous column, ints
        clean.step(z, np.zeros(3), 0.1)
        odd.step(inputs, readonly if k % 2 else [0, 0, 0], 0.1)
    assert odd.program.on_entry_point  # the fast path is the one in use
    np.testing.assert_array_equal(odd.x_hat, clean.x_hat)


@pytest.mark.parametrize('kind', ['emsif', 'snn_emsif'])
def test_the_packed_step_is_the_kernel_on_the_three_tuples_bit_for_bit(kind):
    """A single filter passes its constants, state and network as one PackedRef (one pointer to
    unbox per call, not ~23 arrays): the same kernel inside, so every step equals the kernel
    called on the three tuples of a twin filter, to the bit, also when dt changes every step
    (the dt constants are written in place, the PackedRef is kept, not rebuilt)."""
    config = EstimatorConfig(neuron_count=30)
    packed, tuples = make_estimator(kind, config), make_estimator(kind, config)
    rng = np.random.default_rng(3)
    for k in range(60):
        dt = 0.1 if k < 20 else float(rng.uniform(0.05, 0.15))  # jittered stamps from step 20
        z, u = np.array([[70.0 - k, 30.0, -5.0]]) + rng.normal(0.0, 0.1, (1, 3)), rng.normal(0.0, 1e-3, (1, 3))
        packed.step(z, u, dt)
        if k == 20:
            ref = packed.program.packed.ref
        program = tuples.program
        if dt != program.dt:
            tuples.prepare(dt)
        dynamics, drift = program.dynamics(tuples.batch_x_hat, u, dt)
        status, _ = program.kernel(program.constants, program.state, program.network, program.all_runs, dt, dynamics,
                                   drift, z, u, tuples.network.zero_noise)
        assert status == kernels.STATUS_OK
        np.testing.assert_array_equal(packed.x_hat, tuples.x_hat)
        np.testing.assert_array_equal(packed.P, tuples.P)
    assert packed.program.packed.ref is ref  # 40 steps of other dts: no rebuild
    if packed.spiking:
        np.testing.assert_array_equal(packed.spikes, tuples.spikes)


def test_packed_writes_the_dt_constants_in_place_and_rebuilds_for_the_others():
    """Packed keeps private copies of the constants a dt changes (the caller's arrays are
    never written) and updates them in place; any other constant gets a new tuple and PackedRef."""
    estimator = make_estimator('ekf', EstimatorConfig())
    packed = estimator.program.packed
    given = np.eye(3) * 2.0
    before = packed.ref
    packed.update(r_sample=given)
    assert packed.ref is before and packed.constants[gains.R_SAMPLE] is not given
    np.testing.assert_array_equal(packed.constants[gains.R_SAMPLE], given)
    packed.update(r_sample=np.eye(3) * 5.0)
    np.testing.assert_array_equal(given, np.eye(3) * 2.0)  # the caller's array as it was
    packed.update(leak=0.5)
    assert packed.ref is not before and packed.constants[gains.LEAK] == 0.5


def _snapshot_cases():
    """Every filter kind, and the variants whose state lives elsewhere: membrane noise (the
    generators), the deviation coding (the prediction), the chip network (its own arrays), a
    nonlinear sensor (H re-linearised each step), a batch of runs."""
    scenario = rendezvous_scenario(initial_state_dispersion=True)
    config = scenario.estimator
    cases = [pytest.param(kind, config, {}, id=kind) for kind in FILTER_KINDS]
    return cases + [
        pytest.param('snn_ekf', config.replace(membrane_noise=1e-3), {}, id='snn_ekf-membrane_noise'),
        pytest.param('snn_emsif_weighted', config.replace(network_coding='deviation'), {}, id='deviation_coding'),
        pytest.param('snn_emsif', config.replace(gain_schedule='steady_state', precision='loihi'), {}, id='chip'),
        pytest.param('snn_ekf', config, {'lidar': True}, id='snn_ekf-lidar'),
        pytest.param('ekf', config, {'lidar': True}, id='ekf-lidar'),
        pytest.param('snn_emsif_weighted', config, {'runs': 3}, id='three_runs')]


@pytest.mark.parametrize('kind, config, options', _snapshot_cases())
def test_restore_returns_the_filter_to_its_snapshot_bit_for_bit_and_the_steps_again_equal(kind, config, options):
    from snn_estimator.measurements import make_model
    scenario, zs, us = rendezvous_inputs(steps=40)
    runs = options.get('runs', 1)
    measurement = None
    if options.get('lidar'):  # looking back along -x at the rendezvous positions
        measurement = make_model('range_azimuth_elevation', [1e-2, 1e-6, 1e-6], mounting_rotation=(0.0, 0.0, 1.0, 0.0))
        zs = measurement.h(np.c_[zs, np.zeros_like(zs)])
        config = config.replace(measurement_noise=measurement.noise, measurement_noise_units='per_sample')
    estimator = make_estimator(kind, config, scenario.model, runs=runs, measurement=measurement)

    def state():
        values = [estimator.x_hat.copy(), estimator.gain.copy(), estimator.steps, estimator.capped_steps]
        if estimator.P is not None:
            values.append(estimator.P.copy())
        if estimator.spiking:
            values += [estimator.rates.copy(), estimator.potentials.copy(), estimator.spikes.copy(),
                       np.copy(estimator.total_spikes), estimator.prediction]
        return values

    def batch(value):
        return np.broadcast_to(value, (runs, 3))

    def steps(ks):
        return [estimator.step(batch(zs[k]), batch(us[k] if k % 4 else np.zeros(3)), scenario.dt).copy() for k in ks]

    steps(range(20))
    before, snapshot = state(), estimator.snapshot()
    first = steps(range(20, 30))
    assert not np.array_equal(first[-1], before[0])
    estimator.step(batch(zs[30]), batch(us[30] * 3), scenario.dt)  # another control: the step to redo
    estimator.restore(snapshot)
    for restored, saved in zip(state(), before):
        np.testing.assert_array_equal(restored, saved)
    for again, once in zip(steps(range(20, 30)), first):
        np.testing.assert_array_equal(again, once)
    with pytest.raises(ValueError, match='snapshot'):
        make_estimator(kind, config, scenario.model, runs=runs, measurement=measurement).restore(snapshot)
