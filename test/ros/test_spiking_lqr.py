"""The spiking LQR (snn_estimator.spiking.lqr): its decode against u = -K x, offline and over ROS."""

import numpy as np
import pytest

from snn_estimator.plant.control import lqr_control, lqr_gain
from snn_estimator.sim.scenarios import rendezvous_scenario
from snn_estimator.sim.simulate import simulate
from snn_estimator.spiking.lqr import SpikingLQR

SCENARIO = rendezvous_scenario(initial_state_dispersion=True)
GAIN = lqr_gain(SCENARIO.model, SCENARIO.lqr_state_weight, SCENARIO.lqr_input_weight)


def _trajectory():
    """x_hat - setpoint along an LQR rendezvous (the controller's input)."""
    return simulate(SCENARIO, 'ekf').estimate[0, :-1]


def test_the_networks_command_equals_minus_k_x_to_within_its_coding_error():
    network = SpikingLQR(GAIN, neurons=100)
    states = _trajectory()
    commands = np.array([network.control(x, SCENARIO.dt) for x in states])
    direct = lqr_control(GAIN, states)
    # the coding error of a greedy spike-coding network: |D_i^T e| <= ||D_i||^2 / 2 for every neuron,
    # so ||e|| stays of the order of one decoder column; u - (-K x) = K S e
    bound = np.linalg.norm(GAIN * network.scale[None, :], 2) * np.linalg.norm(network.decoder[0], axis=0).max()
    assert np.abs(commands - direct).max() <= bound
    relative = np.linalg.norm(commands - direct) / np.linalg.norm(direct)
    assert relative < 0.01, relative
    assert network.total_spikes[0] > 0


def test_the_readout_is_minus_k_s_d():
    network = SpikingLQR(GAIN, neurons=20, seeds=(3,))
    np.testing.assert_allclose(network.readout[0], -GAIN @ np.diag(network.scale) @ network.decoder[0])


def test_too_few_neurons_cannot_represent_the_state():
    states = _trajectory()[:300]
    direct = lqr_control(GAIN, states)
    one = SpikingLQR(GAIN, neurons=1)
    commands = np.array([one.control(x, SCENARIO.dt) for x in states])
    assert np.linalg.norm(commands - direct) / np.linalg.norm(direct) > 0.5


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match='snn_lqr_neurons must be a positive integer'):
        SpikingLQR(GAIN, neurons=0)
    with pytest.raises(ValueError, match='snn_lqr_leak must be'):
        SpikingLQR(GAIN, leak=-1.0)
    with pytest.raises(ValueError, match='must be finite'):
        SpikingLQR(GAIN).control(np.full(6, np.nan), 0.1)


@pytest.mark.parametrize('kind', ['ekf', 'snn_ekf'])
def test_snn_lqr_closes_the_loop_offline_beside_the_lqr(kind):
    lqr = simulate(SCENARIO, kind, runs=10)
    snn = simulate(SCENARIO, kind, runs=10, controller='snn_lqr')
    assert snn.final_range().max() < 0.1
    assert snn.delta_v().mean() == pytest.approx(lqr.delta_v().mean(), rel=0.01)
    assert snn.extra['controller_spikes'].min() > 0


@pytest.mark.slow
def test_snn_lqr_closes_the_loop_over_ros_and_equals_the_offline_run(tmp_path):
    pytest.importorskip('rclpy')
    from snn_tools.bags.data import read_bag, summarize
    from snn_tools.run.demo import run_pipeline

    run_pipeline(tmp_path, estimator='snn_ekf', timeout=300.0,
                 extra={'lqr_controller': {'controller_type': 'snn_lqr'}})
    data = read_bag(tmp_path / 'bag')
    summary = summarize(data)
    assert summary['steps'] == 3600 and summary['final_range_m'] < 0.1
    offline = simulate(SCENARIO, 'snn_ekf', controller='snn_lqr')
    np.testing.assert_allclose(data.truth, offline.truth[0], rtol=0, atol=1e-9)
