"""The chip's network (snn_estimator.spiking.chip): Loihi's integer formats and switched weight sets."""

import dataclasses
import math

import numpy as np
import pytest

from snn_estimator.filters.estimators import make_estimator
from snn_estimator.filters.gain_schedule import schedule_gains
from snn_estimator.sim.scenarios import rendezvous_scenario
from snn_estimator.sim.simulate import simulate
from snn_estimator.spiking import chip

SCENARIO = rendezvous_scenario()
SHORT = dataclasses.replace(SCENARIO, duration=60.0, metric_window=30.0)
STEADY = SCENARIO.estimator.replace(gain_schedule='steady_state')
#: The schedule the results use: 4 weight sets, switched at 1, 10 and 100 s.
SCHEDULE = dict(gain_schedule='switched', schedule_times=(1.0, 10.0, 100.0))


# ---------------------------------------------------------------- the float form
@pytest.mark.parametrize('kind', ['snn_ekf', 'snn_emsif', 'snn_emsif_weighted'])
def test_float_chip_network_with_one_set_is_the_float_kernels_network_spike_for_spike(kind):
    ours = simulate(SHORT, kind, runs=2, config=STEADY)
    theirs = simulate(SHORT, kind, runs=2, config=STEADY.replace(gain_schedule='switched', schedule_times=()))
    np.testing.assert_array_equal(theirs.spikes_per_step, ours.spikes_per_step)
    np.testing.assert_allclose(theirs.estimate, ours.estimate, rtol=0, atol=1e-9)


# ---------------------------------------------------------------- the integer formats
def test_quantize_gives_signed_mantissas_with_one_shared_exponent():
    rng = np.random.default_rng(1)
    weights = rng.normal(0.0, 3e-3, (40, 6))
    fmt = chip.ChipFormat(weight_bits=8)
    values, shift = chip.quantize(weights, 1e-6, fmt, fractional=True)
    mantissas = values / 2.0 ** shift
    np.testing.assert_array_equal(mantissas, np.rint(mantissas))
    assert np.abs(mantissas).max() <= 127 and np.abs(mantissas).max() >= 64  # the exponent is the smallest that fits
    np.testing.assert_array_less(np.abs(values * 1e-6 - weights), 0.5 * 2.0 ** shift * 1e-6 + 1e-18)


def test_decay_rounds_toward_zero_as_loihi():
    # Lava PyLifModelBitAcc: sign(x (4096 - d)) * (|x (4096 - d)| >> 12)
    for value, d in ((1000.0, 410.0), (-1000.0, 410.0), (7.0, 4095.0), (-3.0, 1.0)):
        expected = math.copysign(abs(int(value) * (4096 - int(d))) >> 12, value)
        assert chip._decayed(value, True, 4096.0, d, 0.0) == expected


def test_loihi_state_is_integer_and_the_readout_is_what_it_encodes():
    estimator = make_estimator('snn_ekf', STEADY.replace(precision='loihi'), SCENARIO.model)
    network = estimator.chip
    z = SCENARIO.model.measurement_matrix @ SCENARIO.x0
    for _ in range(20):
        estimator.step(z, np.zeros(3), SCENARIO.dt)
    for state in (network._e, network._x_read, network._read):
        np.testing.assert_array_equal(state, np.rint(state))
    assert np.abs(network._read).max() <= 127
    assert np.abs(network._x_read).max() < 2 ** 23 and network.overflows == 0
    described = network.describe()
    assert (described['weight_bits'], described['membrane_bits'], described['decay_bits']) == (8, 24, 12)
    # x_hat is S (D_q r): the integer readout in SI units
    np.testing.assert_allclose(estimator.x_hat, network._x_read[0] * network._read_scale, rtol=0, atol=0)


#: Position RMSE of the fixed-point network over the float one (steady-state gain, truth start,
#: 60 s, 4 runs) at most this, per weight width (24-bit state, 12-bit decays).
TOLERANCE = {8: 2.0, 12: 1.05, 16: 1.05}


@pytest.mark.parametrize('bits', sorted(TOLERANCE))
def test_fixed_point_position_accuracy_within_the_stated_tolerance_of_float(bits):
    float_run = simulate(SHORT, 'snn_emsif', runs=4, config=STEADY)
    fixed = simulate(SHORT, 'snn_emsif', runs=4, config=STEADY.replace(precision='loihi', weight_bits=bits))
    ratio = fixed.rmse()[:3] / float_run.rmse()[:3]
    assert np.all(ratio <= TOLERANCE[bits]), ratio


def test_too_few_weight_bits_degrade_the_estimate():
    float_run = simulate(SHORT, 'snn_emsif', runs=2, config=STEADY)
    coarse = simulate(SHORT, 'snn_emsif', runs=2, config=STEADY.replace(precision='loihi', weight_bits=4))
    assert np.linalg.norm(coarse.rmse()[:3]) > 1.5 * np.linalg.norm(float_run.rmse()[:3])


# ---------------------------------------------------------------- refusals
def test_a_time_varying_gain_cannot_run_on_the_chip():
    with pytest.raises(ValueError, match='precision loihi needs weights a chip can hold'):
        make_estimator('snn_ekf', SCENARIO.estimator.replace(precision='loihi'), SCENARIO.model)


@pytest.mark.parametrize('field, value, message', [
    ('weight_bits', 1, 'weight_bits must be >= 2'), ('membrane_bits', 60, 'membrane_bits must be'),
    ('precision', 'float16', 'precision must be one of float64, loihi')])
def test_bad_formats_are_refused_with_the_field_named(field, value, message):
    with pytest.raises(ValueError, match=message):
        make_estimator('snn_ekf', STEADY.replace(**{'precision': 'loihi', field: value}), SCENARIO.model)


def test_a_non_spiking_filter_has_no_chip_network():
    with pytest.raises(ValueError, match='ekf has no network'):
        make_estimator('ekf', STEADY.replace(precision='loihi'), SCENARIO.model)


def test_bad_switch_times_are_refused():
    with pytest.raises(ValueError, match=r'schedule_times \(s\) must be finite and increasing'):
        make_estimator('snn_ekf', SCENARIO.estimator.replace(gain_schedule='switched', schedule_times=(10.0, 1.0)),
                       SCENARIO.model)


def test_the_sif_gain_has_no_schedule():
    estimator = make_estimator('snn_emsif_star', SCENARIO.estimator.replace(**SCHEDULE), SCENARIO.model)
    with pytest.raises(ValueError, match='SIF gain of Eq. 7 follows the innovation'):
        estimator.step(np.zeros(3), np.zeros(3), 0.1)


# ---------------------------------------------------------------- the schedule
def test_schedule_gains_are_the_time_varying_gain_averaged_per_interval():
    settings = make_estimator('snn_ekf', SCENARIO.estimator, SCENARIO.model).settings
    config = SCENARIO.estimator.replace(**SCHEDULE)
    gains = schedule_gains('snn_ekf', SCENARIO.model, config, settings, 0.1,
                           lambda kind, twin_config: make_estimator(kind, twin_config, SCENARIO.model))
    # the twin EKF's own gain, stepped here without the module
    ekf = make_estimator('ekf', SCENARIO.estimator, SCENARIO.model)
    trajectory = []
    for _ in range(1001):
        ekf.step(SCENARIO.model.measurement_matrix @ ekf.x_hat, np.zeros(3), 0.1)
        trajectory.append(ekf.gain.copy())
    trajectory = np.array(trajectory)
    assert len(gains) == 4
    np.testing.assert_allclose(gains[0], trajectory[:10].mean(axis=0), rtol=1e-9)
    np.testing.assert_allclose(gains[2], trajectory[100:1000].mean(axis=0), rtol=1e-9)
    np.testing.assert_allclose(gains[3], trajectory[1000], rtol=1e-9)
    assert gains[0][0, 0] > gains[1][0, 0] > gains[2][0, 0] > gains[3][0, 0]


@pytest.mark.slow
@pytest.mark.parametrize('kind', ['snn_ekf', 'snn_emsif_weighted'])
def test_four_weight_sets_in_loihi_formats_converge_from_the_dispersion_in_every_run(kind):
    scenario = rendezvous_scenario(initial_state_dispersion=True)
    result = simulate(scenario, kind, runs=100, config=scenario.estimator.replace(precision='loihi', **SCHEDULE))
    assert result.final_range().max() < 0.1
    held = simulate(scenario, kind, runs=100, config=scenario.estimator.replace(gain_schedule='steady_state'))
    assert np.mean(held.final_range() >= 0.1) > 0.5 or kind != 'snn_ekf'  # one set does not (SNN-EKF)


# ---------------------------------------------------------------- NIR and the independent re-run
def _closed_loop(estimator, steps):
    from snn_estimator.plant.control import lqr_control, lqr_gain
    from snn_estimator.plant.sensors import PositionSensor
    from snn_estimator.plant.truth import Plant
    model = SCENARIO.model
    plant = Plant(model, SCENARIO.x0, SCENARIO.process_noise)
    sensor = PositionSensor(model, SCENARIO.measurement_noise)
    gain = lqr_gain(model, SCENARIO.lqr_state_weight, SCENARIO.lqr_input_weight)
    zs, us, truth, estimates, spikes = [], [], [plant.x[0].copy()], [estimator.x_hat.copy()], []
    for _ in range(steps):
        u = lqr_control(gain, estimator.x_hat)
        z = sensor.measure(plant.x)[0]
        estimates.append(estimator.step(z, u, SCENARIO.dt).copy())
        plant.step(u, SCENARIO.dt)
        zs.append(z)
        us.append(u)
        truth.append(plant.x[0].copy())
        spikes.append(estimator.spike_count)
    return np.array(zs), np.array(us), np.array(truth), np.array(estimates), np.array(spikes)


@pytest.mark.filterwarnings('ignore::DeprecationWarning')
def test_brian2_from_the_nir_file_matches_the_integer_network(tmp_path):
    nir = pytest.importorskip('nir')
    pytest.importorskip('brian2')
    from snn_tools.neuromorphic.brian2_sim import run_file
    from snn_tools.neuromorphic.nir_export import network_graph

    estimator = make_estimator('snn_ekf', STEADY.replace(precision='loihi'), SCENARIO.model)
    estimator.prepare(SCENARIO.dt)
    path = tmp_path / 'chip.nir'
    nir.write(path, network_graph(estimator, SCENARIO.dt))
    zs, us, truth, ours, spikes = _closed_loop(estimator, 60)
    theirs = run_file(path, zs, us, substeps=200)
    # the integer network rounds its drive to the readout LSB (0.17 mm, 1.7e-6 m/s); Brian2 does not
    np.testing.assert_allclose(theirs.estimate[:, :3], ours[:, :3], atol=5e-3)
    error = [np.linalg.norm(x[-30:, :3] - truth[-30:, :3]) for x in (theirs.estimate, ours)]
    ratio = error[0] / error[1]
    assert 1 / 1.1 <= ratio <= 1.1
    assert abs(theirs.spikes_per_step.sum() - spikes.sum()) <= 0.01 * spikes.sum()


def test_the_schedule_exports_one_nir_graph_per_weight_set(tmp_path):
    nir = pytest.importorskip('nir')
    from snn_tools.neuromorphic.nir_export import export_schedule, network_arrays

    estimator = make_estimator('snn_ekf', SCENARIO.estimator.replace(precision='loihi', **SCHEDULE), SCENARIO.model)
    paths = export_schedule(estimator, SCENARIO.dt, tmp_path)
    assert [p.name for p in paths] == [f'snn_ekf_set{j}.nir' for j in range(4)]
    graphs = [nir.read(p) for p in paths]
    assert [float(g.metadata['active_from_s']) for g in graphs] == [0.0, 1.0, 10.0, 100.0]
    network = estimator.chip
    for j, graph in enumerate(graphs):
        arrays = network_arrays(graph)
        # F_k = D^T S^-1 K with the set's quantized gain (Eq. 20), decoder the quantized one
        k_scaled = network._gain_weights[j] * network._read_lsb / SCENARIO.dt
        np.testing.assert_allclose(arrays.measurement, network.decoder[0].T @ k_scaled, rtol=1e-12, atol=1e-15)
        scale = np.asarray(SCENARIO.estimator.state_scale)
        np.testing.assert_allclose(arrays.decoder, scale[:, None] * network.decoder[0])
    assert not np.allclose(network_arrays(graphs[0]).measurement, network_arrays(graphs[3]).measurement)
