"""Monte-Carlo campaigns (snn_tools.campaign.run): spec checking, the cell runner, resuming, and the
same table whatever the cluster. The multi-process tests start their own Dask clusters and
processes, bound every wait, and kill what they started."""

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from snn_estimator.sim.simulate import simulate
from snn_tools.campaign import cells as campaign_cells
from snn_tools.campaign import run as campaign
from snn_tools.campaign.cells import SETTINGS, build_scenario, run_cell
from snn_tools.campaign.run import CampaignProgress, dask_client, main, run_campaign
from snn_tools.campaign.spec import CellFailed, SpecError, load_spec, parse_spec, prepare_directory, validate

distributed = pytest.importorskip('distributed')

DASK = Path(sys.executable).with_name('dask')
#: A small campaign: 4 grid points x 2 filters = 8 cells of 6 runs in batches of 4 (2 per cell).
TINY = {'scenario': 'rendezvous', 'runs': 6, 'runs_per_task': 4, 'filters': ['snn_emsif', 'ekf'],
        'grid': {'leak_rate': [0.001, 0.01], 'neuron_count': [50, 100]},
        'settings': {'duration': 5.0, 'metric_window': 2.0}}
#: Long enough to interrupt and to kill a worker in the middle: 16 cells, ~0.3 s each.
MEDIUM = {'scenario': 'rendezvous', 'runs': 8, 'runs_per_task': 4, 'filters': ['snn_emsif', 'ekf'],
          'grid': {'neuron_count': [50, 100], 'leak_rate': [0.001, 0.01], 'boundary_layer': [0.05, 0.1]},
          'settings': {'duration': 60.0, 'metric_window': 10.0}}


def spec_with(**changes) -> dict:
    return {**TINY, **changes}


def table(out: Path) -> list[dict]:
    """results.parquet as rows, without the wall times (the only column that may differ)."""
    return [{k: v for k, v in row.items() if k != 'wall_time_s'}
            for row in pq.read_table(out / 'results.parquet').to_pylist()]


def reference(spec) -> list[dict]:
    """Every cell computed in this process, without Dask."""
    rows = [run_cell(spec.scenario, c.filter, c.settings, spec.runs, spec.seed, spec.runs_per_task)
            for c in spec.cells()]
    return [{k: v for k, v in row.items() if k != 'wall_time_s'} for row in rows]


@pytest.fixture(scope='module')
def client():
    """An in-process Dask cluster (one worker thread): the campaign logic without process start-up."""
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=1,
                            dashboard_address=None) as in_process:
        yield in_process


# ---------------------------------------------------------------- spec checking
@pytest.mark.parametrize('changes, key', [
    ({'grdi': {}}, 'grdi'),
    ({'grid': {'leak_rat': [0.1]}}, 'leak_rat'),
    ({'grid': {'leak_rate': [0.01, -1.0]}}, 'leak_rate'),
    ({'grid': {}}, 'grid'),
    ({'grid': {'leak_rate': []}}, 'grid.leak_rate'),
    ({'grid': {'leak_rate': 0.01}}, 'grid.leak_rate'),
    ({'grid': {'leak_rate': [0.01, 0.01]}}, 'grid.leak_rate'),
    ({'grid': {'neuron_count': [100.5]}}, 'neuron_count'),
    ({'grid': {'boundary_layer': [[0.1, 0.2]]}}, 'boundary_layer'),
    ({'grid': {'silenced_fraction': [1.5]}}, 'silenced_fraction'),
    ({'grid': {'preset': ['literal']}}, 'preset'),
    ({'grid': {'seed': [1, 2]}}, 'seed'),
    ({'grid': {'neuron_count': [50]}, 'settings': {'neuron_count': 100}}, 'neuron_count'),
    ({'settings': {'duration': 5.05, 'metric_window': 2.0}}, 'duration'),
    ({'settings': {'duration': 5.0, 'metric_window': 6.0}}, 'metric_window'),
    ({'filters': ['snn_kalman']}, 'snn_kalman'),
    ({'filters': []}, 'filters'),
    ({'scenario': 'lunar_landing'}, 'scenario'),
    ({'runs': 0}, 'runs'),
    ({'runs': 2.5}, 'runs'),
    ({'seed': -1}, 'seed'),
    ({'runs_per_task': 0}, 'runs_per_task'),
])
def test_a_bad_spec_is_refused_naming_the_key(changes, key):
    with pytest.raises(SpecError, match=key):
        validate(parse_spec(spec_with(**changes)))


def test_a_setting_of_another_scenario_is_refused():
    spec = {**TINY, 'scenario': 'van_der_pol', 'grid': {'cw_model': ['standard', 'as_published']},
            'settings': {}}
    with pytest.raises(SpecError, match='cw_model.*rendezvous only'):
        parse_spec(spec)


def test_values_bad_only_together_are_refused_naming_the_cell():
    spec = spec_with(grid={'duration': [10.0, 5.0], 'metric_window': [2.0, 8.0]}, settings={})
    with pytest.raises(SpecError, match=r"grid cell \{'duration': 5.0, 'metric_window': 8.0\}.*"
                                        r'metric_window \(8.0 s\) must not exceed duration'):
        validate(parse_spec(spec))


def test_the_command_line_refuses_a_bad_spec_before_anything_runs(tmp_path, capsys):
    path = tmp_path / 'bad.yaml'
    path.write_text(yaml.safe_dump(spec_with(grid={'leak_rate': [-0.5]})))
    assert main(['--spec', str(path), '--out', str(tmp_path / 'out')]) == 2
    assert 'leak_rate' in capsys.readouterr().err
    assert not (tmp_path / 'out').exists()


def test_the_command_line_lists_the_settings_a_grid_may_sweep(capsys):
    assert main(['--list-settings']) == 0
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    assert listed == list(SETTINGS)


def test_numbers_written_1e_3_are_numbers(tmp_path):
    path = tmp_path / 'spec.yaml'
    path.write_text('scenario: rendezvous\nruns: 1\nfilters: [ekf]\ngrid: {leak_rate: [1e-3, 2.5E+2]}\n')
    assert load_spec(path).grid['leak_rate'] == [0.001, 250.0]


def test_the_shipped_specs_are_valid():
    for name in ('campaigns/example.yaml', 'campaigns/bench.yaml', 'campaigns/docking.yaml', 'campaigns/approach.yaml'):
        validate(load_spec(name))


def test_every_setting_goes_somewhere():
    for name, setting in SETTINGS.items():
        assert setting.target in ('estimator', 'factory', 'scenario', 'derived'), name
        assert (setting.apply is not None) == (setting.target == 'derived'), name


# ---------------------------------------------------------------- the cell runner
def test_a_cell_equals_the_core_monte_carlo_of_the_same_seeds():
    settings = {'neuron_count': 60, 'duration': 5.0, 'metric_window': 2.0}
    row = run_cell('rendezvous', 'snn_emsif', settings, runs=5, seed=3, runs_per_task=5)
    scenario = build_scenario('rendezvous', settings, seed=3)
    direct = simulate(scenario, 'snn_emsif', runs=5, seed=3)
    states = scenario.model.state_names
    assert [row[f'rmse_{s}'] for s in states] == direct.rmse().tolist()
    assert [row[f'mean_error_{s}'] for s in states] == direct.mean_error().tolist()
    assert row['spike_fraction'] == direct.spike_fraction
    assert row['final_range_median'] == float(np.median(direct.final_range()))
    assert (row['filter'], row['runs'], row['seed'], row['neuron_count']) == ('snn_emsif', 5, 3, 60)


def test_batches_change_only_the_rounding_of_a_cell():
    settings = {'duration': 5.0, 'metric_window': 2.0}
    whole = run_cell('rendezvous', 'snn_ekf', settings, runs=7, runs_per_task=7)
    split = run_cell('rendezvous', 'snn_ekf', settings, runs=7, runs_per_task=3)
    for key, value in whole.items():
        if key.startswith(('rmse_', 'mean_error_')):
            assert split[key] == pytest.approx(value, rel=1e-12), key
    assert split['spike_fraction'] == whole['spike_fraction']
    assert split['final_range_median'] == whole['final_range_median']


def test_a_non_spiking_cell_has_no_spike_fraction_and_van_der_pol_no_range():
    row = run_cell('van_der_pol', 'ekf', {'duration': 0.5, 'metric_window': 0.2}, runs=2)
    assert row['spike_fraction'] is None
    assert 'final_range_median' not in row
    assert {'rmse_x1', 'rmse_x2', 'mean_error_x1', 'mean_error_x2'} <= set(row)


def test_a_silenced_fraction_silences_what_the_ros_estimator_would():
    pytest.importorskip('rclpy')
    from scenario_nodes.core_objects import silenced_set
    scenario = build_scenario('rendezvous', {'neuron_count': 40, 'silenced_fraction': 0.25}, seed=7)
    expected = silenced_set({'silenced_fraction': 0.25}, 40, 7)
    assert list(scenario.estimator.silenced_neurons) == expected and len(expected) == 10


def test_a_cell_is_the_same_with_or_without_other_grid_values():
    """Common random numbers: a cell's numbers depend on its own settings and the seed only."""
    one = parse_spec(spec_with(grid={'neuron_count': [50]}))
    two = parse_spec(spec_with(grid={'neuron_count': [100, 50]}))
    cell = one.cells()[0]
    same = next(c for c in two.cells() if c.settings == cell.settings and c.filter == cell.filter)
    assert cell.name == same.name
    first = run_cell(one.scenario, cell.filter, cell.settings, one.runs, one.seed, one.runs_per_task)
    second = run_cell(two.scenario, same.filter, same.settings, two.runs, two.seed, two.runs_per_task)
    assert {k: v for k, v in first.items() if k != 'wall_time_s'} == \
        {k: v for k, v in second.items() if k != 'wall_time_s'}


# ---------------------------------------------------------------- campaigns in process
def test_a_campaign_writes_one_row_per_cell_equal_to_the_cell_runner(tmp_path, client):
    spec = parse_spec(TINY)
    outcome = run_campaign(spec, tmp_path, client)
    assert (outcome.cells, outcome.computed, outcome.skipped) == (8, 8, 0)
    assert table(tmp_path) == reference(spec)
    columns = pq.read_schema(tmp_path / 'results.parquet').names
    for column in ('filter', 'leak_rate', 'neuron_count', 'runs', 'seed', 'rmse_x', 'mean_error_vz',
                   'spike_fraction', 'final_range_median', 'wall_time_s'):
        assert column in columns
    summary = (tmp_path / 'summary.md').read_text()
    assert '8 cells, complete' in summary
    assert (tmp_path / 'figures' / 'heatmap_rmse_x.png').exists()
    assert (tmp_path / 'figures' / 'spike_fraction_vs_N.png').exists()


def test_a_rerun_computes_only_the_missing_cells(tmp_path, client):
    spec = parse_spec(TINY)
    run_campaign(spec, tmp_path, client)
    full = table(tmp_path)
    cells = sorted((tmp_path / 'cells').glob('*.json'))
    cells[3].unlink()
    stamps = {p: p.stat().st_mtime_ns for p in cells if p.exists()}
    outcome = run_campaign(spec, tmp_path, client)
    assert (outcome.computed, outcome.skipped) == (1, 7)
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items())
    assert table(tmp_path) == full
    assert run_campaign(spec, tmp_path, client).computed == 0


def test_a_list_valued_setting_becomes_a_json_text_column(tmp_path, client):
    spec = parse_spec({'scenario': 'van_der_pol', 'runs': 2, 'filters': ['emsif'],
                       'grid': {'boundary_layer': [0.05, [0.1]]},
                       'settings': {'duration': 1.0, 'metric_window': 0.5}})
    validate(spec)
    run_campaign(spec, tmp_path, client)
    rows = pq.read_table(tmp_path / 'results.parquet').to_pylist()
    assert [r['boundary_layer'] for r in rows] == ['0.05', '[0.1]']


def test_another_spec_in_the_same_directory_is_refused(tmp_path):
    prepare_directory(tmp_path, parse_spec(TINY))
    with pytest.raises(SpecError, match='changed: runs'):
        prepare_directory(tmp_path, parse_spec(spec_with(runs=7)))
    prepare_directory(tmp_path, parse_spec(spec_with(description='only words differ')))


class _InterruptAfter(CampaignProgress):
    """A progress bar whose user presses Ctrl-C after ``cells`` cells."""

    def __init__(self, cells: int):
        super().__init__(quiet=True)
        self.limit = cells

    def cell_finished(self) -> None:
        super().cell_finished()
        if self.cells_done >= self.limit:
            raise KeyboardInterrupt


def test_an_interrupt_leaves_a_table_of_the_finished_cells(tmp_path, client):
    spec = parse_spec(TINY)
    with pytest.raises(KeyboardInterrupt):
        run_campaign(spec, tmp_path, client, _InterruptAfter(3))
    rows = table(tmp_path)
    assert len(rows) == len(list((tmp_path / 'cells').glob('*.json'))) == 3
    assert 'INCOMPLETE: 3 of 8 cells' in (tmp_path / 'summary.md').read_text()
    assert run_campaign(spec, tmp_path, client).computed == 5
    assert table(tmp_path) == reference(spec)


def test_a_failing_cell_stops_the_campaign_naming_it_and_keeps_the_finished_ones(tmp_path, client,
                                                                                monkeypatch):
    spec = parse_spec(TINY)
    broken = spec.cells()[2]

    def run_chunk(scenario, kind, settings, *args):
        if (kind, settings) == (broken.filter, broken.settings):
            raise FloatingPointError('diverged')
        return campaign_cells.run_chunk(scenario, kind, settings, *args)

    monkeypatch.setattr(campaign, 'run_chunk', run_chunk)
    with pytest.raises(CellFailed, match=r"cell snn_emsif \{'leak_rate': 0.001, 'neuron_count': 100.*diverged"):
        run_campaign(spec, tmp_path, client)
    rows = table(tmp_path)
    assert 2 <= len(rows) < 8 and not any(r['filter'] == broken.filter and r['neuron_count'] == 100
                                          and r['leak_rate'] == 0.001 for r in rows)


# ---------------------------------------------------------------- real clusters (processes)
def _start(command: list, log: Path) -> subprocess.Popen:
    """A process in its own session (so that it and its children can be signalled together),
    with SIGINT's default action as in a terminal: a test run started in the background of a
    non-interactive shell inherits SIGINT ignored, and the campaign would then run through its
    Ctrl-C (two fresh-clone `make test` runs started so failed that way)."""
    with open(log, 'w') as handle:
        return subprocess.Popen([str(c) for c in command], stdout=handle, stderr=subprocess.STDOUT,
                                start_new_session=True, env=os.environ.copy(),
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _stop(process: subprocess.Popen) -> None:
    """Terminate a process group started by _start; kill it if it lingers."""
    for sig, patience in ((signal.SIGTERM, 15), (signal.SIGKILL, 15)):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            break
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=patience)
            break
    with contextlib.suppress(subprocess.TimeoutExpired):
        process.wait(timeout=5)


def _wait_for(condition, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out after {seconds} s waiting for {what}')
        time.sleep(0.05)


@contextlib.contextmanager
def external_cluster(folder: Path, workers: int = 2):
    """`dask scheduler` and `dask worker` processes on localhost, as a user scales out;
    yields (address, worker processes)."""
    processes = []
    try:
        scheduler_file = folder / 'scheduler.json'
        processes.append(_start([DASK, 'scheduler', '--host', '127.0.0.1', '--port', '0',
                                 '--no-dashboard', '--scheduler-file', scheduler_file],
                                folder / 'scheduler.log'))
        _wait_for(scheduler_file.exists, 60, 'the scheduler file')
        address = json.loads(scheduler_file.read_text())['address']
        for index in range(workers):
            processes.append(_start([DASK, 'worker', address, '--nworkers', '1', '--nthreads', '1',
                                     '--host', '127.0.0.1', '--no-dashboard', '--name', f'w{index}'],
                                    folder / f'worker{index}.log'))
        with distributed.Client(address, timeout='30s') as probe:
            probe.wait_for_workers(workers, timeout=120)
        yield address, processes[1:]
    finally:
        for process in reversed(processes):
            _stop(process)


def _campaign_command(spec_path: Path, out: Path, *where) -> list:
    return [sys.executable, '-m', 'snn_tools.campaign.run', '--spec', spec_path, '--out', out, *where]


@pytest.fixture(scope='module')
def medium(tmp_path_factory):
    """The MEDIUM spec on disk, and its table computed in this process."""
    folder = tmp_path_factory.mktemp('medium')
    path = folder / 'medium.yaml'
    path.write_text(yaml.safe_dump(MEDIUM))
    return path, reference(load_spec(path))


@pytest.mark.slow
def test_the_table_is_the_same_with_1_or_2_workers_or_an_external_cluster(tmp_path, medium):
    path, expected = medium
    spec = load_spec(path)
    for workers in (1, 2):
        with dask_client(workers) as local:
            run_campaign(spec, tmp_path / f'local{workers}', local)
        assert table(tmp_path / f'local{workers}') == expected, f'{workers} local workers'
    with external_cluster(tmp_path) as (address, _):
        finished = subprocess.run([str(c) for c in _campaign_command(path, tmp_path / 'external',
                                                                     '--scheduler', address, '--quiet')],
                                  capture_output=True, text=True, timeout=300, check=False)
    assert finished.returncode == 0, finished.stderr
    assert table(tmp_path / 'external') == expected


@pytest.fixture(scope='module')
def longer(tmp_path_factory):
    """MEDIUM over the whole 360 s approach: a cell takes long enough (~0.2 s with the compiled
    loop) that a Ctrl-C after two cells finds most of them still to do."""
    folder = tmp_path_factory.mktemp('longer')
    path = folder / 'longer.yaml'
    path.write_text(yaml.safe_dump({**MEDIUM, 'settings': {'duration': 360.0, 'metric_window': 10.0}}))
    return path, reference(load_spec(path))


@pytest.mark.slow
def test_ctrl_c_keeps_the_finished_cells_and_the_same_command_finishes_the_rest(tmp_path, longer):
    path, expected = longer
    out = tmp_path / 'out'
    command = _campaign_command(path, out, '--workers', '1')
    campaign = _start(command, tmp_path / 'first.log')
    try:
        _wait_for(lambda: len(list((out / 'cells').glob('*.json'))) >= 2, 180, 'two finished cells')
        os.killpg(campaign.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
        assert campaign.wait(timeout=120) == 130, (tmp_path / 'first.log').read_text()
    finally:
        _stop(campaign)
    done = len(table(out))
    cells = sorted((out / 'cells').glob('*.json'))
    assert 2 <= done == len(cells) < len(expected)
    stamps = {p: p.stat().st_mtime_ns for p in cells}
    again = subprocess.run([str(c) for c in command], capture_output=True, text=True, timeout=300, check=False)
    assert again.returncode == 0, again.stderr
    assert f'{done} of {len(expected)} cells already done' in again.stderr
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items())
    assert table(out) == expected


def _running_on(client, name: str) -> bool:
    """Whether the worker called ``name`` is running a campaign task."""
    address = next(a for a, w in client.scheduler_info()['workers'].items() if w['name'] == name)
    return any(str(key).startswith('snn-campaign-') for key in client.processing([address])[address])


@pytest.mark.slow
def test_the_cells_of_a_killed_worker_are_recomputed(tmp_path, medium):
    path, expected = medium
    out = tmp_path / 'out'
    with external_cluster(tmp_path) as (address, workers):
        campaign = _start(_campaign_command(path, out, '--scheduler', address), tmp_path / 'campaign.log')
        try:
            with distributed.Client(address, timeout='30s') as observer:
                _wait_for(lambda: len(list((out / 'cells').glob('*.json'))) >= 1, 180, 'a finished cell')
                _wait_for(lambda: _running_on(observer, 'w0'), 60, 'a task running on w0')
                os.killpg(workers[0].pid, signal.SIGKILL)  # the machine of worker 0 is gone
            assert campaign.wait(timeout=240) == 0, (tmp_path / 'campaign.log').read_text()
        finally:
            _stop(campaign)
    assert len(list((out / 'cells').glob('*.json'))) == len(expected)
    assert table(out) == expected
