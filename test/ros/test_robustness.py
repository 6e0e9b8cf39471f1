"""Bad input, runtime parameters, faults: rejected, counted, reported; never a crash or a NaN.

Inputs are sent over ROS to nodes built in-process (isolated contexts); each rejection is
checked in `diagnostics` together with the next good input being processed.
"""

import numpy as np
import pytest

pytest.importorskip('rclpy')
hypothesis = pytest.importorskip('hypothesis')

from geometry_msgs.msg import AccelStamped  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from ros_helpers import Probe, make, ros_context, spin_until  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from scenario_nodes import qos  # noqa: E402
from scenario_nodes.codec import encode_point  # noqa: E402
from scenario_nodes.controller_node import ControllerNode  # noqa: E402
from scenario_nodes.conversions import (  # noqa: E402
    accel_to_control,
    control_to_accel,
    measurement_to_point,
    ns_to_stamp,
    odometry_to_state,
    stamp_to_ns,
    state_to_odometry,
)
from scenario_nodes.estimator_node import EstimatorNode  # noqa: E402
from scenario_nodes.plant_node import PlantNode  # noqa: E402
from scenario_nodes.sensor_node import SensorNode  # noqa: E402

DT = 100_000_000
#: An estimator that starts at once (no history to read) where the tests put it.
QUIET = {'history_wait': 0.0, 'initial_state_dispersion': False}
X0 = np.array([70.0, 30.0, -5.0])


class Harness(Probe):
    """A probe that can also drive /clock and call services."""

    def __init__(self, context, executor, nodes):
        super().__init__(context, executor, nodes)
        self.executor = executor
        self.clock_pub = self.node.create_publisher(Clock, '/clock', qos.CLOCK_QOS)
        self.publishers[qos.SET_STATE] = self.node.create_publisher(Odometry, qos.SET_STATE, qos.PUBLISHER_QOS)

    def clock(self, stamp_ns):
        self.clock_pub.publish(Clock(clock=ns_to_stamp(stamp_ns)))

    def call(self, service_type, name, request, timeout=10.0):
        client = self.node.create_client(service_type, name)
        assert spin_until(self.executor, client.service_is_ready, timeout)
        future = client.call_async(request)
        assert spin_until(self.executor, future.done, timeout)
        return future.result()

    def set_parameters(self, node_name, **values):
        request = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg()
                                                    for k, v in values.items()])
        return self.call(SetParameters, f'/{node_name}/set_parameters', request).results

    def estimates(self):
        return [(stamp_to_ns(m.header.stamp), odometry_to_state(m)[0]) for m in self.received[qos.ESTIMATE]]

    def wait_estimates(self, count, timeout=10.0):
        assert spin_until(self.executor, lambda: len(self.received[qos.ESTIMATE]) >= count, timeout), \
            f'{len(self.received[qos.ESTIMATE])} estimates, expected {count}'

    def wait_value(self, name, key, value, timeout=10.0):
        assert spin_until(self.executor, lambda: self.diagnostics(name).get(key) == str(value), timeout), \
            (key, self.diagnostics(name).get(key), value)


@pytest.fixture
def estimator_rig():
    """An estimator with a harness; initialised and stepped once (estimates at 0 and 0.1 s)."""
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        node = make(EstimatorNode, context, executor, nodes, 'estimator', diagnostics_period=0.0,
                    history_wait=0.0, initial_state_dispersion=False)
        assert spin_until(executor, lambda: harness.node.count_subscribers(qos.MEASUREMENT) > 0)
        harness.clock(0)
        harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), 0, 'lvlh'))
        harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), 0, 'lvlh'))
        harness.wait_estimates(2)
        yield harness, node


def step(harness, stamp_ns, count):
    """Send a good measurement and control for stamp_ns; wait for estimate number ``count``."""
    harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), stamp_ns, 'lvlh'))
    harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), stamp_ns, 'lvlh'))
    harness.wait_estimates(count)


@pytest.mark.parametrize('bad, reason', [
    (lambda: measurement_to_point(np.array([np.inf, 0, 0]), (0, 1, 2), DT, 'lvlh'), 'non_finite'),
    (lambda: measurement_to_point(X0, (0, 1, 2), DT, 'map'), 'wrong_frame'),
    (lambda: measurement_to_point(X0, (0, 1, 2), DT // 2, 'lvlh'), 'stale'),
])
def test_estimator_rejects_bad_measurements_and_goes_on(estimator_rig, bad, reason):
    harness, node = estimator_rig
    harness.publish(qos.MEASUREMENT, bad())
    harness.wait_value('estimator', f'measurements_rejected.{reason}', 1)
    step(harness, DT, 3)
    assert node.estimator.steps == 2
    assert all(np.all(np.isfinite(x)) for _, x in harness.estimates())


def test_estimator_rejects_stragglers_older_than_max_input_age(estimator_rig):
    harness, node = estimator_rig
    assert harness.set_parameters('estimator', max_input_age=0.15)[0].successful
    step(harness, DT, 3)
    step(harness, 2 * DT, 4)
    step(harness, 3 * DT, 5)  # newest measurement: 0.3 s
    harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), DT // 2, 'lvlh'))
    harness.wait_value('estimator', 'measurements_rejected.too_old', 1)
    step(harness, 4 * DT, 6)
    assert node.estimator.steps == 5


def test_an_estimator_behind_the_clock_still_takes_its_queued_measurements(estimator_rig):
    harness, node = estimator_rig
    step(harness, DT, 3)
    harness.clock(50 * DT)  # the clock ran ahead (the plant in safe mode) while inputs are queued
    assert spin_until(harness.executor, lambda: node.get_clock().now().nanoseconds == 50 * DT)
    for k in range(2, 6):
        step(harness, k * DT, k + 2)
    assert node.values()['measurements_rejected'] == 0 and node.values()['dropout_steps'] == 0


def test_a_measurement_stamped_far_ahead_of_the_clock_is_rejected_and_does_not_block_the_rest(
        estimator_rig):
    harness, node = estimator_rig
    # max_input_age 1 s + 2 steps: 1.2 s is the most a measurement may lead the clock
    harness.clock(DT)
    assert spin_until(harness.executor, lambda: node.get_clock().now().nanoseconds == DT)
    harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), 1000 * DT, 'lvlh'))
    harness.wait_value('estimator', 'measurements_rejected.future', 1)
    for k in range(1, 6):
        harness.clock(k * DT)
        step(harness, k * DT, k + 2)
    assert node.estimator.steps == 6
    values = node.values()
    assert values['measurements_rejected'] == 1 and values['dropout_steps'] == 0


@pytest.mark.parametrize('publish_spikes, spike_messages', [(True, 2), (False, 0)])
def test_estimator_counts_the_spike_messages_it_publishes_apart_from_the_estimates(publish_spikes, spike_messages):
    """The recorder's completeness check compares the bag with these counts."""
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        node = make(EstimatorNode, context, executor, nodes, 'estimator', **QUIET, publish_spikes=publish_spikes)
        assert spin_until(executor, lambda: harness.node.count_subscribers(qos.MEASUREMENT) > 0)
        harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), 0, 'lvlh'))
        harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), 0, 'lvlh'))
        harness.wait_estimates(2)
        assert spin_until(executor, lambda: len(harness.received[qos.SPIKES]) >= spike_messages)
        executor.spin_once(timeout_sec=0.2)
        assert len(harness.received[qos.SPIKES]) == spike_messages
        assert node.values()['estimates_published'] == 2
        assert node.values()['spikes_published'] == spike_messages


def _flown_with_a_differing_report(provisional):
    """An estimator that hears the plant's reports: u_1 = 0.02 m/s^2 along x is commanded, the
    plant reports it flew zero thrust (u_1 came after its tick). Returns the estimates received,
    the spike counts received and the node's values."""
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        harness.publishers[qos.APPLIED_CONTROL] = harness.node.create_publisher(
            AccelStamped, qos.APPLIED_CONTROL, qos.PUBLISHER_QOS)
        node = make(EstimatorNode, context, executor, nodes, 'estimator', **QUIET, provisional_steps=provisional)
        assert spin_until(executor, lambda: harness.node.count_subscribers(qos.APPLIED_CONTROL) > 0)
        harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), 0, 'lvlh'))
        harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), 0, 'lvlh'))
        harness.wait_estimates(2)
        harness.publish(qos.APPLIED_CONTROL, control_to_accel(np.zeros(3), 0, 'lvlh'))  # the plant reports
        assert spin_until(executor, lambda: node.values()['applied_received'] == 1)
        harness.publish(qos.CONTROL, control_to_accel(np.array([0.02, 0.0, 0.0]), DT, 'lvlh'))
        harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), DT, 'lvlh'))
        if provisional:  # answered at once, with u_1
            harness.wait_estimates(3)
        else:
            executor.spin_once(timeout_sec=0.3)
            assert len(harness.received[qos.ESTIMATE]) == 2  # waits for the report
        harness.publish(qos.APPLIED_CONTROL, control_to_accel(np.zeros(3), DT, 'lvlh'))
        harness.wait_estimates(4 if provisional else 3)
        executor.spin_once(timeout_sec=0.3)
        return harness.estimates(), len(harness.received[qos.SPIKE_COUNT]), node.values()


def test_an_estimate_taken_again_with_the_applied_control_is_published_again_under_its_stamp():
    """With provisional steps z_1 is answered at once with u_1; the plant's report that it flew
    zero thrust takes the step again: x_hat(0.2 s) comes a second time, corrected, equal to what
    waiting for the report gives; its spike count once; counted in diagnostics."""
    estimates, spike_counts, values = _flown_with_a_differing_report(True)
    waited, waited_spike_counts, waited_values = _flown_with_a_differing_report(False)
    assert [stamp for stamp, _ in estimates] == [0, DT, 2 * DT, 2 * DT]
    assert [stamp for stamp, _ in waited] == [0, DT, 2 * DT]
    assert not np.allclose(estimates[2][1], estimates[3][1], rtol=0, atol=1e-9)  # u_1 against zero
    np.testing.assert_array_equal(estimates[3][1], waited[2][1])
    assert spike_counts == waited_spike_counts == 3
    assert values['estimates_corrected'] == 1 and values['provisional_corrected'] == 1
    assert values['estimates_published'] == 4 and values['provisional_held'] == 0
    assert waited_values['estimates_corrected'] == 0 and waited_values['provisional_steps'] == 0


def test_estimator_rejects_controls_with_a_wrong_frame(estimator_rig):
    harness, node = estimator_rig
    harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), DT, 'map'))
    harness.wait_value('estimator', 'controls_rejected.wrong_frame', 1)
    step(harness, DT, 3)
    assert node.estimator.steps == 2


def test_estimator_rejects_inputs_from_before_its_initialisation():
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        node = make(EstimatorNode, context, executor, nodes, 'estimator', diagnostics_period=0.0,
                    history_wait=0.0, initial_state_dispersion=False)
        assert spin_until(executor, lambda: harness.node.count_subscribers(qos.MEASUREMENT) > 0)
        harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), 10 * DT, 'lvlh'))
        harness.wait_estimates(1)
        assert node.runner.start_ns == 10 * DT
        harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), 5 * DT, 'lvlh'))
        harness.wait_value('estimator', 'controls_rejected.before_init', 1)
        harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), 5 * DT, 'lvlh'))
        harness.wait_value('estimator', 'measurements_rejected.stale', 1)
        harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), 10 * DT, 'lvlh'))
        harness.wait_estimates(2)
        assert node.estimator.steps == 1


def test_a_backwards_time_jump_restarts_the_filter(estimator_rig):
    harness, node = estimator_rig
    step(harness, DT, 3)
    for k in range(2, 40):
        step(harness, k * DT, k + 2)
    # the simulation restarts: measurements from t = 0 again
    harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), 0, 'lvlh'))
    harness.wait_value('estimator', 'time_jumps', 1)
    assert node.runner.start_ns == 0  # initialised again at the new t = 0
    harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), 0, 'lvlh'))
    assert spin_until(harness.executor, lambda: harness.estimates()[-1][0] == DT)


def test_the_clock_going_back_restarts_the_filter(estimator_rig):
    harness, node = estimator_rig
    harness.clock(50 * DT)
    assert spin_until(harness.executor, lambda: node.get_clock().now().nanoseconds == 50 * DT)
    harness.clock(0)
    assert spin_until(harness.executor, lambda: node.values().get('time_jumps') == 1)
    assert not node.runner.started


def test_sensor_dropout_is_predicted_over_and_a_burst_is_processed_in_order(estimator_rig):
    harness, node = estimator_rig
    for k in range(1, 6):  # controls keep coming, measurements do not
        harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), k * DT, 'lvlh'))
    harness.clock(6 * DT)
    harness.wait_estimates(7)
    assert [s for s, _ in harness.estimates()][-1] == 6 * DT
    assert node.values()['dropout_steps'] == 5
    # a burst: six measurements and controls at once
    for k in range(6, 12):
        harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), k * DT, 'lvlh'))
        harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), k * DT, 'lvlh'))
    harness.wait_estimates(13)
    stamps = [s for s, _ in harness.estimates()]
    assert stamps[-6:] == [k * DT for k in range(7, 13)]
    assert node.values()['measurements_rejected'] == 0


def test_a_missing_measurement_between_two_is_predicted_over(estimator_rig):
    harness, node = estimator_rig
    harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), DT, 'lvlh'))
    step(harness, 2 * DT, 4)  # z(0.1 s) never came
    assert [s for s, _ in harness.estimates()][-2:] == [2 * DT, 3 * DT]
    assert node.values()['dropout_steps'] == 1


def test_reset_service_and_set_state_topic(estimator_rig):
    harness, node = estimator_rig
    target = np.array([1.0, 2.0, 3.0, 0.1, 0.0, -0.1])
    covariance = np.diag([0.5, 0.5, 0.5, 0.01, 0.01, 0.01])
    harness.publish(qos.SET_STATE, state_to_odometry(target, covariance, DT, 'lvlh', 'chaser'))
    assert spin_until(harness.executor, lambda: node.values().get('set_state') == 1)
    np.testing.assert_allclose(node.estimator.x_hat, target, atol=1e-6)
    np.testing.assert_allclose(np.diag(node.estimator.P), np.diag(covariance))
    response = harness.call(Trigger, '/estimator/reset', Trigger.Request())
    # mid-flight: from the data at the next measurement, never the parameters' initial state
    assert response.success and 'recent measurements' in response.message and node.runner.started
    step(harness, DT, 3)
    assert node.values()['restarts_from.last_trusted'] == 1  # too few measurements for a fit yet
    np.testing.assert_allclose(harness.estimates()[-1][1][:3], X0, atol=0.5)  # the measurement, not target


def test_a_persistently_inconsistent_innovation_re_initialises_from_the_measurement(estimator_rig):
    harness, node = estimator_rig
    wrong = np.array([170.0, 30.0, -5.0, -1.7, -0.9, 0.25])  # 100 m off
    harness.publish(qos.SET_STATE, state_to_odometry(wrong, np.diag([1e-2] * 3 + [1e-4] * 3), DT, 'lvlh', 'c'))
    assert spin_until(harness.executor, lambda: node.values().get('set_state') == 1)
    for k in range(1, 12):
        step(harness, k * DT, k + 2)
    assert node.values()['reinitialisations.inconsistent_innovation'] == 1
    assert abs(harness.estimates()[-1][1][0] - 70.0) < 1.0


def test_runtime_parameters_apply_atomically_or_are_refused_with_a_reason(estimator_rig):
    harness, node = estimator_rig
    results = harness.set_parameters('estimator', boundary_layer=[0.2, 0.2, 0.2], leak_rate=0.01)
    assert all(r.successful for r in results)
    assert node.estimator.settings.leak_rate == 0.01
    np.testing.assert_allclose(node.estimator.settings.boundary_layer, 0.2)
    before = node.estimator.settings
    for values, words in [({'boundary_layer': [-1.0]}, 'boundary_layer'),
                          ({'leak_rate': -1.0}, 'leak_rate'),
                          ({'neuron_count': 10}, 'read-only'),
                          ({'filter_type': 'ekf'}, 'read-only'),
                          ({'silenced_neurons': [500]}, 'silenced_neurons')]:
        results = harness.set_parameters('estimator', **values)
        assert not results[0].successful and words in results[0].reason, (values, results[0].reason)
        assert node.estimator.settings == before
    assert all(r.successful for r in harness.set_parameters('estimator', silenced_fraction=0.5))
    assert len(node.estimator.silenced) == 100
    step(harness, DT, 3)
    assert np.all(node.estimator.spikes[list(node.estimator.silenced)] == 0)


@pytest.fixture
def controller_rig():
    """A controller with a harness, its subscription matched."""
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        controller = make(ControllerNode, context, executor, nodes, 'lqr_controller', diagnostics_period=0.0)
        assert spin_until(executor, lambda: harness.node.count_subscribers(qos.ESTIMATE) > 0)
        yield harness, controller


def test_controller_bad_inputs_safe_mode_and_gain_changes(controller_rig):
    harness, controller = controller_rig
    executor = harness.executor
    x = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])
    for bad, reason in [(state_to_odometry(np.full(6, np.nan), None, DT, 'lvlh', 'c'), 'non_finite'),
                        (state_to_odometry(x, None, DT, 'map', 'c'), 'wrong_frame')]:
        harness.publish(qos.ESTIMATE, bad)
        harness.wait_value('lqr_controller', f'estimates_rejected.{reason}', 1)
    harness.publish(qos.ESTIMATE, state_to_odometry(x, None, DT, 'lvlh', 'c'))
    assert spin_until(executor, lambda: len(harness.received[qos.CONTROL]) == 1)
    # the same estimate again (a lockstep resend): the same control again
    harness.publish(qos.ESTIMATE, state_to_odometry(x, None, DT, 'lvlh', 'c'))
    assert spin_until(executor, lambda: len(harness.received[qos.CONTROL]) == 2)
    assert harness.received[qos.CONTROL][1] == harness.received[qos.CONTROL][0]
    harness.wait_value('lqr_controller', 'controls_resent', 1)
    # an older estimate than the last: rejected
    harness.publish(qos.ESTIMATE, state_to_odometry(x, None, DT // 2, 'lvlh', 'c'))
    harness.wait_value('lqr_controller', 'estimates_rejected.not_newer', 1)
    # an estimate newer than the last but more than max_input_age behind the clock
    assert harness.set_parameters('lqr_controller', estimate_timeout=100.0)[0].successful
    harness.clock(15 * DT)
    assert spin_until(executor, lambda: controller.get_clock().now().nanoseconds == 15 * DT)
    harness.publish(qos.ESTIMATE, state_to_odometry(x, None, 2 * DT, 'lvlh', 'c'))
    harness.wait_value('lqr_controller', 'estimates_rejected.too_old', 1)
    # the clock runs on without estimates: safe mode, zero thrust at every step
    assert harness.set_parameters('lqr_controller', estimate_timeout=0.5)[0].successful
    for k in range(16, 30):
        harness.clock(k * DT)
        executor.spin_once(timeout_sec=0.05)
    assert spin_until(executor, lambda: controller.safe_mode and
                      harness.received[qos.CONTROL][-1].accel.linear.x == 0.0)
    zero = harness.received[qos.CONTROL][-1]
    assert [zero.accel.linear.x, zero.accel.linear.y, zero.accel.linear.z] == [0.0, 0.0, 0.0]
    assert stamp_to_ns(zero.header.stamp) > 15 * DT
    harness.wait_value('lqr_controller', 'safe_mode', True)
    harness.publish(qos.ESTIMATE, state_to_odometry(x, None, 30 * DT, 'lvlh', 'c'))
    assert spin_until(executor, lambda: not controller.safe_mode and stamp_to_ns(
        harness.received[qos.CONTROL][-1].header.stamp) == 30 * DT)
    back = harness.received[qos.CONTROL][-1]
    assert stamp_to_ns(back.header.stamp) == 30 * DT and back.accel.linear.x != 0.0
    gain = controller.gain
    assert all(r.successful for r in harness.set_parameters('lqr_controller', lqr_input_weight=[1e3]))
    assert not np.allclose(controller.gain, gain)
    refused = harness.set_parameters('lqr_controller', lqr_input_weight=[-1.0])[0]
    assert not refused.successful and 'lqr_input_weight' in refused.reason


def test_controller_rejects_an_estimate_far_ahead_of_the_clock_and_keeps_its_watchdog(controller_rig):
    harness, controller = controller_rig
    executor = harness.executor
    x = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])
    harness.clock(DT)
    assert spin_until(executor, lambda: controller.get_clock().now().nanoseconds == DT)
    harness.publish(qos.ESTIMATE, state_to_odometry(x, None, 2 * DT, 'lvlh', 'c'))  # one step ahead: fine
    assert spin_until(executor, lambda: len(harness.received[qos.CONTROL]) == 1)
    harness.publish(qos.ESTIMATE, state_to_odometry(x, None, 10_000 * DT, 'lvlh', 'c'))
    harness.wait_value('lqr_controller', 'estimates_rejected.future', 1)
    for k in range(2, 6):  # the real estimates still get controls
        harness.clock(k * DT)
        harness.publish(qos.ESTIMATE, state_to_odometry(x, None, (k + 1) * DT, 'lvlh', 'c'))
        assert spin_until(executor, lambda k=k: len(harness.received[qos.CONTROL]) == k)
    for k in range(6, 20):  # and when they stop, the watchdog still sees it
        harness.clock(k * DT)
        executor.spin_once(timeout_sec=0.05)
    assert spin_until(executor, lambda: controller.safe_mode)


def test_sensor_starts_over_when_the_clock_or_the_truth_time_goes_back():
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        sensor = make(SensorNode, context, executor, nodes, 'position_sensor', diagnostics_period=0.0)
        assert spin_until(executor, lambda: harness.node.count_subscribers(qos.TRUTH) > 0)
        truth = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])

        def measured(stamps):
            return [stamp_to_ns(m.header.stamp) for m in harness.received[qos.MEASUREMENT]] == stamps

        # without a clock: truth 2 s back is a restart; the same truth again (a lockstep resend)
        # gets the same measurement again, not a new draw
        for stamp in (50 * DT, 51 * DT, 51 * DT, 30 * DT):
            harness.publish(qos.TRUTH, state_to_odometry(truth, None, stamp, 'lvlh', 'c'))
        assert spin_until(executor, lambda: measured([50 * DT, 51 * DT, 51 * DT, 30 * DT]))
        again = harness.received[qos.MEASUREMENT]
        assert (again[1].point.x, again[1].point.y) == (again[2].point.x, again[2].point.y)
        harness.wait_value('position_sensor', 'measurements_resent', 1)
        # with a clock, even truth 2 s back is only late: not measured...
        harness.clock(40 * DT)
        assert spin_until(executor, lambda: sensor.get_clock().now().nanoseconds == 40 * DT)
        harness.publish(qos.TRUTH, state_to_odometry(truth, None, 10 * DT, 'lvlh', 'c'))
        harness.wait_value('position_sensor', 'truth_rejected.not_newer', 1)
        # ...but the clock going back (a restarted plant) starts the sensor over
        harness.clock(5 * DT)
        assert spin_until(executor, lambda: sensor.get_clock().now().nanoseconds == 5 * DT)
        harness.publish(qos.TRUTH, state_to_odometry(truth, None, 5 * DT, 'lvlh', 'c'))
        assert spin_until(executor, lambda: measured([50 * DT, 51 * DT, 51 * DT, 30 * DT, 5 * DT]))
        harness.wait_value('position_sensor', 'time_jumps', 2)


def test_controller_starts_over_when_the_clock_goes_back(controller_rig):
    harness, controller = controller_rig
    x = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])
    harness.clock(20 * DT)
    assert spin_until(harness.executor, lambda: controller.get_clock().now().nanoseconds == 20 * DT)
    harness.publish(qos.ESTIMATE, state_to_odometry(x, None, 21 * DT, 'lvlh', 'c'))
    assert spin_until(harness.executor, lambda: len(harness.received[qos.CONTROL]) == 1)
    harness.clock(5 * DT)  # a restarted plant: estimates from 6 s on are new again
    assert spin_until(harness.executor, lambda: controller.get_clock().now().nanoseconds == 5 * DT)
    harness.publish(qos.ESTIMATE, state_to_odometry(x, None, 6 * DT, 'lvlh', 'c'))
    assert spin_until(harness.executor, lambda: len(harness.received[qos.CONTROL]) == 2)
    harness.wait_value('lqr_controller', 'time_jumps', 1)


def test_plant_rejects_bad_controls_and_pauses():
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        make(PlantNode, context, executor, nodes, 'cw_plant', start_time=1.0, duration=0.0,
             diagnostics_period=0.0)
        assert spin_until(executor, lambda: harness.received[qos.TRUTH])
        start = 10 * DT
        for bad, reason in [(control_to_accel(np.array([np.nan, 0, 0]), start, 'lvlh'), 'non_finite'),
                            (control_to_accel(np.zeros(3), start, 'map'), 'wrong_frame'),
                            (control_to_accel(np.zeros(3), 0, 'lvlh'), 'before_init')]:
            harness.publish(qos.CONTROL, bad)
            harness.wait_value('cw_plant', f'controls_rejected.{reason}', 1)
        assert len(harness.received[qos.TRUTH]) == 1
        assert all(r.successful for r in harness.set_parameters('cw_plant', paused=True))
        harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), start, 'lvlh'))
        harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), start + DT, 'lvlh'))  # early
        executor.spin_once(timeout_sec=0.3)
        assert len(harness.received[qos.TRUTH]) == 1  # paused: no step
        harness.set_parameters('cw_plant', paused=False)
        assert spin_until(executor, lambda: len(harness.received[qos.TRUTH]) == 3)  # held + early
        assert stamp_to_ns(harness.received[qos.TRUTH][2].header.stamp) == start + 2 * DT


def test_a_realtime_plant_stops_after_its_duration():
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        plant = make(PlantNode, context, executor, nodes, 'cw_plant', mode='realtime',
                     real_time_factor=20.0, duration=0.5)  # 5 steps of 0.1 s in 25 ms
        assert spin_until(executor, lambda: plant.values()['done'])
        for _ in range(10):  # 0.5 s more of wall time: the ticker has fired ~100 more times
            executor.spin_once(timeout_sec=0.05)
        assert plant.values()['steps'] == 5
        assert len(harness.received[qos.TRUTH]) == 6  # the initial state and five steps


floats = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                   st.floats(-1e3, 1e3))
messages = st.tuples(st.sampled_from(['measurement', 'control', 'set_state', 'clock', 'param', 'garbage']),
                     st.lists(floats, min_size=6, max_size=6),
                     st.integers(-2, 40), st.sampled_from(['lvlh', 'lvlh', 'map', '']))
parameter_values = st.sampled_from([
    ('boundary_layer', [0.05]), ('boundary_layer', [-0.1]), ('boundary_layer', [0.1, 0.2]),
    ('leak_rate', 0.01), ('leak_rate', -3.0), ('leak_rate', 20.0), ('measurement_noise_scale', 0.0),
    ('process_noise_scale', 2.0), ('silenced_fraction', 0.3), ('silenced_fraction', 1.0),
    ('silenced_neurons', [1, 2, 3]), ('silenced_neurons', [-1]), ('nis_window', 0)])


@pytest.mark.slow
@settings(max_examples=15, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.lists(messages, min_size=1, max_size=30), st.lists(parameter_values, max_size=3))
def test_random_and_malformed_inputs_never_escape_and_outputs_stay_finite(sequence, parameters):
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        node = make(EstimatorNode, context, executor, nodes, 'estimator', **QUIET,
                    diagnostics_period=0.0, neuron_count=40)
        # the controller answers on its own topic, so that its controls are told from ours
        controller = make(ControllerNode, context, executor, nodes, 'lqr_controller',
                          cli_args=['--ros-args', '-r', 'control:=answers'])
        controls = []  # what the controller itself publishes
        harness.node.create_subscription(AccelStamped, 'answers', controls.append, qos.LISTENER_QOS)
        assert spin_until(executor, lambda: harness.node.count_subscribers(qos.MEASUREMENT) > 0)
        measurements = 0
        for kind, values, k, frame in sequence:
            stamp = max(k, 0) * DT
            if kind == 'measurement':
                measurements += 1
                harness.publish(qos.MEASUREMENT, measurement_to_point(np.array(values[:3]), (0, 1, 2), stamp, frame))
            elif kind == 'control':
                harness.publish(qos.CONTROL, control_to_accel(np.array(values[:3]), stamp, frame))
            elif kind == 'set_state':
                harness.publish(qos.SET_STATE, state_to_odometry(np.array(values), None, stamp, frame, 'c'))
            elif kind == 'clock':
                harness.clock(stamp)
            elif kind == 'garbage':  # bytes of the right topic type but not valid CDR of it
                measurements += 1
                good = encode_point(np.array(values[:3]), (0, 1, 2), stamp, frame)
                harness.publish(qos.MEASUREMENT, good[:4 + k % (len(good) - 4)] if k % 2 else
                                good[:8] + bytes([255]) * 8 + good[16:])
            elif parameters:
                name, value = parameters[k % len(parameters)]
                harness.node.get_logger().debug(f'setting {name}')
                node.set_parameters([Parameter(name, value=value)])
            for _ in range(4):
                executor.spin_once(timeout_sec=0.0)  # an exception in a callback would raise here
        spin_until(executor, lambda: False, timeout=0.2)
        values = node.values()
        assert values['measurements_received'] == measurements == (
            values['measurements_rejected'] + values['measurements_used'] + values['measurements_dropped']
            + values['measurements_pending'] + values['measurements_repeated'])
        assert sum(v for k, v in values.items() if k.startswith('measurements_rejected.')) == \
            values['measurements_rejected']
        for _, x in harness.estimates():
            assert np.all(np.isfinite(x))
        for message in controls:
            assert np.all(np.isfinite(accel_to_control(message)))
        assert np.all(np.isfinite(node.estimator.x_hat))
        assert controller.gain.shape == (3, 6)


def test_a_second_estimator_warm_starts_from_the_running_ones_estimates():
    """Make-before-break swap: the new estimator takes the newest estimate the running one
    offers on `estimate`, replays what came since, and continues from there."""
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        first = make(EstimatorNode, context, executor, nodes, 'estimator', **QUIET,
                     nis_window=0)  # the constant test measurements are not a consistent track
        assert spin_until(executor, lambda: harness.node.count_subscribers(qos.MEASUREMENT) > 0)
        for k in range(20):
            harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), k * DT, 'lvlh'))
            harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), k * DT, 'lvlh'))
            harness.wait_estimates(k + 2)
        newest = harness.estimates()[-1]
        assert first.estimator.steps == 20, (first.estimator.steps, first.values())
        second = make(EstimatorNode, context, executor, nodes, 'estimator', filter_type='ekf',
                      history_wait=5.0, nis_window=0)
        harness.publish(qos.MEASUREMENT, measurement_to_point(X0, (0, 1, 2), 20 * DT, 'lvlh'))
        assert spin_until(executor, lambda: second.runner.started, timeout=10.0)
        assert second.values()['warm_starts'] == 1 and second.runner.start_ns == newest[0] == 20 * DT
        np.testing.assert_allclose(second.estimator.x_hat, newest[1], atol=1e-9)  # not stepped yet
        harness.publish(qos.CONTROL, control_to_accel(np.zeros(3), 20 * DT, 'lvlh'))
        assert spin_until(executor, lambda: second.estimator.steps == 1 and first.estimator.steps == 21), (
            second.estimator.steps, first.estimator.steps, second.values())
        assert np.abs(second.estimator.x_hat - first.estimator.x_hat).max() < 0.5


def _control_answering(harness, x, k):
    """Publish the estimate x at step k and return the controller's control for its stamp."""
    harness.publish(qos.ESTIMATE, state_to_odometry(x, None, k * DT, 'lvlh', 'c'))
    assert spin_until(harness.executor, lambda: any(stamp_to_ns(m.header.stamp) == k * DT
                                                    for m in harness.received[qos.CONTROL]))
    return [m for m in harness.received[qos.CONTROL] if stamp_to_ns(m.header.stamp) == k * DT][-1]


def test_controller_safe_mode_covers_a_dead_sensor_and_reports_its_peers(controller_rig):
    """Estimates keep coming (predictions) but the measurements stopped: zero thrust, the
    'measurement' peer WARN in diagnostics; measurements back: LQR again, the level clears."""
    harness, controller = controller_rig
    executor = harness.executor
    assert harness.set_parameters('lqr_controller', peer_timeout=0.3)[0].successful is False  # read-only
    x = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])

    def step(k, measured=True, settle=0.0):
        harness.clock(k * DT)
        if measured:
            harness.publish(qos.MEASUREMENT, measurement_to_point(x[:3], (0, 1, 2), k * DT, 'lvlh'))
        spin_until(executor, lambda: False, timeout=settle)
        return _control_answering(harness, x, k)

    for k in range(1, 5):
        assert step(k, settle=0.05).accel.linear.x != 0.0
    for k in range(5, 15):  # 1 s of simulated time without measurements
        step(k, measured=False)
    assert step(15, measured=False).accel.linear.x == 0.0  # steering on predictions: no thrust
    assert controller.safe_mode  # within a step, long before the clock could count as stopped
    assert spin_until(executor, lambda: 'no measurement since t = 0.400 s' in
                      harness.received[qos.DIAGNOSTICS][-1].status[0].message, timeout=1.0)
    # peer_timeout (2 s wall): the sensor counts as gone, and the clock as stopped
    assert spin_until(executor, lambda: harness.diagnostics('lqr_controller').get('peer.measurement') == 'WARN'
                      and harness.diagnostics('lqr_controller').get('peer.clock') == 'WARN', timeout=5.0)
    assert 'safe mode' in harness.received[qos.DIAGNOSTICS][-1].status[0].message
    assert harness.received[qos.DIAGNOSTICS][-1].status[0].level == b'\x01'  # WARN
    step(16, settle=0.3)  # both back (the safe-mode timer may answer this step first, with zero)
    assert step(17).accel.linear.x != 0.0 and not controller.safe_mode
    assert spin_until(executor, lambda: harness.diagnostics('lqr_controller').get('peer.measurement') == 'OK')


def test_controller_watches_every_sensor_topic_it_is_given_and_no_other():
    """measurement_topics [camera, lidar] (an estimator with `sensors`, each on its own topic, of
    its own type): one sensor silent is reported as its peer but the loop still measures (no
    safe mode); both silent is safe mode naming both, and a message on the default
    `measurement` topic does not count as either sensor."""
    from geometry_msgs.msg import Vector3Stamped
    from sensor_msgs.msg import Range
    from std_msgs.msg import Header
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        controller = make(ControllerNode, context, executor, nodes, 'lqr_controller', diagnostics_period=0.0,
                          peer_timeout=1.0, measurement_topics=['camera', 'lidar'])
        camera = harness.node.create_publisher(Vector3Stamped, 'camera', qos.PUBLISHER_QOS)
        lidar = harness.node.create_publisher(Range, 'lidar', qos.PUBLISHER_QOS)
        assert spin_until(executor, lambda: camera.get_subscription_count() and lidar.get_subscription_count()
                          and harness.node.count_subscribers(qos.ESTIMATE))
        x = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])

        def step(k, sensors, settle=0.0):
            harness.clock(k * DT)
            stamp = ns_to_stamp(k * DT)
            if 'camera' in sensors:
                camera.publish(Vector3Stamped(header=Header(stamp=stamp, frame_id='camera')))
            if 'lidar' in sensors:
                lidar.publish(Range(header=Header(stamp=stamp, frame_id='lidar'), range=float('inf')))
            if 'measurement' in sensors:
                harness.publish(qos.MEASUREMENT, measurement_to_point(x[:3], (0, 1, 2), k * DT, 'lvlh'))
            spin_until(executor, lambda: False, timeout=settle)
            return _control_answering(harness, x, k)

        for k in range(1, 5):
            assert step(k, ('camera', 'lidar'), settle=0.05).accel.linear.x != 0.0
        peers = harness.diagnostics('lqr_controller')
        assert peers['peer.camera'] == peers['peer.lidar'] == 'OK' and 'peer.measurement' not in peers
        # the LIDAR gone for 1.5 s of simulated time and >= 1.5 s of wall time (over the peer timeout;
        # a timeout well above the pace of the steps: a loaded machine's stalls do not silence the camera)
        for k in range(5, 20):
            assert step(k, ('camera',), settle=0.1).accel.linear.x != 0.0  # still measured by the camera
        assert not controller.safe_mode
        assert spin_until(executor, lambda: harness.diagnostics('lqr_controller')['peer.lidar'] == 'WARN',
                          timeout=3.0)
        assert harness.diagnostics('lqr_controller')['peer.camera'] == 'OK'
        for k in range(20, 31):  # both gone, only the unwatched topics speak: steering on predictions
            last = step(k, ('measurement',))
        assert last.accel.linear.x == 0.0 and controller.safe_mode
        assert spin_until(executor, lambda: 'no measurement since t = 1.900 s on camera, lidar' in
                          harness.received[qos.DIAGNOSTICS][-1].status[0].message, timeout=1.0)
        step(31, ('lidar',), settle=0.3)  # the LIDAR back: the loop measures again

        ticks = iter(range(1, 1000))

        def lidar_speaks():  # the LIDAR and the clock go on, as in a loop: on a loaded machine the watchdog
            now = 31 * DT + next(ticks) * 100_000  # ns: may wake after its 1 s and find them stopped
            harness.clock(now)
            lidar.publish(Range(header=Header(stamp=ns_to_stamp(now), frame_id='lidar'), range=float('inf')))
            return not controller.safe_mode
        assert spin_until(executor, lidar_speaks, timeout=3.0)
        assert step(32, ('lidar',)).accel.linear.x != 0.0 and not controller.safe_mode


def test_controller_refuses_an_empty_or_repeated_sensor_topic():
    with ros_context() as (context, executor, nodes):
        for topics in (['camera', 'camera'], ['']):
            with pytest.raises(ValueError, match='measurement_topics'):
                make(ControllerNode, context, executor, nodes, 'lqr_controller', measurement_topics=topics)


def test_an_integer_set_at_runtime_for_a_double_is_taken_as_that_double_through_the_parameter_service():
    """`ros2 param set /cw_plant real_time_factor 10` sends an INTEGER ParameterValue through the
    standard set_parameters service, as this test does; rclpy alone refuses it as the wrong
    type. A double parameter takes it as the double; a read-only one is still refused as
    read-only, and a string for a double as the wrong type."""
    from rcl_interfaces.msg import ParameterType
    assert Parameter('x', value=10).to_parameter_msg().value.type == ParameterType.PARAMETER_INTEGER
    with ros_context() as (context, executor, nodes):
        harness = Harness(context, executor, nodes)
        controller = make(ControllerNode, context, executor, nodes, 'lqr_controller', diagnostics_period=0.0)
        plant = make(PlantNode, context, executor, nodes, 'cw_plant', mode='realtime', duration=0.0, start=False)
        gain = controller.gain
        results = harness.set_parameters('lqr_controller', estimate_timeout=2, lqr_state_weight=[2, 2, 2, 1, 1, 1])
        assert all(r.successful for r in results), [r.reason for r in results]
        timeout = controller.get_parameter('estimate_timeout')
        assert timeout.type_ == Parameter.Type.DOUBLE and timeout.value == 2.0
        weight = controller.get_parameter('lqr_state_weight')
        assert weight.type_ == Parameter.Type.DOUBLE_ARRAY and list(weight.value) == [2.0, 2.0, 2.0, 1.0, 1.0, 1.0]
        assert not np.allclose(controller.gain, gain)  # the new weight designed a new gain
        refused = harness.set_parameters('cw_plant', real_time_factor=10)[0]
        assert not refused.successful and refused.reason == 'Trying to set a read-only parameter: real_time_factor.'
        assert plant.get_parameter('real_time_factor').value == 1.0
        wrong = harness.set_parameters('lqr_controller', estimate_timeout='long')[0]
        assert not wrong.successful and 'Wrong parameter type' in wrong.reason
        assert controller.get_parameter('estimate_timeout').value == 2.0
