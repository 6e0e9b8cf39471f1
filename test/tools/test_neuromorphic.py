"""The NIR export, the Brian2 simulation built from it, and the operation counts."""

import subprocess
import sys

import numpy as np
import pytest

from snn_estimator.filters.estimators import make_estimator
from snn_estimator.models import VanDerPol
from snn_estimator.plant.control import lqr_control, lqr_gain
from snn_estimator.plant.sensors import PositionSensor
from snn_estimator.plant.truth import Plant
from snn_estimator.sim.scenarios import rendezvous_scenario
from snn_estimator.spiking.costs import CHIPS, Chip, CostModel, StepCosts, energy_pj, filter_macs

nir = pytest.importorskip('nir')
# brian2 2.9.0 parses with pyparsing names that pyparsing 3.3 deprecates
pytestmark = [pytest.mark.filterwarnings('ignore::DeprecationWarning:brian2'),
              pytest.mark.filterwarnings('ignore::DeprecationWarning:pyparsing')]

from snn_tools.neuromorphic.local_rule import loihi_energy_nj  # noqa: E402
from snn_tools.neuromorphic.nir_export import (  # noqa: E402
    SPIKING_KINDS,
    constant_gain_estimator,
    export,
    export_setup,
    main,
    network_arrays,
    network_graph,
    read_parameters,
)

SCENARIO = rendezvous_scenario()


def closed_loop(estimator, steps):
    """z_k, u_k and per-neuron spikes of the first ``steps`` of a rendezvous that ``estimator``
    drives (u = -K x_hat); the estimates x_hat_0..x_hat_steps."""
    model = SCENARIO.model
    plant = Plant(model, SCENARIO.x0, SCENARIO.process_noise)
    sensor = PositionSensor(model, SCENARIO.measurement_noise)
    gain = lqr_gain(model, SCENARIO.lqr_state_weight, SCENARIO.lqr_input_weight)
    zs, us, raster, estimates = [], [], [], [estimator.x_hat.copy()]
    for _ in range(steps):
        u = lqr_control(gain, estimator.x_hat)
        z = sensor.measure(plant.x)[0]
        estimates.append(estimator.step(z, u, SCENARIO.dt).copy())
        plant.step(u, SCENARIO.dt)
        zs.append(z)
        us.append(u)
        raster.append(estimator.spikes.copy())
    return np.array(zs), np.array(us), np.array(raster), np.array(estimates)


@pytest.fixture(scope='module')
def emsif_file(tmp_path_factory):
    path = tmp_path_factory.mktemp('nir') / 'snn_emsif.nir'
    graph = export('snn_emsif', SCENARIO.estimator, SCENARIO.model, SCENARIO.dt, path)
    return path, graph


# ---------------------------------------------------------------- the NIR file
def test_nir_file_reads_back_the_same_graph(emsif_file):
    path, written = emsif_file
    read = nir.read(path)
    assert set(read.nodes) == set(written.nodes)
    assert sorted(map(tuple, read.edges)) == sorted(written.edges)
    for name, node in written.nodes.items():
        for field in ('weight', 'tau', 'r', 'v_leak', 'v_threshold', 'v_reset'):
            if hasattr(node, field):
                np.testing.assert_array_equal(getattr(read.nodes[name], field), getattr(node, field))
    np.testing.assert_array_equal(read.nodes['neurons'].metadata['initial_v'],
                                  written.nodes['neurons'].metadata['initial_v'])
    assert read.metadata['filter_kind'] == 'snn_emsif'
    assert read.metadata['gain_schedule'] == 'steady_state'
    assert float(read.metadata['sample_period']) == SCENARIO.dt


def test_a_synchronous_network_is_exported_with_its_tick_widened_thresholds_and_reset(tmp_path):
    config = SCENARIO.estimator.replace(spike_rule='synchronous', ticks_per_sample=50, threshold_widening=1.5,
                                        firing_slots=5, refractory_ticks=2)
    estimator = constant_gain_estimator('snn_ekf', config, SCENARIO.model)
    path = tmp_path / 'synchronous.nir'
    nir.write(path, network_graph(estimator, SCENARIO.dt))
    graph = nir.read(path)
    norms = np.sum(estimator.decoder ** 2, axis=0)               # ||D_i||^2
    lif = graph.nodes['neurons']
    np.testing.assert_allclose(lif.v_threshold, 2.5 * norms / 2, rtol=1e-15)
    np.testing.assert_allclose(lif.v_threshold - lif.v_reset, norms, rtol=1e-12)
    meta = graph.metadata
    assert meta['spike_rule'] == 'synchronous' and 'no neuron is compared' in meta['spike_rule_meaning']
    assert int(meta['ticks_per_sample']) == 50 and float(meta['tick_s']) == pytest.approx(SCENARIO.dt / 50)
    assert int(meta['firing_slots']) == 5 and int(meta['refractory_ticks']) == 2
    assert float(meta['threshold_widening']) == 1.5
    greedy = network_graph(constant_gain_estimator('snn_ekf', SCENARIO.estimator, SCENARIO.model), SCENARIO.dt)
    assert 'ticks_per_sample' not in greedy.metadata
    np.testing.assert_allclose(greedy.nodes['neurons'].v_reset, -norms / 2, rtol=1e-15)


def papers_weights(estimator, dt):
    """Eq. 16-20 in the network's scaled units, written from the decoder, the model and the
    steady-state gain of reference.py (not from Estimator.weights or steady_state_gain)."""
    from snn_estimator.filters.reference import drift_matrices, written_out_steady_state_gain
    d, scale = estimator.decoder, estimator.settings.state_scale
    model = estimator.model
    a_d, b_d = drift_matrices(model, None, dt, estimator.settings.discretization)
    k = written_out_steady_state_gain(estimator, dt) / scale[:, None]   # S^-1 K
    a_scaled = a_d / scale[:, None] * scale[None, :]                     # S^-1 A_d S
    c_scaled = model.measurement_matrix * scale[None, :]                 # C S
    return {'F': d.T @ (b_d / scale[:, None]),                               # Eq. 16
            'Omega_s': d.T @ (a_scaled + estimator.settings.leak_rate * np.eye(len(scale))) @ d,  # Eq. 17
            'Omega_f': -d.T @ d,                                             # Eq. 18
            'Omega_k': -d.T @ k @ c_scaled @ d,                              # Eq. 19/21/23
            'F_k': d.T @ k,                                                  # Eq. 20/22/24
            'thresholds': 0.5 * np.sum(d * d, axis=0), 'decoder': d}


@pytest.mark.parametrize('kind', SPIKING_KINDS)
def test_exported_weights_equal_the_papers_formulas(kind):
    estimator = constant_gain_estimator(kind, SCENARIO.estimator, SCENARIO.model)
    weights = papers_weights(estimator, SCENARIO.dt)
    graph = network_graph(estimator, SCENARIO.dt)
    net = network_arrays(graph)
    scale = estimator.settings.state_scale
    np.testing.assert_allclose(net.measurement, weights['F_k'], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(net.control, weights['F'], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(net.omega_f, weights['Omega_f'], rtol=1e-12)
    np.testing.assert_allclose(graph.nodes['slow_dynamics'].weight, weights['Omega_s'], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(graph.nodes['slow_correction'].weight, weights['Omega_k'], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(net.slow, weights['Omega_s'] + weights['Omega_k'], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(net.decoder, scale[:, None] * weights['decoder'], rtol=1e-12)
    np.testing.assert_allclose(net.threshold, weights['thresholds'], rtol=1e-12)
    np.testing.assert_allclose(net.tau_v, 1.0 / estimator.settings.leak_rate)
    np.testing.assert_allclose(net.train_jump, 1.0)
    np.testing.assert_allclose(net.decoder @ net.initial_r, estimator.x_hat, atol=1e-9)


def test_parameter_file_sets_filter_size_and_seed_without_rclpy(tmp_path):
    params = tmp_path / 'params.yaml'
    params.write_text("/**:\n  ros__parameters:\n    time_step: 0.1\n"
                      "/**/estimator:\n  ros__parameters:\n    filter_type: snn_emsif_star\n"
                      "    neuron_count: 50\n    seed: 3\n")
    kind, config, _, dt = export_setup(None, params)
    assert (kind, config.neuron_count, config.seed, dt) == ('snn_emsif_star', 50, 3, 0.1)
    out = tmp_path / 'net.nir'
    assert main(['--params-file', str(params), '--out', str(out)]) == 0
    graph = nir.read(out)
    assert graph.nodes['neurons'].v_threshold.size == 50 and int(graph.metadata['seed']) == 3
    probe = ('import sys; from snn_tools.neuromorphic.nir_export import export_setup; '
             'export_setup(None, "config/rendezvous.yaml"); print("rclpy" in sys.modules)')
    result = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == 'False'


# ---------------------------------------------------------------- refusals
def test_a_non_spiking_filter_is_refused():
    with pytest.raises(ValueError, match='no spiking network to export; choose one of snn_ekf'):
        constant_gain_estimator('ekf', SCENARIO.estimator, SCENARIO.model)


def test_a_nonlinear_model_is_refused():
    with pytest.raises(ValueError, match='VanDerPol is nonlinear'):
        constant_gain_estimator('snn_emsif', SCENARIO.estimator, VanDerPol())


def test_a_parameter_file_naming_a_non_spiking_filter_fails_with_a_message(tmp_path, capsys):
    params = tmp_path / 'params.yaml'
    params.write_text('/**/estimator:\n  ros__parameters:\n    filter_type: ekf\n')
    assert main(['--params-file', str(params), '--out', str(tmp_path / 'x.nir')]) == 2
    assert "filter 'ekf' has no spiking network" in capsys.readouterr().err


def test_an_unknown_estimator_parameter_is_refused(tmp_path):
    params = tmp_path / 'params.yaml'
    params.write_text('/**/estimator:\n  ros__parameters:\n    neuron_cont: 50\n')
    with pytest.raises(ValueError, match=r"unknown estimator parameters \['neuron_cont'\]"):
        read_parameters(params)


def test_costs_of_a_non_spiking_filter_are_refused():
    with pytest.raises(ValueError, match='ekf is not a spiking filter'):
        CostModel.of(make_estimator('ekf', SCENARIO.estimator, SCENARIO.model))


# ---------------------------------------------------------------- the independent simulator
def test_brian2_built_from_the_file_reproduces_our_network_spike_for_spike(emsif_file):
    pytest.importorskip('brian2')
    from snn_tools.neuromorphic.brian2_sim import run_file

    path, _ = emsif_file
    ours = constant_gain_estimator('snn_emsif', SCENARIO.estimator, SCENARIO.model)
    zs, us, raster, estimates = closed_loop(ours, steps=15)
    run = run_file(path, zs, us, mode='sampled', rule='greedy', substeps=150)
    assert run.saturated_steps == 0
    np.testing.assert_array_equal(run.raster, raster)
    np.testing.assert_allclose(run.estimate, estimates, rtol=0, atol=1e-9)  # m and m/s


# ---------------------------------------------------------------- operation counts
def test_synaptic_operations_equal_a_count_spike_by_spike():
    estimator = constant_gain_estimator('snn_ekf', SCENARIO.estimator, SCENARIO.model)
    net = network_arrays(network_graph(estimator, SCENARIO.dt))
    _, _, raster, _ = closed_loop(estimator, steps=40)
    counted_synops, counted_dense = [], []
    for spikes in raster:
        synops = np.count_nonzero(net.measurement) + np.count_nonzero(net.control)
        dense = net.slow.size + net.measurement.size + net.control.size + 2 * net.threshold.size + net.decoder.size
        for neuron in np.flatnonzero(spikes):
            fan_out = (np.count_nonzero(net.fast[:, neuron]) + np.count_nonzero(net.slow[:, neuron])
                       + np.count_nonzero(net.decoder[:, neuron]))
            synops += spikes[neuron] * fan_out
            dense += spikes[neuron] * net.omega_f[:, neuron].size
        counted_synops.append(synops)
        counted_dense.append(dense)
    costs = CostModel.of(estimator).step(raster.sum(axis=1))
    assert raster.sum() > 100
    np.testing.assert_array_equal(costs.synops, counted_synops)
    np.testing.assert_array_equal(costs.dense_macs, counted_dense)
    np.testing.assert_array_equal(costs.neuron_updates, 2 * 200 + 6)


class MacCounter:
    """Counts the multiply-adds of matrix products as a written-out step performs them."""

    def __init__(self):
        self.total = 0

    def mm(self, a, b, symmetric=False):
        a, b = np.atleast_2d(a), np.atleast_2d(b)
        rows, inner, cols = a.shape[0], a.shape[1], b.shape[1]
        # a symmetric result (C P C^T, M P M^T, G R G^T) needs only its upper triangle
        self.total += (rows * (rows + 1) // 2 if symmetric else rows * cols) * inner
        return a @ b

    def cholesky(self, matrix):
        """L with L L^T = matrix, by the textbook loops: (k^3 - k)/6 multiply-adds."""
        k = matrix.shape[0]
        self.total += (k ** 3 - k) // 6
        return np.linalg.cholesky(matrix)

    def solve_rows(self, rows, factor):
        """rows (L L^T)^-1 by forward and back substitution: k (k - 1) multiply-adds per row."""
        k = factor.shape[0]
        self.total += rows.shape[0] * k * (k - 1)
        return rows @ np.linalg.inv(factor @ factor.T)


def counted_ekf_step(n, m, nu, law):
    """One EKF / SIF step (Eq. 3-7, the covariance by the sampled step of Decision 43) written out
    with numpy, every product counted."""
    rng = np.random.default_rng(n * 100 + m * 10 + nu)
    count = MacCounter()
    c, x, z, u = rng.normal(size=(m, n)), rng.normal(size=(n, 1)), rng.normal(size=(m, 1)), rng.normal(size=(nu, 1))
    a, b, p = rng.normal(size=(n, n)), rng.normal(size=(n, nu)), np.eye(n)
    r_sample, c_pinv, dt = np.eye(m), np.linalg.pinv(c), 0.1
    innovation = z - count.mm(c, x)                                           # Eq. 4
    if law == 'kalman':                                                       # Eq. 5, sampled
        pct = count.mm(p, c.T)
        factor = count.cholesky(count.mm(c, pct, symmetric=True) + r_sample)
        gain = count.mm(np.eye(n) / dt + a, count.solve_rows(pct, factor))
    else:
        gain = c_pinv * np.minimum(np.abs(innovation.T), 1.0)                 # Eq. 7: a scaling
        count.total += n * m
    increment = count.mm(a, x) + count.mm(b, u) + count.mm(gain, innovation)  # Eq. 3
    count.total += n                                                          # x += dt increment
    if law == 'kalman':                                                       # Eq. 6, sampled
        closed = np.eye(n) + dt * a - count.mm(dt * gain, c)
        count.total += n * n                                                  # dt A
        count.mm(count.mm(closed, p), closed.T, symmetric=True)
        count.mm(count.mm(dt * gain, r_sample), dt * gain.T, symmetric=True)
        count.cholesky(p)                                                     # the guard
    del increment
    return count.total


@pytest.mark.parametrize('n, m, nu', [(1, 1, 1), (2, 1, 1), (6, 3, 3), (9, 4, 2)])
def test_filter_macs_equal_a_count_of_the_written_out_step(n, m, nu):
    assert sum(filter_macs(n, m, nu, 'kalman', 'riccati').values()) == counted_ekf_step(n, m, nu, 'kalman')
    assert sum(filter_macs(n, m, nu, 'sif', 'none').values()) == counted_ekf_step(n, m, nu, 'sif')


def test_energy_is_operations_times_the_chips_figures():
    costs = StepCosts(spikes=10, synops=1000, neuron_updates=406, host_macs=0, dense_macs=0, nonspiking_macs=0)
    chip = Chip('test', 2.0, 3.0, 5.0, 'none', 'none')
    assert energy_pj(costs, chip) == 1000 * 2.0 + 406 * 3.0 + 10 * 5.0
    assert energy_pj(costs, 'truenorth') == 1000 * CHIPS['truenorth'].synop_pj
    with pytest.raises(ValueError, match="chip 'loihi3' is unknown"):
        energy_pj(costs, 'loihi3')


def test_a_time_varying_gain_adds_the_weight_refresh_on_the_host():
    constant = CostModel(200, 6, 3, 3, 'kalman', 'riccati', constant_gain=True).step(10)
    varying = CostModel(200, 6, 3, 3, 'kalman', 'riccati', constant_gain=False).step(10)
    refresh = 200 * 6 * 3 + 200 * 200 * 3
    assert constant.host_macs == 0
    assert varying.host_macs == 292 + 638 + refresh  # gain and covariance of the EKF, then F_k and Omega_k
    assert varying.dense_macs - constant.dense_macs == varying.host_macs
    assert varying.synops == constant.synops


@pytest.mark.slow
def test_the_local_rule_table_rates_each_rule_against_the_twin_and_greedy_of_the_same_runs():
    from snn_tools.neuromorphic.local_rule import SETTINGS, markdown, measure
    data = measure({'position': 2}, kinds=('snn_ekf',), settings=SETTINGS[:1], report=lambda line: None)
    twin, greedy, local = data['rows']
    assert (twin['rule'], twin['kind'], greedy['rule'], local['rule']) == ('twin', 'ekf', 'greedy', 'synchronous')
    assert twin['rmse_ratio'] == 1.0 and greedy['spike_ratio'] == 1.0
    assert local['rmse_ratio'] == pytest.approx(local['rmse_position_m'] / twin['rmse_position_m'])
    assert local['spike_ratio'] == pytest.approx(local['spikes_per_step'] / greedy['spikes_per_step'])
    assert local['ticks_per_sample'] == 100 and local['lost'] == 0
    table = [line for line in markdown(data) if line.startswith('| position')]
    assert len(table) == 3 and f"{local['rmse_position_m']:.4g}" in table[2]


def test_the_local_rule_table_prices_a_chip_by_its_ticks():
    """Loihi energy per estimate (Davies et al. 2018): neuron updates x 52 pJ, synaptic events
    x 23.6 pJ, 30.7 pJ more per spike; worked by hand for N = 200, n = 6, m = nu = 3."""
    greedy = {'rule': 'greedy', 'spikes_per_step': 10.0}
    # updates: (10 + 1) x 200 = 2200; events: 10 x (2 x 200 - 1 + 6) + 200 x 6 = 5250
    assert loihi_energy_nj(greedy, 200) == f'{(2200 * 52.0 + 5250 * 23.6 + 10 * 30.7) / 1e3:.0f}' == '239'
    synchronous = {'rule': 'synchronous', 'spikes_per_step': 10.0, 'ticks_per_sample': 100}
    # the same spikes, 100 ticks of all 200 neurons: the idle updates dominate
    assert loihi_energy_nj(synchronous, 200) == f'{(20000 * 52.0 + 5250 * 23.6 + 10 * 30.7) / 1e3:.0f}' == '1164'
    assert loihi_energy_nj({'rule': 'twin'}, 200) == ''


def test_the_exact_coupling_scale_makes_dt_sv_over_sp_a_power_of_two_near_the_packages():
    from snn_tools.neuromorphic.chip import exact_coupling_scale
    scenario = rendezvous_scenario(initial_state_dispersion=True)
    scale = np.array(exact_coupling_scale(scenario))
    coupling = np.log2(scenario.dt * scale[3:] / scale[:3])
    np.testing.assert_allclose(coupling, np.rint(coupling), rtol=0, atol=1e-12)
    ratio = scale / np.asarray(scenario.estimator.state_scale)
    assert np.all(ratio[:3] == 1.0) and np.all((ratio[3:] > 2 ** -0.5) & (ratio[3:] < 2 ** 0.5))


def test_the_fixed_point_synchronous_section_names_the_rows_that_miss_the_goal():
    from snn_tools.neuromorphic.chip import synchronous_markdown
    row = {'filter': 'snn_ekf', 'window': 'w', 'state_scale': 's', 'rmse_position_m': 0.011,
           'rmse_position_float_m': 0.01, 'rmse_ratio_position': 1.1, 'spikes_per_step': 30.0,
           'spikes_per_step_float': 30.0, 'diverged': 0, 'diverged_float': 0}
    data = {'runs': 20, 'weight_bits': 8, 'goal_ratio': 1.1,
            'rule': {'ticks_per_sample': 100, 'firing_slots': 10, 'threshold_widening': 2.0, 'refractory_ticks': 0},
            'rows': [row, dict(row, state_scale='t', rmse_ratio_position=2.94)]}
    lines = synchronous_markdown(data)
    assert sum(line.startswith('| snn_ekf') for line in lines) == 2
    assert lines[-1].startswith('Goal of issue 40') and 'met in 1 of 2 rows' in lines[-1] and 't (2.94x)' in lines[-1]
