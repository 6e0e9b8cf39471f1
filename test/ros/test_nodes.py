"""Nodes built in-process in isolated contexts: behaviour, conversions at the edge, and the
lockstep loop over ROS equal to the offline simulator."""

import math

import numpy as np
import pytest

pytest.importorskip('rclpy')

from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.exceptions import ParameterException  # noqa: E402
from ros_helpers import Probe, make, ros_context, spin_until  # noqa: E402

from scenario_nodes import qos  # noqa: E402
from scenario_nodes.controller_node import ControllerNode  # noqa: E402
from scenario_nodes.conversions import (  # noqa: E402
    control_to_accel,
    measurement_to_point,
    odometry_to_state,
    stamp_to_ns,
    state_to_odometry,
)
from scenario_nodes.estimator_node import EstimatorNode  # noqa: E402
from scenario_nodes.plant_node import PlantNode  # noqa: E402
from scenario_nodes.sensor_node import SensorNode  # noqa: E402
from snn_estimator import FILTER_KINDS, rendezvous_scenario, simulate  # noqa: E402
from snn_estimator.plant.control import lqr_control, lqr_gain  # noqa: E402


def run_lockstep(kind, steps, plant_class=PlantNode, sensor_parameters=None, **estimator_parameters):
    """The four nodes in one process; returns the estimates by stamp and the truths by stamp."""
    duration = steps * 0.1
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes, skip=(qos.MEASUREMENT,) if sensor_parameters else ())
        make(ControllerNode, context, executor, nodes, 'lqr_controller')
        make(EstimatorNode, context, executor, nodes, 'estimator', filter_type=kind, **estimator_parameters)
        make(SensorNode, context, executor, nodes, 'position_sensor', **(sensor_parameters or {}))
        plant = make(plant_class, context, executor, nodes, plant_class.NAME, duration=duration,
                     control_timeout=30.0)
        last = steps * 100_000_000

        def stamps(topic):
            return {stamp_to_ns(m.header.stamp) for m in probe.received[topic]}
        finished = spin_until(executor, lambda: last in stamps(qos.TRUTH) and last in stamps(qos.ESTIMATE),
                              timeout=120.0)
        assert finished, 'the in-process loop did not complete'
        assert plant.values()['control_timeouts'] == 0
        estimates = {stamp_to_ns(m.header.stamp): odometry_to_state(m)[0] for m in probe.received[qos.ESTIMATE]}
        truths = {stamp_to_ns(m.header.stamp): odometry_to_state(m)[0] for m in probe.received[qos.TRUTH]}
        return estimates, truths


_OTHER_KINDS = [k for k in FILTER_KINDS if k not in ('snn_emsif', 'ekf')]


@pytest.mark.parametrize('kind, parameters', [('snn_emsif', {}), ('ekf', {}),
                                              ('snn_ekf', {'network_coding': 'deviation'})]
                         + [(k, {}) for k in _OTHER_KINDS],
                         ids=['snn_emsif', 'ekf', 'snn_ekf_deviation_coding'] + _OTHER_KINDS)
def test_lockstep_ros_run_equals_the_offline_simulation(kind, parameters):
    """Every filter kind (test_integration.py flies a representative few as processes for the
    whole approach), and the deviation coding (docs/decisions.md, 13b), set by its schema
    parameter alone."""
    steps = 300
    estimates, truths = run_lockstep(kind, steps, **parameters)
    scenario = rendezvous_scenario(initial_state_dispersion=True, **parameters)  # as config/rendezvous.yaml
    offline = simulate(scenario.__class__(**{**scenario.__dict__, 'duration': steps * 0.1}), kind)
    for k in range(steps + 1):
        stamp = k * 100_000_000
        np.testing.assert_allclose(estimates[stamp], offline.estimate[0, k], rtol=0, atol=1e-9)
        np.testing.assert_allclose(truths[stamp], offline.truth[0, k], rtol=0, atol=1e-9)


def test_the_estimator_node_runs_the_synchronous_spike_rule_set_by_its_parameters():
    """spike_rule synchronous and its tick parameters, set as ROS parameters (schema entries),
    reach the core: the ROS loop equals the offline run of the same configuration."""
    steps = 60
    parameters = {'spike_rule': 'synchronous', 'ticks_per_sample': 20, 'firing_slots': 4,
                  'threshold_widening': 0.5, 'refractory_ticks': 1}
    estimates, truths = run_lockstep('snn_ekf', steps, **parameters)
    scenario = rendezvous_scenario(initial_state_dispersion=True, **parameters)
    offline = simulate(scenario.__class__(**{**scenario.__dict__, 'duration': steps * 0.1}), 'snn_ekf')
    base = rendezvous_scenario(initial_state_dispersion=True)
    greedy = simulate(base.__class__(**{**base.__dict__, 'duration': steps * 0.1}), 'snn_ekf')
    for k in range(steps + 1):
        np.testing.assert_allclose(estimates[k * 100_000_000], offline.estimate[0, k], rtol=0, atol=1e-9)
    assert not np.allclose(offline.estimate[0, -1], greedy.estimate[0, -1], rtol=0, atol=1e-9)


def test_lockstep_ros_run_on_a_lidar_equals_the_offline_simulation_on_it():
    """The estimator on range, azimuth and elevation (config/sensor_lidar.yaml's values), its
    H(x_hat) every step, equal to the offline loop on the same sensor."""
    from scenario_nodes.parameter_tables import sensor_suites
    from snn_estimator.sim.scenarios import sensor_rendezvous_scenario
    steps, suite = 150, sensor_suites()['lidar']
    estimates, truths = run_lockstep('snn_ekf', steps, sensor_parameters=suite['position_sensor'],
                                     **suite['estimator'])
    scenario = sensor_rendezvous_scenario(initial_state_dispersion=True)
    offline = simulate(scenario.__class__(**{**scenario.__dict__, 'duration': steps * 0.1}), 'snn_ekf')
    for k in range(steps + 1):
        np.testing.assert_allclose(estimates[k * 100_000_000], offline.estimate[0, k], rtol=0, atol=1e-9)
        np.testing.assert_allclose(truths[k * 100_000_000], offline.truth[0, k], rtol=0, atol=1e-9)


def test_lockstep_ros_run_on_basilisk_truth_equals_the_offline_simulation():
    pytest.importorskip('Basilisk')
    from scenario_nodes.basilisk_plant_node import BasiliskPlantNode
    steps = 200
    estimates, truths = run_lockstep('snn_ekf', steps, BasiliskPlantNode)
    scenario = rendezvous_scenario(plant='basilisk', initial_state_dispersion=True)
    offline = simulate(scenario.__class__(**{**scenario.__dict__, 'duration': steps * 0.1}), 'snn_ekf')
    for k in range(steps + 1):
        stamp = k * 100_000_000
        np.testing.assert_allclose(truths[stamp], offline.truth[0, k], rtol=0, atol=1e-9)
        np.testing.assert_allclose(estimates[stamp], offline.estimate[0, k], rtol=0, atol=1e-9)


def test_estimator_steps_when_measurement_and_control_meet_and_rejects_bad_input():
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes)
        estimator = make(EstimatorNode, context, executor, nodes, 'estimator', diagnostics_period=0.0,
                         initial_state_dispersion=False)
        assert spin_until(executor, lambda: probe.node.count_subscribers(qos.MEASUREMENT) > 0)
        x0 = np.array([70.0, 30.0, -5.0])
        probe.publish(qos.MEASUREMENT, measurement_to_point(x0, (0, 1, 2), 0, 'lvlh'))
        assert spin_until(executor, lambda: len(probe.received[qos.ESTIMATE]) == 1)
        first = probe.received[qos.ESTIMATE][0]
        assert stamp_to_ns(first.header.stamp) == 0  # the initial estimate, at the first measurement
        np.testing.assert_allclose(odometry_to_state(first)[0], [70, 30, -5, -1.7, -0.9, 0.25], atol=1e-9)
        # no control yet: no step
        executor.spin_once(timeout_sec=0.1)
        assert estimator.estimator.steps == 0
        probe.publish(qos.CONTROL, control_to_accel(np.zeros(3), 0, 'lvlh'))
        assert spin_until(executor, lambda: len(probe.received[qos.ESTIMATE]) == 2)
        assert stamp_to_ns(probe.received[qos.ESTIMATE][1].header.stamp) == 100_000_000
        assert spin_until(executor, lambda: len(probe.received[qos.SPIKE_COUNT]) == 2
                          and len(probe.received[qos.SPIKES]) == 2)
        assert len(probe.received[qos.SPIKES][1].data) == 200
        assert sum(probe.received[qos.SPIKES][1].data) == probe.received[qos.SPIKE_COUNT][1].data
        # bad inputs: NaN, stale -- each counted, none stepped; a repeated measurement is answered
        # with the estimate it answered before (the lockstep resend), not stepped again
        nan = measurement_to_point(np.array([math.nan, 0.0, 0.0]), (0, 1, 2), 100_000_000, 'lvlh')
        stale = measurement_to_point(x0, (0, 1, 2), 50_000_000, 'lvlh')  # older than the estimate
        for msg in (nan, stale):
            probe.publish(qos.MEASUREMENT, msg)
        good = measurement_to_point(x0, (0, 1, 2), 100_000_000, 'lvlh')
        probe.publish(qos.MEASUREMENT, good)
        probe.publish(qos.MEASUREMENT, good)  # again
        assert spin_until(executor, lambda: len(probe.received[qos.ESTIMATE]) == 3)
        resent = probe.received[qos.ESTIMATE][2]
        assert stamp_to_ns(resent.header.stamp) == 100_000_000  # the answer to it, again
        first_answer = probe.received[qos.ESTIMATE][1]
        np.testing.assert_array_equal(odometry_to_state(resent)[0], odometry_to_state(first_answer)[0])
        probe.publish(qos.CONTROL, control_to_accel(np.zeros(3), 100_000_000, 'lvlh'))
        assert spin_until(executor, lambda: len(probe.received[qos.ESTIMATE]) == 4)
        assert spin_until(executor, lambda: probe.diagnostics('estimator').get('steps') == '2')
        values = probe.diagnostics('estimator')
        assert values['measurements_rejected'] == '2'
        assert values['measurements_rejected.non_finite'] == '1'
        assert values['measurements_rejected.stale'] == '1'
        assert values['estimates_resent'] == '1'
        assert estimator.estimator.steps == 2
        # the cost of the last estimate, as the core counts it (snn_estimator.spiking.costs)
        from snn_estimator.spiking.costs import CostModel
        costs = CostModel.of(estimator.estimator).step(estimator.estimator.spike_count)
        assert int(values['synops_per_step']) == costs.synops and int(values['dense_macs_per_step']) == costs.dense_macs
        assert all(np.all(np.isfinite(odometry_to_state(m)[0])) for m in probe.received[qos.ESTIMATE])


def test_controller_publishes_minus_k_times_the_estimate_with_its_stamp():
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes)
        controller = make(ControllerNode, context, executor, nodes, 'lqr_controller')
        scenario = rendezvous_scenario()
        expected_gain = lqr_gain(scenario.model, scenario.lqr_state_weight, scenario.lqr_input_weight)
        np.testing.assert_allclose(controller.gain, expected_gain)
        x_hat = np.array([10.0, -3.0, 2.0, 0.1, 0.2, -0.3])
        assert spin_until(executor, lambda: probe.node.count_subscribers(qos.ESTIMATE) > 0)
        probe.publish(qos.ESTIMATE, state_to_odometry(x_hat, None, 4_200_000_000, 'lvlh', 'chaser'))
        assert spin_until(executor, lambda: probe.received[qos.CONTROL])
        msg = probe.received[qos.CONTROL][0]
        assert stamp_to_ns(msg.header.stamp) == 4_200_000_000
        np.testing.assert_allclose([msg.accel.linear.x, msg.accel.linear.y, msg.accel.linear.z],
                                   lqr_control(expected_gain, x_hat), rtol=1e-15)


def test_sensor_measures_the_configured_axes_at_the_truth_time():
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes)
        make(SensorNode, context, executor, nodes, 'position_sensor', measured_axes=[0, 2],
             measurement_noise=[1e-12])
        assert spin_until(executor, lambda: probe.node.count_subscribers(qos.TRUTH) > 0)
        truth = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])
        probe.publish(qos.TRUTH, state_to_odometry(truth, None, 7_000_000_000, 'lvlh', 'chaser'))
        assert spin_until(executor, lambda: probe.received[qos.MEASUREMENT])
        msg = probe.received[qos.MEASUREMENT][0]
        assert stamp_to_ns(msg.header.stamp) == 7_000_000_000
        assert abs(msg.point.x - 1.0) < 1e-4 and abs(msg.point.z - 3.0) < 1e-4 and math.isnan(msg.point.y)


def test_lockstep_plant_waits_for_the_control_and_times_out_to_the_last_one():
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes)
        plant = make(PlantNode, context, executor, nodes, 'cw_plant', control_timeout=0.2, duration=0.0)
        assert spin_until(executor, lambda: probe.received[qos.TRUTH])
        executor.spin_once(timeout_sec=0.5)
        assert len(probe.received[qos.TRUTH]) == 1  # no first control: it waits (no timeout)
        for k in range(10):  # the start-up steps: no timeouts while the processes warm up
            probe.publish(qos.CONTROL, control_to_accel(np.array([0.01, 0.0, 0.0]), k * 100_000_000, 'lvlh'))
            assert spin_until(executor, lambda k=k: len(probe.received[qos.TRUTH]) == k + 2)
        assert stamp_to_ns(probe.received[qos.TRUTH][1].header.stamp) == 100_000_000
        assert plant.values()['control_timeouts'] == 0
        # now no control for step 10: after 0.2 s the plant holds u and goes on
        assert spin_until(executor, lambda: len(probe.received[qos.TRUTH]) >= 12, timeout=5.0)
        assert plant.values()['control_timeouts'] >= 1


def test_a_plant_stopped_before_its_last_step_publishes_its_totals_so_far():
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes)
        plant = make(PlantNode, context, executor, nodes, 'cw_plant', duration=100.0)
        assert spin_until(executor, lambda: probe.received[qos.TRUTH])
        for k in range(3):
            probe.publish(qos.CONTROL, control_to_accel(np.zeros(3), k * 100_000_000, 'lvlh'))
            assert spin_until(executor, lambda k=k: len(probe.received[qos.TRUTH]) == k + 2)
        plant.close()  # what run_node does on SIGINT/SIGTERM
        assert spin_until(executor, lambda: probe.diagnostics('cw_plant').get('truth_published') == '4')
        assert probe.diagnostics('cw_plant')['steps'] == '3'


def test_plant_publishes_the_first_state_only_once_enough_subscriptions_match_truth():
    with ros_context() as (context, executor, nodes):
        plant = make(PlantNode, context, executor, nodes, 'cw_plant', min_truth_subscribers=2, duration=0.0)
        executor.spin_once(timeout_sec=0.3)
        assert plant.values()['truth_published'] == 0  # nobody listens yet
        probe = Probe(context, executor, nodes)
        assert spin_until(executor, lambda: probe.node.count_subscribers(qos.TRUTH) == 1)
        for _ in range(10):
            executor.spin_once(timeout_sec=0.03)
        assert plant.values()['truth_published'] == 0  # one of two: still waiting
        from rclpy.node import Node
        second = Node('second_listener', context=context)
        executor.add_node(second)
        nodes.append(second)
        second.create_subscription(Odometry, qos.TRUTH, lambda msg: None, qos.SUBSCRIPTION_QOS)
        assert spin_until(executor, lambda: probe.received[qos.TRUTH])
        assert plant.values()['truth_published'] == 1 and stamp_to_ns(probe.received[qos.TRUTH][0].header.stamp) == 0


def test_a_sensor_subscribes_to_truth_only_once_its_measurements_have_enough_matched_subscribers():
    """min_measurement_subscribers: the sensor's 'truth' subscription (what the plant's start
    waits for) comes only once its own publisher has matched that many subscriptions, so no
    subscriber whose end DDS matched first loses the first samples; after match_wait it
    subscribes anyway."""
    from geometry_msgs.msg import PointStamped
    from rclpy.node import Node
    with ros_context() as (context, executor, nodes):
        watcher = Node('truth_watcher', context=context)
        executor.add_node(watcher)
        nodes.append(watcher)
        make(SensorNode, context, executor, nodes, 'position_sensor', min_measurement_subscribers=2,
             match_wait=60.0)
        listeners = []
        for k in range(2):
            assert not spin_until(executor, lambda: watcher.count_subscribers(qos.TRUTH) > 0, 0.5), k
            listener = Node(f'measurement_listener_{k}', context=context)
            executor.add_node(listener)
            nodes.append(listener)
            listener.create_subscription(PointStamped, qos.MEASUREMENT, lambda msg: None, qos.SUBSCRIPTION_QOS)
            listeners.append(listener)
        assert spin_until(executor, lambda: watcher.count_subscribers(qos.TRUTH) == 1)
        make(SensorNode, context, executor, nodes, 'position_sensor', cli_args=['--ros-args', '-r', '__node:=second'],
             min_measurement_subscribers=5, match_wait=0.3)
        assert spin_until(executor, lambda: watcher.count_subscribers(qos.TRUTH) == 2, 5.0)  # after 0.3 s


def _plain_node(context, executor, nodes, name):
    from rclpy.node import Node
    node = Node(name, context=context)
    executor.add_node(node)
    nodes.append(node)
    return node


def _held_until_two_subscribe(context, executor, nodes, node_class, name, count, output, input_topic):
    """Start ``node_class`` with ``count`` = 2; its ``input_topic`` subscription must come only
    once two listeners subscribed to its ``output`` (type, topic). Returns the input's watcher."""
    watcher = _plain_node(context, executor, nodes, f'{name}_input_watcher')
    make(node_class, context, executor, nodes, name, match_wait=60.0, **{count: 2})
    for k in range(2):
        assert not spin_until(executor, lambda: watcher.count_subscribers(input_topic) > 0, 0.5), k
        listener = _plain_node(context, executor, nodes, f'{name}_output_listener_{k}')
        listener.create_subscription(*output, lambda msg: None, qos.SUBSCRIPTION_QOS)
    assert spin_until(executor, lambda: watcher.count_subscribers(input_topic) == 1)
    return watcher


def test_the_controller_subscribes_to_estimates_only_once_its_controls_have_enough_matched_subscribers():
    """min_control_subscribers: upstream of the sensor's hold, the controller subscribes to
    'estimate' only once its control publisher matched that many subscriptions (the estimator,
    the plant, the recorder), so the chain the plant's start waits for is matched on each
    publisher's side (a realtime run flew its first 1.1 s without control: decisions.md, 41);
    after match_wait it subscribes anyway."""
    from geometry_msgs.msg import AccelStamped
    with ros_context() as (context, executor, nodes):
        watcher = _held_until_two_subscribe(context, executor, nodes, ControllerNode, 'lqr_controller',
                                            'min_control_subscribers', (AccelStamped, qos.CONTROL), qos.ESTIMATE)
        make(ControllerNode, context, executor, nodes, 'lqr_controller', cli_args=['--ros-args', '-r', '__node:=late'],
             min_control_subscribers=5, match_wait=0.3)
        assert spin_until(executor, lambda: watcher.count_subscribers(qos.ESTIMATE) == 2, 5.0)  # after 0.3 s


def test_the_estimator_subscribes_to_measurements_only_once_its_estimates_reach_enough_subscribers():
    """min_estimate_subscribers (its own liveliness monitor on 'estimate' not counted): the
    estimator subscribes to 'measurement' only once its estimates reach the controller and the
    recorder; a standby, which publishes nothing, and a node that does not activate itself
    subscribe at once; after match_wait it subscribes anyway."""
    with ros_context() as (context, executor, nodes):
        watcher = _held_until_two_subscribe(context, executor, nodes, EstimatorNode, 'estimator',
                                            'min_estimate_subscribers', (Odometry, qos.ESTIMATE), qos.MEASUREMENT)
        for k, changes in enumerate(({'standby': True, 'match_wait': 60.0}, {'autostart': False, 'match_wait': 60.0},
                                     {'match_wait': 0.3})):
            node = make(EstimatorNode, context, executor, nodes, 'estimator',
                        cli_args=['--ros-args', '-r', f'__node:=e{k}'], min_estimate_subscribers=5, **changes)
            if not changes.get('autostart', True):
                node.trigger_configure()  # a managed node: configured (ros2 lifecycle set), not activated
            assert spin_until(executor, lambda k=k: watcher.count_subscribers(qos.MEASUREMENT) == 2 + k, 5.0), changes


@pytest.mark.parametrize('node_class, name, changes, message', [
    (EstimatorNode, 'estimator', {'neuron_count': 0}, 'neuron_count'),
    (EstimatorNode, 'estimator', {'leak_rate': -1.0}, 'leak_rate'),
    (EstimatorNode, 'estimator', {'boundary_layer': [0.1, -0.1, 0.1]}, 'boundary_layer'),
    (EstimatorNode, 'estimator', {'initial_state': [1.0, 2.0]}, 'initial_state'),
    (EstimatorNode, 'estimator', {'initial_covariance': [1.0, 1.0, 1.0, 1.0, 1.0, -1.0]}, 'positive definite'),
    (EstimatorNode, 'estimator', {'filter_type': 'ukf'}, 'filter_type'),
    (EstimatorNode, 'estimator', {'model': 'range_azimuth_elevation', 'measurement_noise': [1.0, 2.0]},
     r'measurement_noise \(R of range_azimuth_elevation'),
    (EstimatorNode, 'estimator', {'model': 'line_of_sight', 'mounting_rotation': [0.0, 0.0, 2.0, 0.0]},
     'mounting_rotation'),
    (EstimatorNode, 'estimator', {'sensors': ['lidar', 'lidar']}, 'every name once'),
    (EstimatorNode, 'estimator', {'sensors': ['li dar']}, 'is not a name'),
    (EstimatorNode, 'estimator', {'sensors': ['lidar'], 'lidar.boundary_layer': [0.1, 0.1]}, 'lidar.boundary_layer'),
    (EstimatorNode, 'estimator', {'sensors': ['camera'], 'camera.model': 'line_of_sight',
                                  'camera.measurement_noise': [1.0, 2.0, 3.0]}, r'camera: measurement_noise'),
    (PlantNode, 'cw_plant', {'mode': 'fast'}, 'mode'),
    (PlantNode, 'cw_plant', {'start_time': 3e9}, 'start_time'),  # beyond a ROS stamp's int32 s
    (SensorNode, 'position_sensor', {'measurement_noise': [1.0, 2.0]}, 'measurement_noise'),
    (ControllerNode, 'lqr_controller', {'lqr_input_weight': [0.0]}, 'lqr_input_weight'),
])
def test_invalid_parameters_refuse_to_build_the_node(node_class, name, changes, message):
    with ros_context() as (context, executor, nodes):
        with pytest.raises((ValueError, ParameterException), match=message):
            make(node_class, context, executor, nodes, name, **changes)


@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
def test_the_plant_starts_once_the_loop_is_there_and_no_step_is_lost(mode):
    """Started first, the plant waits (and says for what) until a sensor, an estimator and a
    controller are in the graph, whatever order they come in; then every truth is measured and
    the first estimate answers the first measurement."""
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes, publish=False)  # a listener plays no role of the loop
        plant = make(PlantNode, context, executor, nodes, 'cw_plant', mode=mode, real_time_factor=10.0,
                     duration=3.0, control_timeout=30.0)
        for kind, name in ((ControllerNode, 'lqr_controller'), (SensorNode, 'position_sensor')):
            make(kind, context, executor, nodes, name)
            spin_until(executor, lambda: False, timeout=0.5)
            assert plant.values()['truth_published'] == 0  # no estimator yet: still waiting
        make(EstimatorNode, context, executor, nodes, 'estimator', initial_state_dispersion=False)
        assert spin_until(executor, lambda: plant.values()['done'], timeout=60.0)
        spin_until(executor, lambda: False, timeout=0.3)
        truths = {stamp_to_ns(m.header.stamp) for m in probe.received[qos.TRUTH]}
        measurements = {stamp_to_ns(m.header.stamp) for m in probe.received[qos.MEASUREMENT]}
        estimates = sorted({stamp_to_ns(m.header.stamp) for m in probe.received[qos.ESTIMATE]})
        assert truths == measurements == {k * 100_000_000 for k in range(31)}
        assert estimates[0] == 0 and estimates == [k * 100_000_000 for k in range(len(estimates))]
        assert len(estimates) >= 30


def test_an_integer_for_a_double_parameter_is_taken_as_that_double_and_a_string_is_refused_with_the_fix():
    """ros2 run ... -p cw_plant:real_time_factor:=10 hands rclpy an integer for a double."""
    with ros_context() as (context, executor, nodes):
        plant = make(PlantNode, context, executor, nodes, 'cw_plant', mode='realtime', real_time_factor=10,
                     duration=0.0, start=False)
        value = plant.get_parameter('real_time_factor')
        assert value.value == 10.0 and value.type_ == value.Type.DOUBLE
        controller = make(ControllerNode, context, executor, nodes, 'lqr_controller',
                          lqr_state_weight=[1, 1, 1, 1, 1, 1], start=False)
        assert list(controller.get_parameter('lqr_state_weight').value) == [1.0] * 6
        fix = r'parameter real_time_factor must be a double \(e\.g\. real_time_factor:=1\)'
        with pytest.raises(ValueError, match=fix):
            make(PlantNode, context, executor, nodes, 'cw_plant', real_time_factor='fast', start=False)


def test_a_late_volatile_subscriber_gets_the_present_and_a_late_history_reader_the_recent_past():
    """ros2 topic echo --once adapts to the publishers' durability: it gets a current sample
    (the topics are volatile), while <topic>/history keeps what a joining estimator needs."""
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes, publish=False)
        make(ControllerNode, context, executor, nodes, 'lqr_controller')
        make(EstimatorNode, context, executor, nodes, 'estimator', filter_type='ekf', history_wait=0.0)
        make(SensorNode, context, executor, nodes, 'position_sensor')
        make(PlantNode, context, executor, nodes, 'cw_plant', duration=0.0, control_timeout=30.0)
        assert spin_until(executor, lambda: len(probe.received[qos.ESTIMATE]) > 300, timeout=90.0)
        late = Node('late_echo', context=context)
        executor.add_node(late)
        nodes.append(late)
        infos = late.get_publishers_info_by_topic('/estimate')
        latched = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
        assert infos and not latched  # so the CLI subscribes volatile
        echo, history = [], []
        late.create_subscription(Odometry, qos.ESTIMATE, echo.append, QoSProfile(
            depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE))
        late.create_subscription(nav_msgs_point(), qos.history_topic(qos.MEASUREMENT), history.append, QoSProfile(
            history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        newest = max(stamp_to_ns(m.header.stamp) for m in probe.received[qos.ESTIMATE])
        assert spin_until(executor, lambda: echo and len(history) >= 200, timeout=20.0)
        assert stamp_to_ns(echo[0].header.stamp) >= newest  # the present, not the first estimate (0 s)
        stamps = [stamp_to_ns(m.header.stamp) for m in history[:200]]
        # the 20 s before the join (a repeated sample, a lockstep resend, may shift it by a step)
        assert stamps == sorted(stamps) and stamps[0] > 0 and stamps[-1] - stamps[0] >= 150 * 100_000_000


def nav_msgs_point():
    from geometry_msgs.msg import PointStamped
    return PointStamped


def test_the_throttled_log_keeps_one_message_per_kind_not_per_first_words():
    """Each kind of warning (its text but for the numbers) at most once per period: a stale
    and a misaligned measurement are two kinds, so the second is not hidden by the first."""
    from scenario_nodes.runtime import ThrottledLog

    class Logger:
        def __init__(self):
            self.lines = []

        def warning(self, message):
            self.lines.append(message)

        info = error = warning

    logger = Logger()
    log = ThrottledLog(logger, period=60.0)
    log('warning', 'rejected measurement at 1.093 s is older than the estimate at 1.207 s')
    log('warning', 'rejected measurement at 1.305 s is older than the estimate at 1.400 s')
    log('warning', 'rejected measurement at 1.5 s does not fall on the estimate time 1.0 s plus steps of 0.1 s')
    log('info', 'started')
    assert len(logger.lines) == 3 and 'does not fall' in logger.lines[1]


def test_an_estimator_with_two_sensors_fuses_a_stamp_once_both_reported_and_counts_a_late_one():
    """`sensors: [camera, lidar]` (config/sensor_camera+lidar.yaml): a stamp waits for both
    topics; "nothing measured" counts as a report; a stamp whose LIDAR report was lost goes on
    with the next complete one, and the report coming after it is counted late, not fused."""
    from geometry_msgs.msg import AccelStamped, Vector3Stamped
    from rclpy.node import Node

    from scenario_nodes.codec import encode_accel, encode_measurement, encode_no_measurement
    from scenario_nodes.parameter_tables import sensor_suites
    from snn_estimator.measurements import make_model
    suite = sensor_suites()['camera+lidar']['estimator']
    models = {name: make_model(suite[f'{name}.model'], suite[f'{name}.measurement_noise'],
                               mounting_rotation=suite[f'{name}.mounting_rotation']) for name in ('camera', 'lidar')}
    x = np.array([[70.0, 30.0, -5.0, 0.0, 0.0, 0.0]])
    step = 100_000_000
    with ros_context() as (context, executor, nodes):
        probe = Node('fused_probe', context=context)
        executor.add_node(probe)
        nodes.append(probe)
        estimates = []
        probe.create_subscription(Odometry, qos.ESTIMATE, estimates.append, qos.LISTENER_QOS)
        topics = {name: probe.create_publisher(Vector3Stamped, name, qos.PUBLISHER_QOS) for name in models}
        control = probe.create_publisher(AccelStamped, qos.CONTROL, qos.PUBLISHER_QOS)
        estimator = make(EstimatorNode, context, executor, nodes, 'estimator', history_wait=0.0,
                         diagnostics_period=0.0, initial_state_dispersion=False, **suite)
        assert spin_until(executor, lambda: all(t.get_subscription_count() for t in topics.values()))

        def send(name, stamp, measured=True):
            model = models[name]
            topics[name].publish(encode_measurement(model, model.h(x)[0], stamp, name) if measured
                                 else encode_no_measurement(model, 'too_far', stamp, name))

        def stamps():
            return [stamp_to_ns(m.header.stamp) for m in estimates]

        send('camera', 0)
        spin_until(executor, lambda: False, timeout=0.1)  # within dropout_wait (0.25 s)
        assert stamps() == []  # waits for the LIDAR's report of t = 0
        send('lidar', 0, measured=False)
        assert spin_until(executor, lambda: stamps() == [0])
        control.publish(encode_accel(np.zeros(3), 0, 'lvlh'))
        assert spin_until(executor, lambda: stamps() == [0, step])
        send('camera', step)
        send('camera', 2 * step)  # the LIDAR's report of t = 0.1 s is lost
        send('lidar', 2 * step)
        control.publish(encode_accel(np.zeros(3), step, 'lvlh'))
        control.publish(encode_accel(np.zeros(3), 2 * step, 'lvlh'))
        assert spin_until(executor, lambda: stamps()[-1:] == [3 * step])
        send('lidar', step)  # late: t = 0.1 s went on without it
        spin_until(executor, lambda: estimator.values().get('late.lidar') == 1, timeout=2.0)
        values = estimator.values()
    assert values['sensors'] == 'camera,lidar' and values['assembled_incomplete'] == 1
    # three stamps fused (the LIDAR's "nothing measured" at 0 leaves the camera's sample); none empty
    assert values['late.lidar'] == 1 and values['not_measured'] == 0 and values['measurements_used'] == 3
