"""The Eq. 15 network in Loihi's formats under the synchronous rule (snn_estimator.spiking.chip_synchronous)."""

import dataclasses

import numpy as np
import pytest

from snn_estimator.filters.estimators import make_estimator
from snn_estimator.sim.scenarios import rendezvous_scenario
from snn_estimator.sim.simulate import simulate
from snn_estimator.spiking.chip_synchronous import SynchronousChipNetwork

SCENARIO = rendezvous_scenario()
DISPERSED = rendezvous_scenario(initial_state_dispersion=True)
SYNCHRONOUS = SCENARIO.estimator.replace(spike_rule='synchronous')
#: The schedule of the chip tables: 4 weight sets, switched at 1, 10 and 100 s.
SCHEDULE = dict(gain_schedule='switched', schedule_times=(1.0, 10.0, 100.0))
#: Issue 40: the fixed-point network with the local rule within this of float at 8-bit weights.
GOAL_RATIO = 1.1


def _position_rmse(result) -> float:
    return float(np.linalg.norm(result.rmse()[:3]))


# ---------------------------------------------------------------- the float form
def test_float_synchronous_chip_network_with_one_set_is_the_float_kernels_network():
    short = dataclasses.replace(SCENARIO, duration=30.0, metric_window=15.0)
    steady = SYNCHRONOUS.replace(gain_schedule='steady_state')
    kernel = simulate(short, 'snn_ekf', runs=2, config=steady)
    ours = simulate(short, 'snn_ekf', runs=2, config=steady.replace(gain_schedule='switched', schedule_times=()))
    # the same algebra in another order: equal spikes until a rounding tips a threshold, then close
    steps = kernel.spikes_per_step.shape[-1]
    same = np.array_equal(kernel.spikes_per_step[..., :steps // 3], ours.spikes_per_step[..., :steps // 3])
    assert same
    np.testing.assert_allclose(ours.estimate, kernel.estimate, rtol=0, atol=5e-3)


# ---------------------------------------------------------------- the integer formats
def _loihi_estimator(**changes):
    config = DISPERSED.estimator.replace(spike_rule='synchronous', precision='loihi', **SCHEDULE).replace(**changes)
    return make_estimator('snn_ekf', config, DISPERSED.model)


def test_omega_f_is_the_gram_of_the_quantized_decoder_held_exactly_in_8_bit_mantissas():
    estimator = _loihi_estimator()
    network = estimator.chip
    estimator.prepare(DISPERSED.dt)
    assert isinstance(network, SynchronousChipNetwork)
    integer_decoder = network.decoder[0] / network.describe()['readout_lsb_scaled']
    np.testing.assert_allclose(integer_decoder, np.rint(integer_decoder), rtol=0, atol=1e-9)
    unit = 2.0 ** network.fraction_bits
    mantissas = network.fast_weights[0] / unit
    np.testing.assert_array_equal(mantissas, np.rint(mantissas))
    assert np.abs(mantissas).max() <= 127
    np.testing.assert_array_equal(mantissas, -np.rint(integer_decoder).T @ np.rint(integer_decoder))
    # integer thresholds (1 + w) ||D_i||^2 / 2 in the membrane's unit
    widening = estimator.settings.threshold_widening
    np.testing.assert_array_equal(network.thresholds[0], np.floor((1.0 + widening) * 0.5 * -np.diag(mantissas) * unit))


def test_membranes_stay_integers_in_range():
    estimator = _loihi_estimator()
    z = DISPERSED.model.measurement_matrix @ DISPERSED.x0
    for _ in range(30):
        estimator.step(z, np.zeros(3), DISPERSED.dt)
    membranes = estimator.chip.membranes
    np.testing.assert_array_equal(membranes, np.rint(membranes))
    assert estimator.chip.overflows == 0


def test_every_eligible_neuron_above_its_threshold_fires_in_the_tick_and_no_other():
    # one tick per sample, every neuron in every slot: the spikes of a sample are those of one tick
    estimator = _loihi_estimator(ticks_per_sample=1, firing_slots=1, refractory_ticks=0)
    network = estimator.chip
    alive = estimator.network.alive[0]
    rng = np.random.default_rng(3)
    several = 0
    for _ in range(40):
        z = DISPERSED.model.measurement_matrix @ DISPERSED.x0 + rng.normal(0.0, 0.5, 3)
        estimator.step(z, np.zeros(3), DISPERSED.dt)
        spikes = estimator.network.spikes[0].copy()
        # the membranes before the tick's spikes acted (no decay at 12 bits: lambda dt 2^12 < 0.5)
        before = network.membranes[0] - network.fast_weights[0] @ spikes
        np.testing.assert_array_equal(spikes.astype(bool), alive & (before > network.thresholds[0]))
        several += spikes.sum() > 1
    assert several > 0  # several neurons fired together: no one-at-a-time choice


def test_under_the_default_rule_neurons_fire_together_within_a_tick():
    estimator = _loihi_estimator()
    z = DISPERSED.model.measurement_matrix @ DISPERSED.x0
    for _ in range(20):
        estimator.step(z, np.zeros(3), DISPERSED.dt)
    assert estimator.chip.ticks_with_several_spikes > 0


# ---------------------------------------------------------------- the chip's own velocity unit
def test_the_integer_chip_holds_velocity_in_a_unit_that_makes_the_kinematic_coupling_a_power_of_two():
    estimator = _loihi_estimator()
    encoded = estimator.x_hat.copy()
    estimator.prepare(DISPERSED.dt)
    network = estimator.chip
    scale = np.asarray(DISPERSED.estimator.state_scale)
    np.testing.assert_array_equal(network.unit[:3], scale[:3])
    assert np.all(np.abs(np.log2(network.unit[3:] / scale[3:])) < 0.5)  # moved by less than 2^0.5
    # the coupling A[p, v] = dt a_d[p, v] s_v / s_p in 8 bits is the exact 2^-10 (0.7 % off at the package's
    # velocity scale, docs/decisions.md 65-66)
    a_d, _ = DISPERSED.model.linearized_increment(None, DISPERSED.dt, estimator.settings.discretization)
    exact = DISPERSED.dt * np.diag(a_d[:3, 3:]) * network.unit[3:] / network.unit[:3]
    np.testing.assert_allclose(exact, 2.0 ** -10, rtol=1e-12)
    np.testing.assert_array_equal(np.diag(network.dynamics[:3, 3:]), 2.0 ** -10)
    # the readout is in m and m/s: the start re-encoded in the chip's unit decodes to the same state
    np.testing.assert_allclose(estimator.x_hat, encoded, rtol=0, atol=2e-3)


def test_the_float_network_keeps_the_package_scale():
    config = DISPERSED.estimator.replace(spike_rule='synchronous', **SCHEDULE)
    estimator = make_estimator('snn_ekf', config, DISPERSED.model)
    estimator.prepare(DISPERSED.dt)
    np.testing.assert_array_equal(estimator.chip.unit, DISPERSED.estimator.state_scale)


# ---------------------------------------------------------------- accuracy against float
@pytest.mark.parametrize('kind', ['snn_ekf', 'snn_emsif_weighted'])
def test_fixed_point_synchronous_network_tracks_within_the_goal_of_float_at_8_bit_weights(kind):
    # the approach (60-120 s), where the SNN-EKF's small late gain leaves a model error uncorrected, at the
    # package's state scale: the chip's own velocity unit makes A's coupling exact (2.8x float without it)
    short = dataclasses.replace(DISPERSED, duration=120.0, metric_window=60.0)
    config = short.estimator.replace(spike_rule='synchronous', **SCHEDULE)
    float_run = simulate(short, kind, runs=4, config=config, trajectories=False)
    fixed = simulate(short, kind, runs=4, config=config.replace(precision='loihi', weight_bits=8), trajectories=False)
    assert not fixed.diverged.any()
    assert _position_rmse(fixed) <= GOAL_RATIO * _position_rmse(float_run)


def test_a_restored_snapshot_replays_the_same_spikes_and_estimates():
    estimator = _loihi_estimator()
    z = DISPERSED.model.measurement_matrix @ DISPERSED.x0
    for _ in range(5):
        estimator.step(z, np.zeros(3), DISPERSED.dt)
    saved = estimator.snapshot()
    first = [(estimator.step(z, np.full(3, 1e-4), DISPERSED.dt).copy(), estimator.network.spikes.copy())
             for _ in range(5)]
    estimator.restore(saved)
    again = [(estimator.step(z, np.full(3, 1e-4), DISPERSED.dt).copy(), estimator.network.spikes.copy())
             for _ in range(5)]
    for (x, spikes), (y, replayed) in zip(first, again):
        np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(spikes, replayed)
