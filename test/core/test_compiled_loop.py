"""The compiled closed loop (snn_estimator.sim.compiled_loop) against simulate's Python loop,
which stays the reference: the same numbers for every filter kind, truth and option."""

import dataclasses

import numpy as np
import pytest

from snn_estimator import rendezvous_scenario, simulate
from snn_estimator.filters.estimators import FILTER_KINDS
from snn_estimator.plant.truth import GaussianStream
from snn_estimator.sim.scenarios import angles_only_scenario, far_range_scenario, van_der_pol_scenario

#: 60 s: the compiled loop's chunks (512 steps) end inside the run
SHORT = 60.0
TRAJECTORIES = ('truth', 'estimate', 'covariance_diag', 'control', 'spikes_per_step', 'raster', 'nees', 'nis')


def short(scenario, duration=SHORT):
    return dataclasses.replace(scenario, duration=duration, metric_window=min(scenario.metric_window, duration))


def assert_same_run(compiled, reference, rtol=1e-9):
    """Every trajectory equal to rtol of its own scale (NEES of the literal EMSIF reaches 1e5)."""
    for name in TRAJECTORIES:
        ours, theirs = getattr(compiled, name), getattr(reference, name)
        assert (ours is None) == (theirs is None), name
        if theirs is None:
            continue
        assert ours.shape == theirs.shape, name
        scale = max(float(np.nanmax(np.abs(theirs))) if np.isfinite(theirs).any() else 0.0, 1e-300)
        np.testing.assert_allclose(ours, theirs, rtol=rtol, atol=rtol * scale, err_msg=name)
    np.testing.assert_array_equal(compiled.extra['saturated_steps'], reference.extra['saturated_steps'])
    assert compiled.capped_steps == reference.capped_steps


@pytest.mark.parametrize('kind', list(FILTER_KINDS))
def test_the_compiled_loop_equals_the_python_loop_for_every_filter_kind(kind):
    scenario = short(rendezvous_scenario(initial_state_dispersion=True))
    assert_same_run(simulate(scenario, kind, runs=3, engine='compiled'),
                    simulate(scenario, kind, runs=3, engine='reference'))


@pytest.mark.parametrize('kind', list(FILTER_KINDS))
def test_the_compiled_loop_on_basilisk_truth_equals_the_python_loop(kind):
    """Basilisk steps the truth between two compiled calls (J2, the thrust limit)."""
    pytest.importorskip('Basilisk')
    scenario = short(rendezvous_scenario(initial_state_dispersion=True, plant='basilisk'), 20.0)
    assert_same_run(simulate(scenario, kind, runs=2, engine='compiled'),
                    simulate(scenario, kind, runs=2, engine='reference'))


@pytest.mark.parametrize('kind', ['ekf', 'snn_ekf', 'snn_emsif'])
@pytest.mark.parametrize('plant, dynamics_model', [('nonlinear_circular', 'nonlinear_circular'),
                                                   ('cw', 'nonlinear_circular'), ('nonlinear_circular', 'cw'),
                                                   ('nonlinear_circular', 'ss_j2'), ('ss_j2', 'cw')])
def test_the_compiled_loop_on_the_nonlinear_relative_motion_equals_the_python_loop(kind, plant, dynamics_model):
    """The filters' model, the truth or both the nonlinear relative motion, 5 km out: the loop
    recomputes the filter's A(x_hat), zero-order hold and drift before each step and steps the
    truth by its RK4 substeps, both compiled (snn_estimator.filters.model_kernels). A linear
    model other than CW (ss_j2, the J2 model) as the filters' model or the truth runs through
    the same constant-A path as CW."""
    scenario = short(far_range_scenario(plant=plant, dynamics_model=dynamics_model, initial_state_dispersion=True))
    assert_same_run(simulate(scenario, kind, runs=2, engine='compiled'),
                    simulate(scenario, kind, runs=2, engine='reference'))


def test_the_compiled_loop_with_the_nonlinear_model_on_basilisk_truth_equals_the_python_loop():
    pytest.importorskip('Basilisk')
    scenario = short(far_range_scenario(dynamics_model='nonlinear_circular', initial_state_dispersion=True), 20.0)
    assert_same_run(simulate(scenario, 'snn_ekf', runs=2, engine='compiled'),
                    simulate(scenario, 'snn_ekf', runs=2, engine='reference'))


@pytest.mark.parametrize('kind, changes', [
    ('snn_emsif', {'membrane_noise': 0.01}),  # 0.05 drives N = 200 to the spike cap within 8 steps
    ('snn_ekf', {'gain_schedule': 'steady_state'}),
    ('snn_emsif_weighted', {'network_coding': 'deviation'}),
    ('snn_emsif', {'spike_rule': 'all_above'}),
    ('snn_ekf', {'spike_rule': 'one_per_step', 'neuron_count': 60}),
])
def test_the_compiled_loop_equals_the_python_loop_with_network_options(kind, changes):
    scenario = short(rendezvous_scenario(initial_state_dispersion=True, **changes))
    assert_same_run(simulate(scenario, kind, runs=2, engine='compiled'),
                    simulate(scenario, kind, runs=2, engine='reference'))


def test_the_compiled_loop_equals_the_python_loop_with_events_setpoint_and_held_noise():
    """Events between two chunk ends (silencing neurons at step 300; retuning the filter at 250),
    the far-range hold point (setpoint) on the CW truth, and the held-sample reading of the
    truth's noise."""
    silence = {300: lambda estimator: estimator.silence(range(0, 200, 3))}
    scenario = short(rendezvous_scenario(initial_state_dispersion=True))
    assert_same_run(simulate(scenario, 'snn_emsif_weighted', runs=2, events=silence, engine='compiled'),
                    simulate(scenario, 'snn_emsif_weighted', runs=2, events=silence, engine='reference'))
    far = short(far_range_scenario(plant='cw'), 600.0)
    assert_same_run(simulate(far, 'snn_ekf', runs=2, engine='compiled'),
                    simulate(far, 'snn_ekf', runs=2, engine='reference'))
    retune = {250: lambda estimator: estimator.retune(boundary_layer=0.02, process_noise_scale=10.0)}
    assert_same_run(simulate(scenario, 'snn_emsif', runs=2, events=retune, engine='compiled'),
                    simulate(scenario, 'snn_emsif', runs=2, events=retune, engine='reference'))
    held = dataclasses.replace(scenario, truth_noise='held_sample')
    assert_same_run(simulate(held, 'ekf', runs=2, engine='compiled'),
                    simulate(held, 'ekf', runs=2, engine='reference'))


def test_an_open_loop_schedule_is_flown_as_the_python_loop_flies_it():
    scenario = short(rendezvous_scenario(initial_state_dispersion=True))
    schedule = np.zeros((scenario.steps, 3))
    schedule[100:150] = [1e-3, 0.0, -2e-3]
    open_loop = dataclasses.replace(scenario, lqr_state_weight=None, lqr_input_weight=None, control_schedule=schedule)
    compiled = simulate(open_loop, 'ekf', runs=2, engine='compiled')
    assert_same_run(compiled, simulate(open_loop, 'ekf', runs=2, engine='reference'))
    np.testing.assert_array_equal(compiled.control[0], schedule)


def test_one_run_alone_is_run_zero_of_a_batch():
    scenario = short(rendezvous_scenario(initial_state_dispersion=True))
    alone = simulate(scenario, 'snn_emsif', runs=1, seed=4, engine='compiled')
    batch = simulate(scenario, 'snn_emsif', runs=5, seed=4, engine='compiled')
    np.testing.assert_array_equal(alone.truth[0], batch.truth[0])
    np.testing.assert_array_equal(alone.estimate[0], batch.estimate[0])
    np.testing.assert_array_equal(alone.spikes_per_step[0], batch.spikes_per_step[0])


def test_auto_compiles_what_it_can_and_runs_the_rest_in_python():
    """A measurement model, a nonlinear model without a compiled twin (Van der Pol) and the
    spiking LQR run the reference loop under engine auto; asked for by name, the compiled engine
    says why it cannot."""
    with pytest.raises(ValueError, match='measurement model'):
        simulate(short(angles_only_scenario(), 10.0), 'ekf', engine='compiled')
    with pytest.raises(ValueError, match='nonlinear model without a compiled twin'):
        simulate(van_der_pol_scenario(), 'ekf', engine='compiled')
    with pytest.raises(ValueError, match='controller snn_lqr'):
        simulate(short(rendezvous_scenario(), 1.0), 'ekf', controller='snn_lqr', engine='compiled')
    with pytest.raises(ValueError, match='engine must be one of'):
        simulate(short(rendezvous_scenario(), 1.0), 'ekf', engine='fast')
    scenario = short(van_der_pol_scenario(), 1.0)
    assert_same_run(simulate(scenario, 'ekf', engine='auto'), simulate(scenario, 'ekf', engine='reference'))


def test_a_control_that_is_not_finite_ends_its_run_at_that_step_in_both_loops():
    """A known schedule with a NaN at step 37: that run diverges there (cause control), before
    anything of the step happens, in the compiled loop as in the Python loop."""
    scenario = short(rendezvous_scenario(), 10.0)
    schedule = np.zeros((scenario.steps, 3))
    schedule[37] = np.nan
    open_loop = dataclasses.replace(scenario, lqr_state_weight=None, lqr_input_weight=None, control_schedule=schedule)
    for engine in ('compiled', 'reference'):
        result = simulate(open_loop, 'ekf', engine=engine)
        assert result.diverged_at.tolist() == [37] and result.extra['diverged_cause'].tolist() == ['control']
        assert np.isfinite(result.truth[0, :38]).all() and np.isnan(result.truth[0, 38:]).all()


def test_taking_rows_in_blocks_gives_the_rows_of_single_draws():
    one_by_one, taken = GaussianStream([3, 9], 2, 4, block=7), GaussianStream([3, 9], 2, 4, block=7)
    rows = np.stack([one_by_one.draw().copy() for _ in range(23)], axis=1)
    parts = [taken.take(5), taken.take(1), taken.draw()[:, None].copy(), taken.take(9), taken.draw()[:, None].copy(),
             taken.take(6)]  # across the block ends, and a draw after rows taken past a block
    np.testing.assert_array_equal(np.concatenate(parts, axis=1), rows)
    assert all(part.flags.c_contiguous for part in parts)


@pytest.mark.parametrize('kind', ['ekf', 'esif', 'snn_emsif', 'snn_emsif_star'])
@pytest.mark.parametrize('engine', ['compiled', 'reference'])
def test_without_trajectories_a_run_reads_as_the_run_that_kept_them(kind, engine):
    """trajectories=False keeps the window's sums and per-run totals only: every reading a table
    takes equals the full run's (a filter with and without P, with and without spikes)."""
    scenario = dataclasses.replace(short(rendezvous_scenario(initial_state_dispersion=True), 120.0), metric_window=50.0)
    full = simulate(scenario, kind, runs=3, engine='reference')
    lean = simulate(scenario, kind, runs=3, engine=engine, trajectories=False)
    assert lean.truth is None and lean.estimate is None and lean.control is None and lean.nees is None
    np.testing.assert_allclose(lean.rmse(), full.rmse(), rtol=1e-9)
    np.testing.assert_allclose(lean.mean_error(), full.mean_error(), rtol=1e-9)
    np.testing.assert_allclose(lean.final_range(), full.final_range(), rtol=1e-9)
    np.testing.assert_allclose(lean.delta_v(), full.delta_v(), rtol=1e-9)
    assert lean.spike_fraction == full.spike_fraction
    ours, theirs = lean.consistency(), full.consistency()
    assert ours.keys() == theirs.keys()
    for name in ours:
        assert ours[name]['average'] == pytest.approx(theirs[name]['average'], rel=1e-9)
        assert ours[name]['verdict'] == theirs[name]['verdict']
    with pytest.raises(ValueError, match='trajectories=True'):
        lean.rmse(10.0)
    with pytest.raises(ValueError, match='trajectories=True'):
        lean.rmse_history()


def test_a_run_without_trajectories_holds_memory_for_its_chunk_not_its_duration():
    """simulate(trajectories=False): the peak memory of a 360 s EKF batch is a small fraction of
    the trajectories' (issue 25: a run keeps its trajectories only when asked)."""
    import tracemalloc
    scenario = rendezvous_scenario(initial_state_dispersion=True)
    simulate(short(scenario, 1.0), 'ekf', runs=2)
    peaks = {}
    for trajectories in (True, False):
        tracemalloc.start()
        simulate(scenario, 'ekf', runs=50, trajectories=trajectories)
        peaks[trajectories] = tracemalloc.get_traced_memory()[1] / 50
        tracemalloc.stop()
    assert peaks[True] > 500e3  # ~0.65 MB of trajectories per run
    assert peaks[False] < 0.1 * peaks[True], peaks


def test_the_bench_states_the_loop_against_the_filters_own_step():
    """make bench's Monte-Carlo figures (results/bench_monte_carlo.json): CPU us per run-step
    of each engine and of the filter's step alone, and their ratios."""
    from snn_tools.bench.steps import closed_loop_costs
    costs = closed_loop_costs(short(rendezvous_scenario(initial_state_dispersion=True), 5.0), 'ekf', runs=4, passes=1)
    for name in ('compiled', 'compiled_sums', 'reference', 'filter_step'):
        assert 0 < costs[name] < 1e4, costs
    assert costs['compiled_over_filter_step'] == pytest.approx(costs['compiled'] / costs['filter_step'], rel=0.02)
    assert costs['reference_over_filter_step'] == pytest.approx(costs['reference'] / costs['filter_step'], rel=0.02)
    assert 0 < costs['noise_draws'] and 0 < costs['loop_around_nothing'] < 1e4, costs


def test_the_bench_loop_around_a_filter_doing_nothing_leaves_the_estimate_and_restores_the_filter():
    """The loop's own cost (make bench's 'nothing' column) is the same loop, truth, sensor and
    control around a step that changes nothing; afterwards simulate flies the real filter again."""
    from snn_tools.bench.steps import filter_doing_nothing
    scenario = short(rendezvous_scenario(initial_state_dispersion=True), 5.0)
    real = simulate(scenario, 'ekf', runs=2, engine='compiled')
    with filter_doing_nothing():
        idle = simulate(scenario, 'ekf', runs=2, engine='compiled')
    np.testing.assert_array_equal(idle.estimate, np.repeat(idle.estimate[:, :1], idle.estimate.shape[1], axis=1))
    np.testing.assert_array_equal(idle.truth[:, 0], real.truth[:, 0])
    assert not np.allclose(idle.truth[:, -1], real.truth[:, -1])  # flown on the unchanging estimate
    assert_same_run(simulate(scenario, 'ekf', runs=2, engine='compiled'), real)


def _poison_covariance(estimator):
    estimator.state.p[1, 0, 0] = np.nan  # the gain, then the estimate of run 1 go non-finite in the step


def _poison_estimate(estimator):
    estimator.state.x_hat[2, 1] = np.inf  # run 2's control is not finite before the step


def _overdrive_network(estimator):
    estimator.network.v[1] = 1e9  # run 1's network spikes up to its cap


@pytest.mark.parametrize('kind, events', [
    ('ekf', {300: _poison_covariance}), ('ekf', {250: _poison_estimate}),
    ('snn_emsif', {300: _overdrive_network}), ('snn_ekf', {100: _poison_estimate})])
@pytest.mark.parametrize('trajectories', [True, False])
def test_a_run_that_diverges_is_marked_and_left_out_as_the_python_loop_does(kind, events, trajectories):
    """simulate's divergence rules (a run's control, estimate or covariance not finite, or its
    network at its spike cap) in the compiled loop: the same run, step and cause, the same NaN
    samples after it, the same statistics over the other runs, with and without trajectories."""
    scenario = dataclasses.replace(short(rendezvous_scenario(initial_state_dispersion=True)), metric_window=20.0)
    ours = simulate(scenario, kind, runs=3, events=events, engine='compiled', trajectories=trajectories)
    theirs = simulate(scenario, kind, runs=3, events=events, engine='reference', trajectories=trajectories)
    assert ours.diverged.sum() == 1
    np.testing.assert_array_equal(ours.diverged_at, theirs.diverged_at)
    np.testing.assert_array_equal(ours.extra['diverged_cause'], theirs.extra['diverged_cause'])
    np.testing.assert_allclose(ours.rmse(), theirs.rmse(), rtol=1e-9)
    np.testing.assert_allclose(ours.final_range(), theirs.final_range(), rtol=1e-9)  # NaN for the diverged run
    np.testing.assert_allclose(ours.delta_v(), theirs.delta_v(), rtol=1e-9)
    assert ours.spike_fraction == pytest.approx(theirs.spike_fraction, rel=1e-12) if ours.spike_fraction else True
    for name, check in ours.consistency().items():
        assert check['average'] == pytest.approx(theirs.consistency()[name]['average'], rel=1e-9)
    if trajectories:
        assert_same_run(ours, theirs)


def test_a_run_that_diverges_on_basilisk_truth_is_marked_as_the_python_loop_does():
    pytest.importorskip('Basilisk')
    scenario = short(rendezvous_scenario(initial_state_dispersion=True, plant='basilisk'), 20.0)
    events = {60: _poison_estimate}
    ours = simulate(scenario, 'ekf', runs=3, events=events, engine='compiled')
    theirs = simulate(scenario, 'ekf', runs=3, events=events, engine='reference')
    np.testing.assert_array_equal(ours.diverged_at, [-1, -1, 60])
    np.testing.assert_array_equal(ours.diverged_at, theirs.diverged_at)
    assert_same_run(ours, theirs)
