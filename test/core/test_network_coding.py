"""network_coding: the deviation coding against the network written out from its equations
(snn_estimator.filters.reference), its decoding, and its spike budget (the paper's coding, the
default, is held to its golden runs in test_golden.py)."""

from dataclasses import replace

import numpy as np
import pytest

from snn_estimator import FILTER_KINDS, TWIN_OF, make_estimator, rendezvous_scenario, simulate
from snn_estimator.filters.reference import DenseSpikingFilter
from snn_tools.experiments import spike_budget

SPIKING = [kind for kind, spec in FILTER_KINDS.items() if spec.spiking]


def dispersed_inputs(steps=300, seed=0):
    """Measurements and controls of a closed loop flown by the EKF from a dispersed start."""
    scenario = rendezvous_scenario(initial_state_dispersion=True)
    result = simulate(replace(scenario, duration=steps * scenario.dt), 'ekf', runs=1, seed=seed)
    truth = result.truth[0, :-1]
    rng = np.random.default_rng([seed, 99])
    zs = truth[:, :3] + 0.1 * rng.standard_normal((steps, 3))
    return scenario, zs, result.control[0]


@pytest.mark.parametrize('kind', SPIKING)
@pytest.mark.parametrize('rule', ['greedy', 'one_per_step'])
def test_deviation_coding_equals_the_network_written_out_from_its_equations(kind, rule):
    """Spike for spike and to 1e-9 in the estimate against reference.DenseSpikingFilter, which
    forms the dense weights with F = 0, Omega_s = lambda D^T D, F_k on z - C x_pred and advances
    x_pred = x_pred + dt (A_d x_hat + B_d u) in numpy (Van der Pol, both drives: test_estimators.py)."""
    scenario, zs, us = dispersed_inputs(steps=200)
    fast = make_estimator(kind, scenario.estimator.replace(network_coding='deviation', neuron_count=60,
                                                           spike_rule=rule))
    dense = DenseSpikingFilter(fast)
    for z, u in zip(zs, us):
        fast.step(z, u, scenario.dt)
        dense.step(z, u, scenario.dt)
        np.testing.assert_array_equal(fast.spikes, dense.spikes)
        np.testing.assert_allclose(fast.x_hat, dense.x_hat, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(fast.prediction, dense.x_pred, rtol=1e-9, atol=1e-12)
    assert fast.total_spikes > 0


def test_the_deviation_coding_decodes_prediction_plus_s_d_r_and_starts_at_a_zero_deviation():
    scenario, zs, us = dispersed_inputs(steps=100)
    estimator = make_estimator('snn_ekf', scenario.estimator.replace(network_coding='deviation'), runs=3)
    x0 = estimator.initial_states()
    np.testing.assert_array_equal(estimator.prediction, x0)
    np.testing.assert_array_equal(estimator.rates, 0.0)
    np.testing.assert_array_equal(estimator.x_hat, x0)
    scale = np.asarray(scenario.estimator.state_scale)
    for z, u in zip(zs, us):
        estimator.step(np.broadcast_to(z, (3, 3)), np.broadcast_to(u, (3, 3)), scenario.dt)
        decoded = estimator.prediction + scale * np.einsum('bkn,bn->bk', estimator.decoder, estimator.rates)
        np.testing.assert_allclose(estimator.x_hat, decoded, rtol=1e-12, atol=1e-12)
    # the greedy rule leaves the coding error of the deviation below threshold
    assert np.all(estimator.potentials <= estimator.thresholds + 1e-12)
    # set_state restarts the prediction at the new estimate, with a zero deviation
    target = np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    estimator.set_state(target)
    np.testing.assert_array_equal(estimator.x_hat, np.broadcast_to(target, (3, 6)))
    np.testing.assert_array_equal(estimator.rates, 0.0)


def test_the_deviation_coding_weights_leave_the_prediction_off_the_network():
    scenario, zs, us = dispersed_inputs(steps=5)
    estimator = make_estimator('snn_ekf', scenario.estimator.replace(network_coding='deviation'))
    for z, u in zip(zs, us):
        estimator.step(z, u, scenario.dt)
    w, d = estimator.weights(dt=scenario.dt), estimator.decoder
    paper = make_estimator('snn_ekf', scenario.estimator).weights(dt=scenario.dt)
    np.testing.assert_array_equal(w['F'], 0.0)                                          # Eq. 16: u enters x_pred
    np.testing.assert_allclose(w['Omega_s'], scenario.estimator.leak_rate * d.T @ d, rtol=1e-12)  # Eq. 17 without A
    np.testing.assert_allclose(w['Omega_f'], paper['Omega_f'], rtol=1e-12)               # Eq. 18 unchanged


def test_the_deviation_coding_is_refused_on_the_chip_network():
    config = rendezvous_scenario().estimator.replace(network_coding='deviation', gain_schedule='switched')
    with pytest.raises(ValueError, match='network_coding deviation'):
        make_estimator('snn_ekf', config)
    with pytest.raises(ValueError, match='network_coding'):
        make_estimator('snn_ekf', config.replace(network_coding='residual'))


def test_silenced_neurons_keep_the_deviation_decoded_on_the_prediction():
    scenario, zs, us = dispersed_inputs(steps=60)
    estimator = make_estimator('snn_ekf', scenario.estimator.replace(network_coding='deviation'))
    for z, u in zip(zs, us):
        estimator.step(z, u, scenario.dt)
    before = estimator.x_hat.copy()
    estimator.silence(range(0, estimator.neuron_count, 2))
    scale = np.asarray(scenario.estimator.state_scale)
    np.testing.assert_allclose(estimator.x_hat, estimator.prediction + scale * (estimator.decoder @ estimator.rates),
                               rtol=1e-12, atol=1e-12)
    # the survivors re-encode the deviation within their coding error (a few units of S)
    assert np.all(np.abs(estimator.x_hat - before) < 5.0 * scale)


def test_the_deviation_coding_spends_at_most_5_percent_of_the_spikes_within_1_1x_of_the_twin():
    """A modest closed-loop check of the budget (issue 25, item 5): 4 dispersed runs of the full
    rendezvous, snn_ekf with network_coding deviation at a quarter of the default units (what
    results/spike_budget.md measures), against the EKF with the same seeds."""
    figures = spike_budget.measure(runs=4, kinds=['snn_ekf'], cases=(('deviation', 0.25),))
    row, = figures['rows']
    assert row['twin'] == TWIN_OF['snn_ekf']
    assert row['spike_fraction'] <= 0.05
    assert row['ratio_window'] <= 1.1
    assert row['ratio_run'] <= 1.1
