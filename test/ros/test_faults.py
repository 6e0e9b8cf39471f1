"""Faults over the real multi-process loop: estimator hot swap and neuron loss at runtime."""

import signal
import time

import numpy as np
import pytest

pytest.importorskip('rclpy')

import rclpy  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402

from scenario_nodes import qos, registry  # noqa: E402
from scenario_nodes.conversions import stamp_to_ns  # noqa: E402
from snn_estimator import rendezvous_scenario, simulate  # noqa: E402
from snn_estimator.catalog import DEFAULT_FILTER  # noqa: E402
from snn_tools.bags.data import matched_errors, read_bag, summarize  # noqa: E402
from snn_tools.paths import config_file  # noqa: E402
from snn_tools.run.demo import Pipeline, pipeline_env  # noqa: E402

pytestmark = pytest.mark.slow
ESTIMATOR_MODULE = registry.node('estimator').module


class Monitor:
    """A node in the test process that follows /clock and sets parameters of the pipeline."""

    def __init__(self):
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = Node('fault_monitor', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.now = 0.0
        self.newest_estimate = 0.0
        self.node.create_subscription(Clock, '/clock', self._on_clock, qos.CLOCK_QOS)
        # the newest estimate from history: one published before this reader matched a new estimator counts too
        self.node.create_subscription(Odometry, qos.history_topic(qos.ESTIMATE), self._on_estimate, qos.HISTORY_QOS)

    def _on_clock(self, msg):
        self.now = stamp_to_ns(msg.clock) * 1e-9

    def _on_estimate(self, msg):
        self.newest_estimate = max(self.newest_estimate, stamp_to_ns(msg.header.stamp) * 1e-9)

    def wait_estimate_after(self, seconds, timeout=60.0):
        deadline = time.monotonic() + timeout
        while self.newest_estimate <= seconds:
            assert time.monotonic() < deadline, f'no estimate after {seconds} s'
            self.executor.spin_once(timeout_sec=0.05)

    def wait_clock(self, seconds, timeout=120.0):
        deadline = time.monotonic() + timeout
        while self.now < seconds:
            assert time.monotonic() < deadline, f'clock stuck at {self.now} s'
            self.executor.spin_once(timeout_sec=0.005)

    def set(self, node_name, **values):
        client = self.node.create_client(SetParameters, f'/{node_name}/set_parameters')
        deadline = time.monotonic() + 30
        while not client.service_is_ready():
            assert time.monotonic() < deadline
            self.executor.spin_once(timeout_sec=0.05)
        request = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg()
                                                    for k, v in values.items()])
        # setting the same values again is harmless: resent every 2 s, as a response the
        # server writes before it has matched our reader is lost
        while True:
            future = client.call_async(request)
            answer_by = time.monotonic() + 2.0
            while not future.done() and time.monotonic() < answer_by:
                self.executor.spin_once(timeout_sec=0.05)
            if future.done():
                break
            client.remove_pending_request(future)
            assert time.monotonic() < deadline, f'/{node_name}/set_parameters did not answer'
        results = future.result().results
        assert all(r.successful for r in results), [r.reason for r in results]

    def close(self):
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def run_with(tmp_path, name, overrides, during):
    """Run the 360 s lockstep loop, calling ``during(pipeline, monitor)``; returns the bag data."""
    run_dir = tmp_path / name
    run_dir.mkdir()
    overrides = {**overrides, 'recorder': {'output': str(run_dir / 'bag')}}
    overrides.setdefault('cw_plant', {}).update({'exit_when_done': True, 'control_timeout': 0.2})
    pipeline = Pipeline(run_dir, config_file(), overrides, pipeline_env())
    monitor = Monitor()
    try:
        pipeline.start()
        during(pipeline, monitor)
        plant = pipeline.processes['cw_plant']
        deadline = time.monotonic() + 240
        while plant.poll() is None:
            assert time.monotonic() < deadline, 'the run did not finish'
            monitor.executor.spin_once(timeout_sec=0.05)
        time.sleep(0.3)
    finally:
        monitor.close()
        pipeline.stop_all()
    return read_bag(run_dir / 'bag'), run_dir


def test_estimator_hot_swap_safe_mode_and_recovery(tmp_path):
    """snn_emsif is killed at t ~ 100 s; the controller holds zero thrust; snn_ekf starts 10
    simulated seconds later (the plant paused while its process comes up), starts from a
    least-squares fit of the sensor's history, and the loop converges."""
    def pause(monitor):
        monitor.set('cw_plant', paused=True)
        for _ in range(10):
            monitor.executor.spin_once(timeout_sec=0.05)
        return monitor.now

    def during(pipeline, monitor):
        # the plant is held while the estimator is killed, so that the loop then really flies
        # 10 simulated seconds without one, however late the monitor sees the clock
        monitor.wait_clock(100.0)
        killed_at = pause(monitor)
        pipeline.processes['estimator'].send_signal(signal.SIGKILL)
        pipeline.processes['estimator'].wait(10)
        monitor.set('cw_plant', paused=False)
        monitor.wait_clock(killed_at + 10.0)
        paused_at = pause(monitor)
        pipeline.start_node('estimator', ESTIMATOR_MODULE, {'filter_type': 'snn_ekf'}, 'estimator_swap')
        monitor.wait_estimate_after(paused_at)  # the new estimator is live
        monitor.set('cw_plant', paused=False)

    data, run_dir = run_with(tmp_path, 'swap', {}, during)
    summary = summarize(data)
    controller = data.last_diagnostics('lqr_controller')
    estimator = data.last_diagnostics('estimator')
    swap_log = (run_dir / 'logs' / 'estimator_swap.log').read_text()
    print(f"hot swap: final range {summary['final_range_m']:.4f} m, safe-mode steps "
          f"{controller.get('safe_mode_steps')}, control timeouts {summary['control_timeouts']}")
    assert summary['steps'] == 3600
    assert summary['final_range_m'] < 0.5
    assert int(controller['safe_mode_steps']) > 0
    # safe mode ended once estimates came back (at the very end it may be on again: the plant
    # is done, so the clock stops, which the controller reports as a stopped clock)
    assert any(values['safe_mode'] == 'False' for stamp, values in data.diagnostics['lqr_controller']
               if 150.0 < stamp < 350.0)
    # the killed process took its estimate history with it: the new one fits the sensor history
    assert estimator['filter'] == 'snn_ekf'
    assert 'started from a least-squares fit of' in swap_log
    for array in (data.truth, data.estimate, data.control, data.estimate_variance):
        assert np.all(np.isfinite(array))
    # after the restart the estimate tracks the truth (not merely stays near the target): 3 sigma
    # of the sensor (0.1 m) in position and a few cm/s in velocity, at every stamp after 150 s
    times, errors = matched_errors(data)
    after = times > 150.0
    assert after.sum() > 1000
    assert np.abs(errors[after, :3]).max() < 0.3 and np.abs(errors[after, 3:]).max() < 0.05


def test_a_hot_standby_takes_over_when_the_active_estimator_dies(tmp_path):
    """A second estimator runs on the same inputs, inactive (standby); the active one is killed
    at ~100 s; the standby activates itself and the loop goes on with (almost) no safe mode,
    where kill-and-restart (the test above) flies ~100 steps blind."""
    def during(pipeline, monitor):
        pipeline.start_node('estimator', ESTIMATOR_MODULE, {'standby': True}, node_name='estimator_standby')
        monitor.wait_clock(100.0)
        pipeline.processes['estimator'].send_signal(signal.SIGKILL)
        pipeline.processes['estimator'].wait(10)

    data, run_dir = run_with(tmp_path, 'standby', {}, during)
    summary = summarize(data)
    controller = data.last_diagnostics('lqr_controller')
    standby_log = (run_dir / 'logs' / 'estimator_standby.log').read_text()
    print(f"hot standby: final range {summary['final_range_m']:.4f} m, safe-mode steps "
          f"{controller.get('safe_mode_steps')}, control timeouts {summary['control_timeouts']}")
    assert summary['steps'] == 3600 and summary['final_range_m'] < 0.1
    assert int(controller['safe_mode_steps']) <= 5
    assert 'standby: no other estimator is alive' in standby_log and 'active: publishing estimates' in standby_log
    after = data.estimate_t > 101.0
    assert np.all(np.diff(data.estimate_t[after]) >= 0) and data.estimate_t[-1] >= 360.0


def test_half_the_neurons_silenced_at_100_s_over_ros(tmp_path):
    """silenced_fraction 0.5 set through the parameter service at t = 100 s; RMSE over the last
    60 s stays within 2x of the intact run (the offline run with the same seeds)."""
    def during(pipeline, monitor):
        monitor.wait_clock(100.0)
        monitor.set('estimator', silenced_fraction=0.5)

    data, _ = run_with(tmp_path, 'silenced', {'cw_plant': {'control_timeout': 1.0}}, during)
    summary = summarize(data)
    assert summary['estimator'] == DEFAULT_FILTER
    intact = simulate(rendezvous_scenario(initial_state_dispersion=True), DEFAULT_FILTER)
    damaged = np.array([summary['rmse_last_60s'][s] for s in ('x', 'y', 'z', 'vx', 'vy', 'vz')])
    ratio = damaged / intact.rmse()
    print('RMSE ratio, half the neurons silenced / intact:', np.round(ratio, 3))
    assert np.all(ratio < 2.0)
    assert summary['final_range_m'] < 0.1
    estimator = data.last_diagnostics('estimator')
    assert estimator['silenced_neurons'] == '100'
    late = data.spikes[data.estimate_t[:len(data.spikes)] > 200.0]  # well after the change
    assert (late > 0).any(axis=0).sum() <= 100  # only the survivors fire
