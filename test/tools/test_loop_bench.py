"""snn_loop_bench: the CPU window arithmetic against hand-computed values, and one short run
through the real pipeline (figures present and consistent; speed itself is not asserted)."""

import functools
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip('rclpy')

from snn_tools.bench import loop as loop_bench  # noqa: E402
from snn_tools.bench.loop import CpuSampler, process_cpu_seconds  # noqa: E402


class _Pipeline:
    processes = {}


@functools.cache
def _batch_allowed() -> bool:
    """Whether this machine lets a process switch itself to SCHED_BATCH (some containers
    refuse; the pipeline then falls back to the normal policy and says so)."""
    probe = 'import os; os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))'
    return hasattr(os, 'SCHED_BATCH') and subprocess.run([sys.executable, '-c', probe]).returncode == 0


def _sampler(samples):
    sampler = CpuSampler(_Pipeline())
    sampler.samples = samples
    return sampler


def test_cpu_per_step_uses_only_the_middle_of_the_stepping_interval():
    # stepping from t = 10 to 20 s (1000 steps, 100 per second); the estimator burns 0.2 s of
    # CPU per wall second while stepping, 5 s at start-up (outside the window)
    samples = [(t, {'estimator': 5.0 * (t >= 1) + 0.2 * max(0.0, min(t, 20) - 10)})
               for t in [0.5 * k for k in range(0, 45)]]
    cpu = _sampler(samples).cpu_per_step(stepping_end=20.0, stepping_wall_s=10.0, steps=1000)
    # window 12..18 s: 1.2 s of CPU over 600 steps = 2 ms per step
    assert cpu == {'estimator': pytest.approx(2.0)}


def test_cpu_per_step_is_none_without_enough_samples_or_an_end():
    samples = [(10.0, {'estimator': 1.0}), (20.0, {'estimator': 2.0})]
    assert _sampler(samples).cpu_per_step(20.0, 10.0, 1000) is None  # 2 samples, none inside
    more = [(10.0 + 0.5 * k, {'estimator': 1.0 + 0.1 * k}) for k in range(21)]
    assert _sampler(more).cpu_per_step(20.0, 10.0, 1000) is not None
    assert _sampler(more).cpu_per_step(0.0, 10.0, 1000) is None  # the plant did not finish
    assert _sampler(more).cpu_per_step(20.0, 0.0, 1000) is None


def test_process_cpu_seconds_reads_a_live_process_and_none_for_a_gone_one():
    if not os.path.exists('/proc/self/stat'):
        pytest.skip('no /proc')
    before = process_cpu_seconds(os.getpid())
    sum(i * i for i in range(2_000_000))  # burn some CPU
    assert process_cpu_seconds(os.getpid()) > before
    finished = subprocess.run([sys.executable, '-c', 'import os; print(os.getpid())'],
                              capture_output=True, text=True, check=True)
    assert process_cpu_seconds(int(finished.stdout)) is None


def test_bad_arguments_are_refused():
    with pytest.raises(SystemExit) as error:
        loop_bench.main(['--runs', '0'])
    assert error.value.code == 2


@pytest.mark.slow
def test_a_short_run_reports_the_factor_and_every_node_s_cpu(tmp_path, capsys):
    out = tmp_path / 'loop.json'
    assert loop_bench.main(['--runs', '1', '--duration', '60', '--estimator', 'ekf', '--out', str(out),
                            '--rtt-samples', '200']) == 0
    printed = capsys.readouterr().out
    assert 'run 1: real-time factor' in printed and 'median' in printed
    figures = json.loads(out.read_text())
    assert figures['cpu_affinity'] == 'auto'  # the default
    run = figures['runs'][0]
    assert run['scheduling'] == ('batch' if _batch_allowed() else 'normal')  # the default, if allowed
    assert run['steps'] == 600 and run['real_time_factor'] > 0
    assert math.isfinite(run['final_range_m'])
    if os.path.exists('/proc/self/stat'):
        cpu = run['cpu_ms_per_step']
        assert set(cpu) == {'recorder', 'lqr_controller', 'estimator', 'position_sensor', 'cw_plant'}
        # every node works each step; no node can use more than all CPUs for the whole step
        wall_ms_per_step = 1e3 * run['wall_time_s'] / run['steps']
        assert all(0 < ms < 1.5 * os.cpu_count() * wall_ms_per_step for ms in cpu.values())
    # the floor comes from the round trip measured in the same invocation
    rtt_us = figures['round_trip']['median_us']
    assert rtt_us > 0
    assert run['fraction_of_floor'] == pytest.approx(run['real_time_factor'] * rtt_us * 1e-6 / 0.1)
    assert figures['fraction_of_floor'] == pytest.approx(run['fraction_of_floor'])
    # every step sends /clock to the four nodes that use simulated time and the recorder
    deliveries = run['deliveries_per_step']
    assert deliveries['by_topic']['clock'] == run['subscribers']['clock'] >= 4
    assert deliveries['by_topic']['truth'] == pytest.approx(2.0, abs=0.05)  # sensor and recorder
    assert deliveries['by_topic']['applied_control'] == run['subscribers']['applied_control'] == 1  # estimator
    assert deliveries['by_topic']['measurement'] == pytest.approx(3.0, abs=0.05)  # estimator, controller, recorder
    assert run['critical_path_hops'] == 2  # provisional steps: the plant's report is off the path


def test_cpu_plan_gives_the_estimator_and_controller_a_cpu_of_their_own():
    from snn_tools.run.demo import cpu_plan
    plan = cpu_plan({0, 1})
    assert plan['estimator'] == plan['lqr_controller'] == {1}
    assert plan['cw_plant'] == plan['position_sensor'] == plan['recorder'] == {0}
    basilisk = cpu_plan({0, 1}, plant='basilisk')  # a heavier plant: the recorder takes either CPU
    assert basilisk['basilisk_plant'] == {0} and basilisk['recorder'] == {0, 1} and basilisk['estimator'] == {1}
    four = cpu_plan({4, 5, 6, 7})
    assert four['estimator'] == {7} and four['recorder'] == {4, 5, 6}
    assert cpu_plan({3}) == {}  # one CPU: nothing to separate


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, 'sched_getaffinity') or len(os.sched_getaffinity(0)) < 2
                    or not _batch_allowed(),
                    reason='needs CPU affinity, SCHED_BATCH allowed and two CPUs')
def test_pipeline_nodes_start_on_their_planned_cpus_and_policy_unless_told_not_to(tmp_path):
    from snn_tools.paths import config_file
    from snn_tools.run.demo import Pipeline, cpu_plan, pipeline_env
    everything = os.sched_getaffinity(0)
    own_nice = os.getpriority(os.PRIO_PROCESS, 0)
    for pin, scheduling, plant in ((True, 'batch', 'basilisk'), (False, 'normal', 'cw')):
        expected = cpu_plan(plant=plant) if pin else {}
        pipeline = Pipeline(tmp_path / str(pin), config_file(), {}, pipeline_env(), pin_cpus=pin,
                            scheduling=scheduling, plant=plant)
        pipeline.start()
        try:
            assert not pin or set(pipeline.processes) <= set(expected)  # every node planned
            for name, process in pipeline.processes.items():
                assert os.sched_getaffinity(process.pid) == expected.get(name, everything), name
                # 'normal' is set, not inherited: right even if pytest itself runs under batch
                policy = os.SCHED_BATCH if scheduling == 'batch' else os.SCHED_OTHER
                assert os.sched_getscheduler(process.pid) == policy, (name, scheduling)
                nice = min(own_nice + 10, 19) if name == 'recorder' else own_nice
                assert os.getpriority(os.PRIO_PROCESS, process.pid) == nice, name
            assert pipeline.scheduling == scheduling and pipeline.refused_batch == []
        finally:
            pipeline.stop_all()


def test_a_refused_sched_batch_is_reported_and_recorded_as_normal(tmp_path, monkeypatch, capsys):
    """Where the kernel refuses SCHED_BATCH (the child then stays SCHED_OTHER), the pipeline
    says so once and reports the policy the nodes really run under. No node process is started:
    the pipeline reads the policy of what it started (running_policy), here SCHED_OTHER."""
    from types import SimpleNamespace

    from snn_tools.paths import config_file
    from snn_tools.run import demo
    monkeypatch.setattr(demo.subprocess, 'Popen', lambda *args, **kwargs: SimpleNamespace(pid=0))
    monkeypatch.setattr(demo, 'running_policy', lambda pid: os.SCHED_OTHER)
    pipeline = demo.Pipeline(tmp_path, config_file(), {}, demo.pipeline_env(), pin_cpus=False,
                             scheduling='batch')
    pipeline.start()
    assert pipeline.refused_batch == [node.name for node in pipeline.nodes]
    assert pipeline.scheduling == 'normal'
    assert capsys.readouterr().err.count('refused SCHED_BATCH') == 1


def test_pipeline_refuses_an_unknown_scheduling_policy(tmp_path):
    from snn_tools.paths import config_file
    from snn_tools.run.demo import Pipeline, pipeline_env
    with pytest.raises(ValueError, match='scheduling'):
        Pipeline(tmp_path, config_file(), {}, pipeline_env(), scheduling='fifo')


@pytest.mark.slow
def test_snn_demo_prints_and_writes_the_summary_with_how_the_nodes_ran(tmp_path):
    """The demo command itself (what `make demo` runs), shortened: summary.json carries the
    issue's keys and the process set-up the real-time factor depends on."""
    done = subprocess.run([sys.executable, '-m', 'snn_tools.run.demo', '--duration', '30',
                           '--estimator', 'ekf', '--runs-dir', str(tmp_path), '--name', 'short',
                           '--no-report', '--scheduling', 'normal', '--cpu-affinity', 'off'],
                          capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-2000:]
    assert 'real-time factor' in done.stdout and 'final range' in done.stdout
    summary = json.loads((tmp_path / 'short' / 'summary.json').read_text())
    assert {'estimator', 'sim_time_s', 'wall_time_s', 'real_time_factor', 'steps', 'rmse_last_60s',
            'final_range_m', 'spikes_total', 'spike_fraction', 'control_timeouts',
            'measurements_rejected'} <= set(summary)
    assert summary['estimator'] == 'ekf' and summary['steps'] == 300
    assert summary['scheduling'] == 'normal' and summary['cpu_affinity'] == 'off'


def test_the_fraction_of_the_floor_is_the_factor_over_dt_per_round_trip():
    from snn_tools.bench.round_trip import floor_factor
    assert floor_factor(0.1, 160.0) == pytest.approx(625.0)  # 0.1 s / 160 us
    assert loop_bench.fraction_of_floor(93.75, 0.1, 160.0) == pytest.approx(0.15)
    with pytest.raises(ValueError):
        floor_factor(0.1, 0.0)


def test_deliveries_per_step_are_messages_times_matched_subscriptions():
    published = {'truth': 1.0, 'clock': 1.0, 'estimate': 1.0, 'diagnostics': 0.1}
    subscribers = {'truth': 2, 'clock': 4, 'estimate': 2, 'diagnostics': 1}
    deliveries = loop_bench.deliveries_per_step(published, subscribers)
    assert deliveries['by_topic'] == {'truth': 2.0, 'clock': 4.0, 'estimate': 2.0, 'diagnostics': 0.1}
    assert deliveries['total'] == pytest.approx(8.1)


def test_wakeups_per_step_use_the_same_window_and_read_this_process():
    if not os.path.exists('/proc/self/task'):
        pytest.skip('no /proc')
    sampler = _sampler([])
    # 20 switches per wall second while stepping 100 steps per second: 0.2 per step
    sampler.switches = [(10.0 + 0.5 * k, {'estimator': 100 + 10 * k}) for k in range(21)]
    assert sampler.wakeups_per_step(20.0, 10.0, 1000) == {'estimator': pytest.approx(0.2)}
    assert loop_bench.voluntary_switches(os.getpid()) > 0


@pytest.mark.slow
def test_the_round_trip_pair_returns_a_positive_rtt():
    from snn_tools.bench.round_trip import measure_round_trip
    figures = measure_round_trip(samples=200)
    assert figures['samples'] == 200
    assert 0 < figures['median_us'] <= figures['p99_us'] <= figures['max_us'] < 1e6


@pytest.mark.slow
def test_single_process_mode_gives_the_multi_process_results(tmp_path):
    """All nodes in one process and one executor: the lockstep run is the same run, estimate by
    estimate (and hence the same as the offline core, which the multi-process run is tested
    against)."""
    from snn_tools.bags.data import read_bag, summarize
    from snn_tools.run.demo import run_pipeline
    runs = {}
    for single in (False, True):
        result = run_pipeline(tmp_path / str(single), 'snn_emsif', 'lockstep', duration=20.0,
                              single_process=single)
        runs[single] = read_bag(result['bag'])
    multi, single = runs[False], runs[True]
    assert summarize(single)['steps'] == summarize(multi)['steps'] == 200
    assert single.estimate.shape == multi.estimate.shape and single.estimate.size
    np.testing.assert_allclose(single.estimate_t, multi.estimate_t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(single.estimate, multi.estimate, rtol=0, atol=1e-9)
    np.testing.assert_allclose(single.truth, multi.truth, rtol=0, atol=1e-9)
    assert summarize(single)['final_range_m'] == pytest.approx(summarize(multi)['final_range_m'], abs=1e-9)


@pytest.mark.slow
def test_the_single_process_demo_starts_flies_and_stops_eight_times_without_a_crash(tmp_path):
    """Issue 25: the single process crashed with SIGSEGV at shutdown in 2 of 6 runs (the
    recorder's drain spun rclpy's EventsExecutor after the estimator's liveliness event was
    queued and its node removed; snn_tools.run.single_process.finish). Short runs, as the crash was in
    the teardown: every one exits 0 with the whole run in its bag."""
    from snn_tools.bags.data import read_bag, summarize
    from snn_tools.run.demo import run_pipeline
    for k in range(8):
        result = run_pipeline(tmp_path / str(k), 'snn_ekf', 'lockstep', duration=5.0, single_process=True)
        assert result['exit_codes'] == {'cw_plant': 0}, (k, result['exit_codes'])
        summary = summarize(read_bag(result['bag']))
        assert summary['steps'] == 50 and summary['recording_complete'], (k, summary['messages'])
