"""snn_latency_bench: the percentile maths against numpy, the stamp pairing against hand-built
samples, and one short realtime run through the real pipeline (the JSON keys, figures positive)."""

import json
import math
import os

import numpy as np
import pytest

from snn_tools.bench import latency as latency_bench
from snn_tools.bench.latency import first_arrivals, match_latencies, percentile, stamp_ns, summary


@pytest.mark.parametrize('values', [
    [3.0],
    [1.0, 2.0],
    [5.0, 1.0, 4.0, 2.0, 3.0],
    list(np.random.default_rng(7).exponential(0.4, 10_001)),  # a long tail, like latencies
    list(np.random.default_rng(8).integers(0, 5, 999).astype(float)),  # many ties
])
def test_percentiles_equal_numpy_s_linear_method(values):
    ordered = np.sort(np.asarray(values))
    for q in (0.0, 1.0, 50.0, 90.0, 99.0, 99.9, 100.0):
        assert percentile(ordered, q) == pytest.approx(np.percentile(values, q), rel=0, abs=1e-12), q


def test_percentile_refuses_no_samples_and_a_q_outside_0_100():
    with pytest.raises(ValueError):
        percentile(np.array([]), 50)
    with pytest.raises(ValueError, match='0-100'):
        percentile(np.array([1.0]), 101)


def test_summary_gives_p50_p99_max_and_the_start_apart():
    values = np.r_[[40.0] + [1.0] * (latency_bench.START_SAMPLES - 1), np.arange(1.0, 1001.0) / 100]
    figures = summary(values)
    assert figures['p50_ms'] == pytest.approx(np.percentile(values, 50))
    assert figures['p99_ms'] == pytest.approx(np.percentile(values, 99))
    assert figures['max_ms'] == 40.0 and figures['samples'] == values.size
    assert figures['start_max_ms'] == 40.0 and figures['steady_max_ms'] == 10.0
    with pytest.raises(ValueError, match='no latency samples'):
        summary([])


def test_latencies_pair_each_measurement_with_the_answer_stamped_one_step_later():
    step = 100_000_000
    measurement = {0: 1_000, step: 2_000, 2 * step: 3_000, 3 * step: 4_000}
    # the estimate using z_k is stamped t_k + step; z at 3*step has no answer yet (skipped)
    estimate = {step: 1_500_000 + 1_000, 2 * step: 2_000 + 250_000, 3 * step: 3_000 + 4_000_000, 0: 7}
    latencies = match_latencies(measurement, estimate, step)
    assert latencies.tolist() == pytest.approx([1.5, 0.25, 4.0])


def test_a_stamp_that_comes_again_counts_from_its_first_arrival():
    """A corrected estimate (or a resend) comes again under its stamp: the latency is to the
    first, the one the controller answered."""
    rows = np.array([[100, 5], [200, 9], [100, 12], [300, 20], [200, 30]], dtype=np.int64)
    assert first_arrivals(rows) == {100: 5, 200: 9, 300: 20}


def test_the_stamp_is_read_from_the_cdr_header():
    from scenario_nodes.codec import encode_accel, encode_odometry, encode_point
    stamp = 1_234 * 1_000_000_000 + 567_890_123
    assert stamp_ns(encode_point(np.ones(3), (0, 1, 2), stamp, 'lvlh')) == stamp
    assert stamp_ns(encode_accel(np.zeros(3), stamp, 'lvlh')) == stamp
    assert stamp_ns(encode_odometry(np.zeros(6), None, stamp, 'lvlh', 'chaser')) == stamp


def test_too_few_samples_are_refused():
    with pytest.raises(SystemExit) as error:
        latency_bench.main(['--samples', '3'])
    assert error.value.code == 2


def test_a_path_without_answers_or_a_steady_part_is_reported_not_raised():
    """Under load a short realtime run can miss every control (CI once got fewer than
    START_SAMPLES): the bench reports the count and prints a line instead of crashing."""
    none = latency_bench.path_figures(np.array([]), 60)
    assert none == {'samples': 0, 'unanswered': 60}
    assert 'no answers to 60 measurements' in latency_bench.format_line('10x', 'measurement_to_control', none)
    few = latency_bench.path_figures(np.array([2.0, 3.0, 4.0]), 60)
    assert few['samples'] == 3 and few['unanswered'] == 57 and few['steady_max_ms'] is None
    line = latency_bench.format_line('10x', 'measurement_to_control', few)
    assert 'after n/a' in line and '57 unanswered' in line


@pytest.mark.slow
def test_a_failed_case_keeps_the_finished_cases_and_its_logs_and_a_repeated_case_runs_in_its_own_folder(
        tmp_path, monkeypatch, capsys):
    """A case that fails (a node exiting early) must not lose the cases already measured, nor the
    logs its error message points to; a case named twice runs twice (the recorder refuses a bag
    folder that exists, so each run needs its own)."""
    folders = []

    def fake_run_case(run_dir, case, samples, estimator, domain_id):
        assert run_dir not in folders
        folders.append(run_dir)
        run_dir.mkdir(parents=True)
        (run_dir / 'logs').mkdir()
        if case == '10x_batch':
            raise RuntimeError(f'node(s) [\'recorder\'] exited early; see {run_dir / "logs"}')
        path = {'p50_ms': 0.5, 'p99_ms': 1.0, 'max_ms': 2.0, 'samples': samples, 'unanswered': 0,
                'start_max_ms': 2.0, 'steady_max_ms': 1.0, 'mean_ms': 0.6}
        return {'real_time_factor': 10.0, 'measurement_to_estimate': path, 'measurement_to_control': path}

    monkeypatch.setattr(latency_bench, 'run_case', fake_run_case)
    monkeypatch.setattr(latency_bench, 'mkdtemp', lambda prefix: str(tmp_path / 'runs'))
    out = tmp_path / 'latency.json'
    history = tmp_path / 'latency_runs'
    assert latency_bench.main(['--samples', '40', '--cases', '10x', '10x_batch', '10x', '--out', str(out),
                               '--history', str(history)]) == 1
    report = json.loads(out.read_text())
    (kept,) = history.glob('latency_*.json')  # the same report, named by its start
    assert json.loads(kept.read_text()) == report and kept.name == f"latency_{report['started_utc']}.json"
    assert sorted(report['cases']) == ['10x', '10x_02']
    assert list(report['failed_cases']) == ['01_10x_batch']
    assert len(set(folders)) == 3
    assert (folders[1] / 'logs').is_dir()  # kept: the error message points there
    assert 'kept in' in capsys.readouterr().err


def test_a_short_realtime_run_answers_a_measurement_within_the_step_and_waiting_takes_one(tmp_path, capsys):
    """At 1x (100 ms of wall time per step): a loaded machine still answers every step; the
    10x cases of a 60-sample run last under a second, shorter than discovery under load. With
    provisional steps (the default) the estimate answers z_k at once (a few ms, half a step at
    most even under load); waiting for the plant's applied_control report takes one step."""
    pytest.importorskip('rclpy')
    out = tmp_path / 'latency.json'
    assert latency_bench.main(['--samples', '40', '--cases', '1x', '1x_wait', '--estimator', 'ekf',
                               '--out', str(out)]) == 0
    assert 'measurement_to_control' in capsys.readouterr().out
    cases = json.loads(out.read_text())['cases']
    for name, case in cases.items():
        assert case['real_time_factor'] == 1.0
        for path in ('measurement_to_estimate', 'measurement_to_control'):
            figures = case[path]
            assert figures['samples'] + figures['unanswered'] == 40
            assert figures['samples'] >= 30, (name, figures)  # the first ones may precede discovery
            assert 0 < figures['p50_ms'] <= figures['p99_ms'] <= figures['max_ms'] < 1000
            assert math.isfinite(figures['steady_max_ms'])
        # the control answers the estimate: it cannot arrive much sooner. Not exactly: the probe
        # stamps arrival in its callbacks, and when both wait in its executor the control's may run
        # first (a CI run: control p50 1.0799 ms, estimate 1.0877 ms), so a tenth of a millisecond
        assert case['measurement_to_control']['p50_ms'] >= case['measurement_to_estimate']['p50_ms'] - 0.1
    print({name: case['measurement_to_estimate']['p50_ms'] for name, case in cases.items()})
    assert cases['1x']['measurement_to_estimate']['p50_ms'] < 50.0
    assert cases['1x']['measurement_to_control']['p50_ms'] < 50.0
    assert cases['1x_wait']['measurement_to_estimate']['p50_ms'] > 90.0
    # the nodes' own counters, from the bag: with provisional steps no step waits for the plant's
    # report but the first and the last (the controller's u_k was there: the chain was matched
    # before the start, decisions.md 41); waiting for it, every step does
    assert cases['1x']['pipeline_counts']['steps_waiting_for_report'] <= 2, cases['1x']['pipeline_counts']
    assert cases['1x_wait']['pipeline_counts']['steps_waiting_for_report'] >= 40
    assert cases['1x']['pipeline_counts']['lqr_controller.controls_published'] >= 40


def test_the_cpu_wake_latency_switch_holds_the_kernels_request_open_and_reports_what_it_cannot(
        monkeypatch, tmp_path, capsys):
    """SNN_CPU_WAKE_LATENCY_US writes the microseconds as the s32 the kernel reads and keeps the
    file open (closing it withdraws the request); a bad value or a device it cannot open is said
    on stderr and the node goes on."""
    import struct

    pytest.importorskip('rclpy')
    from scenario_nodes import runtime
    device = tmp_path / 'cpu_dma_latency'
    device.write_bytes(b'')
    monkeypatch.setattr(runtime, 'CPU_LATENCY_DEVICE', str(device))
    monkeypatch.setattr(runtime, '_held_requests', [])
    monkeypatch.setenv('SNN_GC', 'none')  # this test's process: the collector left alone
    monkeypatch.setenv('SNN_CPU_WAKE_LATENCY_US', '0')
    runtime.tune_process([])
    assert struct.unpack('i', device.read_bytes()) == (0,)
    assert len(runtime._held_requests) == 1
    os.fstat(runtime._held_requests[0])  # still open
    assert capsys.readouterr().err == ''
    for value, said in (('fast', 'ignored'), ('-5', 'ignored')):
        monkeypatch.setenv('SNN_CPU_WAKE_LATENCY_US', value)
        runtime.tune_process([])
        assert said in capsys.readouterr().err
    monkeypatch.setattr(runtime, 'CPU_LATENCY_DEVICE', str(tmp_path / 'absent' / 'device'))
    monkeypatch.setenv('SNN_CPU_WAKE_LATENCY_US', '10')
    runtime.tune_process([])
    assert 'not held, cannot open' in capsys.readouterr().err
    assert len(runtime._held_requests) == 1
    os.close(runtime._held_requests[0])


def test_the_nodes_tuning_switches_freeze_gc_set_the_log_level_and_ignore_a_bad_one(monkeypatch, capsys):
    import gc

    from scenario_nodes.runtime import tune_process

    class Logger:
        level = None

        def set_level(self, level):
            self.level = level

    class Node:
        logger = Logger()

        def get_logger(self):
            return self.logger

    node = Node()
    monkeypatch.setenv('SNN_GC', 'none')
    monkeypatch.setenv('SNN_LOG_LEVEL', 'loud')
    tune_process([node])
    assert node.logger.level is None and 'SNN_LOG_LEVEL' in capsys.readouterr().err
    assert gc.isenabled() and gc.get_freeze_count() == 0  # none: as Python sets it
    pytest.importorskip('rclpy')
    from rclpy.logging import LoggingSeverity
    monkeypatch.setenv('SNN_LOG_LEVEL', 'warn')
    monkeypatch.setenv('SNN_GC', 'freeze')
    try:
        tune_process([node])
        assert node.logger.level == LoggingSeverity.WARN
        assert not gc.isenabled() and gc.get_freeze_count() > 0
        gc.unfreeze()
        gc.enable()
        # the default (also for a bad value, said): the start-up's objects frozen, collection on
        for value, said in ((None, ''), ('later', 'SNN_GC')):
            if value is None:
                monkeypatch.delenv('SNN_GC')
            else:
                monkeypatch.setenv('SNN_GC', value)
            tune_process([node])
            assert gc.isenabled() and gc.get_freeze_count() > 0, value
            assert said in capsys.readouterr().err
            gc.unfreeze()
    finally:
        gc.unfreeze()
        gc.enable()



def test_snn_demo_passes_the_cpu_wake_latency_to_every_node_and_refuses_a_negative_one(tmp_path, monkeypatch):
    """--cpu-wake-latency-us reaches the nodes through the environment they inherit."""
    from snn_tools.run import demo
    seen = {}

    def run_pipeline(*args, **kwargs):
        seen['value'] = os.environ.get('SNN_CPU_WAKE_LATENCY_US')
        raise RuntimeError('stopped here')

    monkeypatch.setattr(demo, 'run_pipeline', run_pipeline)
    monkeypatch.setenv('SNN_CPU_WAKE_LATENCY_US', '')  # restored after the test (main sets it)
    with pytest.raises(SystemExit):
        demo.main(['--cpu-wake-latency-us', '-1', '--runs-dir', str(tmp_path)])
    assert 'value' not in seen
    assert demo.main(['--cpu-wake-latency-us', '0', '--runs-dir', str(tmp_path), '--name', 'awake']) == 1
    assert seen['value'] == '0'


def test_the_probe_is_counted_in_every_nodes_hold(tmp_path):
    """The probe subscribes to measurement, estimate and control: each publisher of the loop waits
    for one more subscription (listeners), so the probe cannot stand in for a node of the loop."""
    from snn_tools.paths import config_file
    from snn_tools.run.demo import Pipeline, pipeline_env
    counts = {}
    for listeners in (0, 1):
        overrides = {}
        Pipeline(tmp_path, config_file(), overrides, pipeline_env(),
                 listeners=dict.fromkeys(('measurement', 'estimate', 'control'), listeners))
        counts[listeners] = (overrides['position_sensor']['min_measurement_subscribers'],
                             overrides['estimator']['min_estimate_subscribers'],
                             overrides['lqr_controller']['min_control_subscribers'])
    assert counts == {0: (3, 2, 3), 1: (4, 3, 4)}
