"""Campaigns of the approach and of the dynamics model (issue 39, item 4): a spec with scenario
approach parses and refuses bad settings by name, an approach cell's row is summarize() of the
flights fly_approach flies for it, dynamics_model is a grid key of the scenarios that build the
filters' model from it, and rows finished before the scenario/dynamics_model columns get them.
Every cell here starts at the 20 m hold (a ~800 s approach to contact, ~1 s)."""

import json

import pytest

from snn_estimator.models import relative_motion
from snn_estimator.sim.approach import HOLDS, LEGS, approach_scenario, fly_approach, summarize
from snn_tools.campaign.cells import build_scenario, run_cell
from snn_tools.campaign.report import write_report
from snn_tools.campaign.spec import SpecError, cell_path, parse_spec, read_rows, validate

#: A short approach: from the 20 m hold to contact, on the model truth the filters use.
SHORT = {'first_hold': '20 m', 'plant': 'cw'}
SPEC = {'scenario': 'approach', 'runs': 1, 'filters': ['ekf', 'snn_ekf'],
        'grid': {'dynamics_model': ['cw', 'nonlinear_circular']}, 'settings': SHORT}


def test_a_spec_with_scenario_approach_parses_into_a_cell_per_filter_and_dynamics_model():
    spec = parse_spec({**SPEC, 'settings': {**SHORT, 'sensors': 'by_range', 'max_duration': 900.0}})
    cells = spec.cells()
    assert [(c.filter, c.settings['dynamics_model']) for c in cells] == [
        ('ekf', 'cw'), ('snn_ekf', 'cw'), ('ekf', 'nonlinear_circular'), ('snn_ekf', 'nonlinear_circular')]
    assert all(c.settings['sensors'] == 'by_range' and c.settings['first_hold'] == '20 m' for c in cells)
    with pytest.raises(SpecError, match=r"settings\.duration: setting 'duration' applies to .* only, not approach"):
        parse_spec({**SPEC, 'settings': {**SHORT, 'duration': 10.0}})


@pytest.mark.parametrize('key, value, message', [
    ('dynamics_model', 'kepler', "dynamics_model must be one of cw, nonlinear_circular, ss_j2; got 'kepler'"),
    ('plant', 'j2_model', "plant must be one of cw, nonlinear_circular, ss_j2, basilisk; got 'j2_model'"),
    ('sensors', 'radar', "sensors must be one of position, by_range, angles_far; got 'radar'"),
    ('first_hold', '1 km', "first_hold must be one of 5 km, 2 km, 250 m, 20 m; got '1 km'"),
])
def test_a_bad_approach_setting_is_refused_naming_the_key_and_its_choices(key, value, message):
    grid = {key: [value]} if key == 'dynamics_model' else {**SPEC['grid']}
    settings = {**SHORT, key: value} if key != 'dynamics_model' else SHORT
    with pytest.raises(SpecError, match=message):
        validate(parse_spec({**SPEC, 'grid': grid, 'settings': settings}))


def test_a_filter_without_a_covariance_is_refused_by_the_approach():
    with pytest.raises(SpecError, match=r'\(filter esif\).*esif has none'):
        validate(parse_spec({**SPEC, 'filters': ['esif']}))


def test_dynamics_model_is_refused_where_the_scenario_flies_cw_only():
    with pytest.raises(SpecError, match="grid.dynamics_model: setting 'dynamics_model' applies to far_range, "
                                        'approach only, not rendezvous'):
        parse_spec({'scenario': 'rendezvous', 'runs': 1, 'filters': ['ekf'],
                    'grid': {'dynamics_model': ['cw', 'nonlinear_circular']}})


@pytest.mark.parametrize('scenario', ['far_range', 'approach'])
def test_dynamics_model_as_a_grid_key_builds_each_cell_with_that_model(scenario):
    spec = parse_spec({'scenario': scenario, 'runs': 1, 'filters': ['ekf'],
                       'grid': {'dynamics_model': ['cw', 'nonlinear_circular']}, 'settings': {'plant': 'cw'}})
    for cell, name in zip(spec.cells(), ('cw', 'nonlinear_circular')):
        built = build_scenario(scenario, cell.settings, seed=0)
        assert type(built.model) is type(relative_motion(name))
        assert built.model.dynamics_model == built.estimator.dynamics_model == name
        truth = built.truth if scenario == 'approach' else (built.truth_model or built.model)
        assert type(truth) is type(relative_motion('cw'))  # plant cw: the truth stays CW


@pytest.fixture(scope='module')
def two_runs():
    """A two-run SNN-EKF cell on the nonlinear model, one run per task (so the row combines two
    batches), and the same two flights flown directly in one batch."""
    settings = {**SHORT, 'dynamics_model': 'nonlinear_circular'}
    row = run_cell('approach', 'snn_ekf', settings, runs=2, seed=3, runs_per_task=1)
    scenario = approach_scenario('nonlinear_circular', plant='cw', holds=HOLDS[3:], legs=LEGS[3:])
    return settings, row, summarize(fly_approach(scenario, 'snn_ekf', runs=2, seed=3))


def test_an_approach_cell_gives_summarize_of_its_flights_flown_directly(two_runs):
    _, row, expected = two_runs
    assert expected['outcomes']['contact'] == 2  # the figures at contact below are numbers
    assert expected['delta_v']['mean'] < expected['delta_v']['max']  # two runs: mean and max differ
    assert (row['scenario'], row['dynamics_model'], row['runs'], row['seed']) == (
        'approach', 'nonlinear_circular', 2, 3)
    assert row['contact_rate'] == expected['outcomes']['contact'] / 2
    pairs = {'closing_speed_mean': expected['closing_speed']['mean'],
             'closing_speed_max': expected['closing_speed']['max'],
             'lateral_at_contact_max': expected['lateral_at_contact']['max'],
             'corridor_violation_runs': expected['corridor_violation_runs'],
             'keep_out_entry_before_go': expected['keep_out_entry_before_go'],
             'outcomes_abort': expected['outcomes']['abort'], 'outcomes_no_go': expected['outcomes']['no_go'],
             'delta_v_mean': expected['delta_v']['mean'], 'delta_v_max': expected['delta_v']['max'],
             'nees_mean': expected['nees']['mean'],
             'holds_20m_hold_error_mean': expected['holds']['20 m']['hold_error']['mean'],
             'holds_20m_go': expected['holds']['20 m']['go'], 'spikes_mean': expected['spikes']['mean'],
             'success': expected['success']}
    assert {k: row[k] for k in pairs} == pytest.approx(pairs, rel=1e-12)
    assert row['holds_5km_hold_error_mean'] is None and row['holds_5km_go'] == 0  # a hold never flown
    assert row['spikes_mean'] > 0


def test_the_summary_shows_the_scenario_the_dynamics_model_and_the_safety_figures(two_runs, tmp_path):
    settings, row, expected = two_runs
    spec = parse_spec({'scenario': 'approach', 'runs': 2, 'seed': 3, 'filters': ['snn_ekf'],
                       'grid': {'first_hold': ['20 m']}, 'settings': {k: v for k, v in settings.items()
                                                                      if k != 'first_hold'}})
    text = write_report(tmp_path, spec, [row], total_cells=1).read_text()
    head = next(line for line in text.splitlines() if line.startswith('| scenario'))
    assert head.startswith('| scenario | dynamics_model | first_hold | contact_rate | success | closing_speed_mean')
    line = next(line for line in text.splitlines() if line.startswith('| approach'))
    assert line.startswith(f"| approach | nonlinear_circular | 20 m | 1 | {expected['success']} | "
                           f"{expected['closing_speed']['mean']:.3g} |")


def test_a_row_finished_before_the_identity_columns_gets_them_when_read(tmp_path):
    spec = parse_spec({'scenario': 'far_range', 'runs': 1, 'filters': ['ekf'],
                       'grid': {'dynamics_model': ['cw', 'nonlinear_circular']}})
    (tmp_path / 'cells').mkdir()
    for cell in spec.cells():  # rows as campaigns wrote them before: no scenario, no dynamics_model
        old = {'filter': cell.filter, **cell.settings, 'runs': 1, 'seed': 0, 'rmse_x': 1.0}
        cell_path(tmp_path, cell).write_text(json.dumps(old))
    rows = read_rows(tmp_path, spec.cells(), spec.scenario)
    assert [(r['scenario'], r['dynamics_model'], r['rmse_x']) for r in rows] == [
        ('far_range', 'cw', 1.0), ('far_range', 'nonlinear_circular', 1.0)]
    assert list(rows[0])[:3] == ['filter', 'scenario', 'dynamics_model']
