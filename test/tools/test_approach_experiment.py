"""make approach's tool (snn_tools.experiments.approach): its cells are fly_approach's runs and
their summary, the results say which sensors each suite flew, and its tables show each cell."""

import numpy as np

from snn_estimator.config import resolve
from snn_estimator.sim.approach import HOLDS, LEGS, approach_scenario, fly_approach, summarize
from snn_tools.experiments import approach as experiment

#: From the 250 m hold for 400 s: the hold's go and the start of the last transfer, in ~1 s.
SHORT = {'holds': HOLDS[2:], 'legs': LEGS[2:], 'max_duration': 400.0}
CELLS = (('ekf/cw/short', 'ekf', 'cw', SHORT),
         ('ekf/nonlinear_circular/short/sensors=angles_far', 'ekf', 'nonlinear_circular',
          {**SHORT, 'sensors': 'angles_far'}))


def test_a_cell_is_the_summary_of_the_runs_fly_approach_flies_and_the_results_name_each_suites_sensors():
    results = experiment.campaign(2, kinds=(), models=(), plant='nonlinear_circular', seed=3, extra=CELLS)
    assert list(results['cells']) == [name for name, *_ in CELLS]
    for name, kind, model, changes in CELLS:
        flights = fly_approach(approach_scenario(model, plant='nonlinear_circular', **changes), kind, runs=2, seed=3)
        cell = results['cells'][name]
        assert (cell['kind'], cell['dynamics_model']) == (kind, model)
        assert cell['summary'] == summarize(flights)
        assert [f['holds'] for f in cell['flights']] == [f['holds'] for f in flights]
    assert results['cells']['ekf/cw/short']['summary']['holds']['250 m']['go'] == 2
    # the suites as flown: from the scenario's stacked sensors, not a sentence written beside them
    assert results['sensor'] == ('position (R = 1e-2 m^2, 1 Hz); sensors=angles_far: line_of_sight from 1000 m, '
                                 'range_azimuth_elevation from 1.8 m to 3000 m, docking_camera from 0.05 m to 30 m, '
                                 '1 Hz each')


def test_the_tables_have_a_row_per_cell_and_the_hold_figures_at_each_decision():
    results = experiment.campaign(1, kinds=(), models=(), plant='nonlinear_circular', extra=CELLS[:1])
    text = experiment.table(results)
    row = next(line for line in text.splitlines() if line.startswith('| ekf/cw/short |'))
    summary = results['cells']['ekf/cw/short']['summary']
    assert f"{summary['delta_v']['mean']:.2f}" in row
    assert "at each hold's decision (go, or the no-go that ended the run), mean (max):" in text
    error = summary['holds']['250 m']['estimate_error']
    assert f"| ekf/cw/short | - (-) | - (-) | {error['mean']:.3f} ({error['max']:.3f}) |" in text
    assert np.isfinite(error['mean'])


def test_the_j2_q_cells_raise_only_the_filters_velocity_noise():
    """J2_Q_CELLS (decision 83): the EKF on each model with the filter's Q on the velocity states
    at 1e-9 and 1e-8 (Q_hat 0.9 of it), the position states and the truth's own process noise as
    the default's."""
    default = approach_scenario('cw')
    for name, kind, model, changes in experiment.J2_Q_CELLS:
        scenario = approach_scenario(model, **changes)
        q = float(name.split('=')[-1])
        scale = scenario.estimator.process_noise_scale  # Q_hat = scale Q, 0.9 (Sec. 3.2)
        q_hat = np.diag(resolve(scenario.estimator, scenario.model).q_hat)
        assert kind == 'ekf'
        np.testing.assert_allclose(q_hat, scale * np.array([1e-12] * 3 + [q] * 3), rtol=1e-12)
        np.testing.assert_array_equal(scenario.process_noise, default.process_noise)
    assert {float(n.split('=')[-1]) for n, *_ in experiment.J2_Q_CELLS} == {1e-9, 1e-8}


def test_the_tracked_results_hold_the_summaries_and_give_the_same_tables_without_each_runs_figures():
    """make approach writes each run's figures apart (results/*_runs.json, untracked): the
    tracked file keeps the summaries, and the tables (the sensors' samples included) are the same."""
    results = experiment.campaign(2, kinds=(), models=(), plant='nonlinear_circular', extra=CELLS[1:])
    tracked, runs = experiment.split_runs(results)
    assert all('flights' not in cell for cell in tracked['cells'].values())
    assert runs == {name: cell['flights'] for name, cell in results['cells'].items()} and len(runs[CELLS[1][0]]) == 2
    assert experiment.table(tracked) == experiment.table(results)
    assert 'Sensors by range: samples per run' in experiment.table(tracked)
