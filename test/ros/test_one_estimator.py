"""Exactly one active estimator: a standby takes over only when the active one is gone, two
active ones settle on one by name, and the scenario does not start before one is active."""

import time

import numpy as np
import pytest

pytest.importorskip('rclpy')

from ros_helpers import Probe, make, ros_context, spin_until  # noqa: E402

from scenario_nodes import qos  # noqa: E402
from scenario_nodes.controller_node import ControllerNode  # noqa: E402
from scenario_nodes.conversions import control_to_accel, measurement_to_point, stamp_to_ns  # noqa: E402
from scenario_nodes.estimator_node import EstimatorNode  # noqa: E402
from scenario_nodes.plant_node import PlantNode  # noqa: E402
from scenario_nodes.sensor_node import SensorNode  # noqa: E402
from snn_estimator.runners.filter_runner import Standby  # noqa: E402

DT = 100_000_000
X0 = np.array([70.0, 30.0, -5.0])
QUIET = {'history_wait': 0.0, 'initial_state_dispersion': False, 'nis_window': 0, 'neuron_count': 20,
         'filter_type': 'ekf'}


class Listener(Probe):
    """A probe whose own publishers stay off `estimate` (it feeds measurements and controls)."""

    def __init__(self, context, executor, nodes):
        super().__init__(context, executor, nodes)
        self.node.destroy_publisher(self.publishers.pop(qos.ESTIMATE))

    def matched(self, count=2):
        """``count`` estimators' input subscriptions matched ours (the probe's own listener
        is one more)."""
        return all(self.publishers[topic].get_subscription_count() >= 1 + count
                   for topic in (qos.MEASUREMENT, qos.CONTROL))

    def estimate_stamps(self):
        return [stamp_to_ns(m.header.stamp) for m in self.received[qos.ESTIMATE]]

    def feed(self, spin, stamps):
        """z_k and u_k for each stamp, sent again until the estimate of the next step is here
        (best effort: a sample sent before a new subscription matched is lost)."""
        for stamp in stamps:
            for _ in range(20):
                self.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), stamp, 'lvlh'))
                self.publish(qos.CONTROL, control_to_accel(np.zeros(3), stamp, 'lvlh'))
                if spin(lambda: stamp + DT in self.estimate_stamps(), 0.5):  # noqa: B023 (called at once)
                    break


class Estimators:
    """Estimators built and removed in the test's context. They share one DDS participant,
    where a writer counts as alive only while it publishes (between processes the middleware
    asserts it): the liveliness lease is long enough here for the test's pauses."""

    def __init__(self, context, executor):
        self.context, self.executor, self.nodes = context, executor, []

    def make(self, name, **changes):
        return make(EstimatorNode, self.context, self.executor, self.nodes, name, start=False, **QUIET,
                    standby_timeout=5.0, cli_args=['--ros-args', '-r', f'__node:={name}'], **changes)

    def remove(self, node):
        self.executor.remove_node(node)
        self.nodes.remove(node)
        node.destroy_node()

    def spin(self, predicate, timeout=10.0):
        return spin_until(self.executor, predicate, timeout)

    def close(self):
        for node in list(self.nodes):
            self.remove(node)


@pytest.fixture
def rig():
    with ros_context() as (context, executor, nodes):
        estimators = Estimators(context, executor)
        try:
            yield Listener(context, executor, nodes), estimators
        finally:
            estimators.close()


def test_the_standby_rule_takes_over_only_after_seeing_an_active_one_go_and_yields_by_name():
    rule = Standby()
    rule.update(0, [])
    assert not rule.takes_over(started=True)  # nobody seen yet: not "gone"
    rule.update(1, ['estimator'])
    assert not rule.takes_over(True) and rule.yields('estimator_standby') and not rule.yields('a_first')
    rule.update(0, ['estimator'])  # killed: still in the graph, not alive
    assert rule.takes_over(True) and not rule.takes_over(False) and not rule.yields('estimator_standby')


def test_a_standby_and_an_active_estimator_started_together_never_publish_together_and_the_standby_takes_over(rig):
    """20 times: an active and a standby estimator built and started back to back (in either
    order); every estimate stamp is published once. Then the active one goes and the standby
    takes over within its liveliness lease."""
    probe, processes = rig
    spin = processes.spin
    for trial in range(20):
        base = trial * 1000 * DT
        order = [('estimator', False), ('estimator_standby', True)][::1 if trial % 2 else -1]
        built = {name: processes.make(name, standby=standby) for name, standby in order}
        for name, _ in order:
            built[name].start()
        assert spin(probe.matched)
        probe.feed(spin, [base + k * DT for k in range(4)])
        spin(lambda: False, 0.3)  # a standby that would take over by the age of estimates does
        active, standby = built['estimator'].values(), built['estimator_standby'].values()
        assert active['active'] and active['estimates_published'] >= 4, (trial, active)
        assert not standby['active'] and standby['estimates_published'] == 0, (trial, standby)
        if trial < 19:
            for node in built.values():
                processes.remove(node)
            assert spin(lambda: not probe.matched(1))  # gone from the graph before the next pair
    processes.remove(built['estimator'])
    gone = time.monotonic()
    standby = built['estimator_standby']
    assert spin(lambda: standby.active, timeout=5.0)
    print(f'standby active {time.monotonic() - gone:.3f} s after the active estimator went')
    probe.feed(spin, [base + 4 * DT])
    assert built['estimator_standby'].values()['estimates_published'] >= 1


def test_of_two_active_estimators_the_one_named_last_yields_and_stands_by(rig):
    probe, processes = rig
    spin = processes.spin
    first, second = processes.make('estimator_a'), processes.make('estimator_b')
    first.start()
    second.start()
    assert spin(probe.matched)
    probe.feed(spin, [k * DT for k in range(3)])  # both publish (in one participant, alive once they did)
    assert spin(lambda: not second.active, timeout=5.0)
    assert first.active and second.values()['yields'] == 1 and 'yields' not in first.values()
    before = second.values()['estimates_published']
    probe.feed(spin, [k * DT for k in range(3, 6)])
    assert second.values()['estimates_published'] == before and first.active
    processes.remove(first)
    assert spin(lambda: second.active, timeout=5.0)  # the yielded one stood by


def test_configure_alone_does_not_start_the_plant_activate_does():
    with ros_context() as (context, executor, nodes):
        plant = make(PlantNode, context, executor, nodes, 'cw_plant', duration=1.0, control_timeout=30.0)
        make(ControllerNode, context, executor, nodes, 'lqr_controller')
        make(SensorNode, context, executor, nodes, 'position_sensor')
        estimator = make(EstimatorNode, context, executor, nodes, 'estimator', autostart=False, **QUIET)
        estimator.trigger_configure()
        spin_until(executor, lambda: False, timeout=1.5)
        assert plant.values()['truth_published'] == 0  # configured, inactive: not an estimator yet
        estimator.trigger_activate()
        assert spin_until(executor, lambda: plant.values()['done'], timeout=30.0)


@pytest.mark.slow
def test_a_standby_and_an_active_estimator_started_as_processes_at_once_never_publish_together(rig, tmp_path):
    """As users start them (`ros2 run` twice, each its own process and DDS participant, where
    the middleware asserts liveliness): 8 times (SNN_STANDBY_TRIALS: more, to hunt a race) an
    active and a standby estimator launched at the same instant (in either order); every
    estimate stamp comes once, and only the active one publishes (the only diagnostics are the
    active one's). The in-process test above runs 20 such starts."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path
    probe, processes = rig
    spin = processes.spin
    script = str(Path(sys.executable).parent / 'estimator')
    settings = [a for name, value in QUIET.items() for a in ('-p', f'{name}:={value}')] + [
        '-p', 'diagnostics_period:=0.0', '-p', 'initial_state:=[70.0, 30.0, -5.0, 0.0, 0.0, 0.0]']
    for trial in range(int(os.environ.get('SNN_STANDBY_TRIALS', '8'))):
        base = trial * 1000 * DT
        order = [('estimator', 'false'), ('estimator_standby', 'true')][::1 if trial % 2 else -1]
        logs = [open(tmp_path / f'{name}_{trial}.log', 'w') for name, _ in order]
        started = [subprocess.Popen([script, '--ros-args', '-r', f'__node:={name}', '-p', f'standby:={standby}',
                                     *settings], stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ))
                   for (name, standby), log in zip(order, logs)]
        try:
            assert spin(probe.matched, timeout=60.0), trial
            spin(lambda: False, 1.0)  # DDS matches one end of a pair before the other
            for k in range(8):  # each input once: an estimate stamp that comes twice had two publishers
                probe.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), base + k * DT, 'lvlh'))
                probe.publish(qos.CONTROL, control_to_accel(np.zeros(3), base + k * DT, 'lvlh'))
                spin(lambda: False, 0.1)
            spin(lambda: False, 0.5)  # a standby that took over by the age of estimates would publish now
            stamps = [s for s in probe.estimate_stamps() if base <= s < base + 1000 * DT]
            assert len(stamps) == len(set(stamps)) and len(stamps) >= 4, (trial, sorted(stamps))
            # diagnostics come from the active estimator only (an inactive one publishes nothing)
            assert spin(lambda: probe.diagnostics('estimator').get('active') == 'True'), trial
            standby_says = {kv.value for m in probe.received[qos.DIAGNOSTICS] for status in m.status
                            if status.name == 'estimator' for kv in status.values if kv.key == 'standby'}
            assert standby_says == {'False'}, (trial, standby_says)
        finally:
            for process in started:
                process.send_signal(signal.SIGINT)
            for process, log in zip(started, logs):
                try:
                    process.wait(15)
                except subprocess.TimeoutExpired:
                    process.kill()
                log.close()
        assert spin(lambda: not probe.matched(1), timeout=30.0)  # both gone before the next pair
        probe.received[qos.DIAGNOSTICS].clear()
