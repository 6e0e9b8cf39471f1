"""The sensor node with a measurement model other than position, in-process: its messages are
h(x) of the truth plus the offline sensor's noise, and samples it cannot measure are counted,
never published. The node runs in its own namespace, so no other node's truth or diagnostics
on the test's domain can reach these tests."""

import math

import numpy as np
import pytest

pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import Vector3Stamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from ros_helpers import latest_status, make, ros_context, spin_until  # noqa: E402
from sensor_msgs.msg import Range  # noqa: E402

from scenario_nodes import qos  # noqa: E402
from scenario_nodes.conversions import message_to_measurement, stamp_to_ns, state_to_odometry  # noqa: E402
from scenario_nodes.sensor_node import SensorNode  # noqa: E402
from snn_estimator.measurements import make_model  # noqa: E402
from snn_estimator.plant.sensors import MeasurementSensor  # noqa: E402

NAMESPACE = '/sensor_model_test'
REMAP = ['--ros-args', '-r', f'__ns:={NAMESPACE}', '-r', 'measurement:=lidar']


class Probe:
    """Publishes truths to the sensor and collects its measurements and diagnostics."""

    def __init__(self, context, executor, nodes, message_type):
        from rclpy.node import Node
        self.node = Node('sensor_model_probe', namespace=NAMESPACE, context=context)
        executor.add_node(self.node)
        nodes.append(self.node)
        self.received, self.statuses = [], []
        self.node.create_subscription(message_type, 'lidar', self.received.append, qos.LISTENER_QOS)
        self.node.create_subscription(DiagnosticArray, qos.DIAGNOSTICS, self.statuses.append, qos.LISTENER_QOS)
        self.truth = self.node.create_publisher(Odometry, qos.TRUTH, qos.PUBLISHER_QOS)

    def ready(self) -> bool:
        return self.node.count_subscribers(qos.TRUTH) > 0 and self.node.count_publishers('lidar') > 0

    def diagnostics(self) -> dict:
        return latest_status(self.statuses, 'position_sensor')
LIDAR = {'model': 'range_azimuth_elevation', 'measurement_noise': [1e-4, 1e-6, 1e-6], 'observer': 'chaser',
         'field_of_view': math.radians(60.0), 'max_range': 200.0, 'mounting_offset': [0.5, 0.0, -0.2],
         'mounting_rotation': [0.0, 0.0, 1.0, 0.0], 'seed': 4, 'diagnostics_period': 0.0,
         'sensor_frame_id': 'lidar'}


def test_range_azimuth_elevation_sensor_publishes_h_of_the_truth_and_counts_what_it_cannot_see():
    # the chaser ahead of the target on V-bar looks back along -x: the mounting turns the sensor
    # 180 deg about z, so its boresight (+x) is LVLH -x
    truths = [np.array([70.0, 10.0, -5.0, -0.5, 0.1, 0.0]),
              np.array([60.0, -8.0, 6.0, -0.4, 0.0, 0.1]),
              np.array([20.0, 60.0, 0.0, 0.0, 0.0, 0.0]),    # 72 deg off the boresight: out of view
              np.array([250.0, 0.0, 0.0, 0.0, 0.0, 0.0]),    # beyond max_range
              np.array([50.0, 3.0, 2.0, -0.3, 0.0, 0.0])]
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes, Vector3Stamped)
        received = probe.received
        make(SensorNode, context, executor, nodes, 'position_sensor', cli_args=REMAP, **LIDAR)
        assert spin_until(executor, probe.ready)
        for k, x in enumerate(truths):
            probe.truth.publish(state_to_odometry(x, None, (k + 1) * 100_000_000, 'lvlh', 'chaser'))
            assert spin_until(executor, lambda k=k: len(probe.statuses) >= k + 1)
        assert spin_until(executor, lambda: len(received) == 5)
        assert spin_until(executor, lambda: probe.diagnostics().get('measurement_rejected') == '2')
        values = probe.diagnostics()
        assert values['truth_rejected'] == '0'
        assert values['measurement_rejected.out_of_view'] == '1' and values['measurement_rejected.too_far'] == '1'
        assert values['measurements_published'] == '5'  # 3 measured, 2 "nothing measured"

    model = make_model(LIDAR['model'], LIDAR['measurement_noise'])
    assert [stamp_to_ns(m.header.stamp) for m in received] == [k * 100_000_000 for k in range(1, 6)]
    nothing = [received.pop(3), received.pop(2)]  # out of view, beyond range: said, not measured
    assert all(message_to_measurement(model, msg) is None and msg.header.frame_id == 'lidar' for msg in nothing)

    model = make_model(LIDAR['model'], LIDAR['measurement_noise'], observer='chaser',
                       field_of_view=LIDAR['field_of_view'], max_range=200.0,
                       mounting_offset=LIDAR['mounting_offset'], mounting_rotation=LIDAR['mounting_rotation'])
    offline = MeasurementSensor(model, seeds=[4])
    expected = [offline.measure(x[None]) for x in truths]
    measured = [e for e in expected if e.valid[0]]
    assert [stamp_to_ns(m.header.stamp) for m in received] == [100_000_000, 200_000_000, 500_000_000]
    sigma = np.sqrt(np.diagonal(model.noise))
    for msg, sample, x in zip(received, measured, [truths[0], truths[1], truths[4]]):
        assert msg.header.frame_id == 'lidar'
        z = message_to_measurement(model, msg)
        np.testing.assert_array_equal(z, sample.z[0])  # the offline sensor's numbers, exactly
        truth_z = model.h(x)
        assert np.all(np.abs(model.residual(z, truth_z)) < 5 * sigma)
        # and h(x) by hand: the boresight is LVLH -x, so the target (at -p - d from the sensor)
        # lies near the boresight: range |p + d|, small angles
        assert abs(truth_z[0] - np.linalg.norm(x[:3] + LIDAR['mounting_offset'])) < 1e-12
        assert abs(truth_z[1]) < 0.3 and abs(truth_z[2]) < 0.3


def test_range_sensor_publishes_sensor_msgs_range_with_its_limits():
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes, Range)
        received = probe.received
        make(SensorNode, context, executor, nodes, 'position_sensor', cli_args=REMAP, model='range',
             measurement_noise=[1e-6], min_range=1.0, max_range=500.0, sensor_frame_id='rf')
        assert spin_until(executor, probe.ready)
        probe.truth.publish(state_to_odometry(np.array([30.0, 40.0, 0, 0, 0, 0]), None, 0, 'lvlh', 'chaser'))
        assert spin_until(executor, lambda: received)
        msg = received[0]
        assert abs(msg.range - 50.0) < 0.01 and (msg.min_range, msg.max_range) == (1.0, 500.0)
        offline = MeasurementSensor(make_model('range', [1e-6], min_range=1.0, max_range=500.0), seeds=[0])
        z = offline.measure(np.array([[30.0, 40.0, 0, 0, 0, 0]])).z[0, 0]
        assert msg.range == float(np.float32(z))  # the offline number, rounded to Range's float32
        assert msg.header.frame_id == 'rf' and abs(msg.variance - 1e-6) < 1e-12


@pytest.mark.parametrize('changes, message', [
    ({'model': 'line_of_sight', 'measurement_noise': [1e-6, 1e-6, 1e-6]}, 'R of line_of_sight, 2x2'),
    ({'model': 'range', 'mounting_rotation': [0.0, 0.0, 0.0, 3.0]}, 'unit quaternion'),
])
def test_a_bad_model_parameter_refuses_to_build_the_node(changes, message):
    with ros_context() as (context, executor, nodes):
        with pytest.raises(ValueError, match=message):
            make(SensorNode, context, executor, nodes, 'position_sensor', **changes)


def test_a_resent_truth_that_gave_no_measurement_is_neither_measured_nor_counted_again():
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes, Vector3Stamped)
        received = probe.received
        make(SensorNode, context, executor, nodes, 'position_sensor', cli_args=REMAP, **LIDAR)
        assert spin_until(executor, probe.ready)
        hidden = state_to_odometry(np.array([-70.0, 0.0, 0.0, 0, 0, 0]), None, 100_000_000, 'lvlh', 'chaser')
        for _ in range(3):  # the plant's lockstep resend of the same stamp
            probe.truth.publish(hidden)
        seen = state_to_odometry(np.array([70.0, 0.0, 0.0, 0, 0, 0]), None, 200_000_000, 'lvlh', 'chaser')
        probe.truth.publish(seen)
        assert spin_until(executor, lambda: len(received) == 1)
        assert spin_until(executor, lambda: probe.diagnostics().get('measurements_published') == '1')
        values = probe.diagnostics()
        assert values['measurement_rejected'] == '1' and values['measurement_rejected.out_of_view'] == '1'
        assert values['truth_rejected'] == '0'


def test_measurement_period_samples_on_its_own_grid_of_the_truth_stamps():
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes, Vector3Stamped)
        make(SensorNode, context, executor, nodes, 'position_sensor', cli_args=REMAP,
             **{**LIDAR, 'measurement_period': 0.25})
        assert spin_until(executor, probe.ready)
        stamps = [100, 200, 300, 400, 500, 600, 700, 800, 900]  # ms
        for stamp in stamps:
            probe.truth.publish(state_to_odometry(np.array([70.0, 0.0, 0.0, 0, 0, 0]), None, stamp * 1_000_000,
                                                  'lvlh', 'chaser'))
        assert spin_until(executor, lambda: len(probe.received) == 9)
        executor.spin_once(timeout_sec=0.2)
        # due at 100, then 350, 600, 850 ms: sampled at the first truth at or after each (a
        # period counted from each sample instead would give 100, 400, 700); every truth between
        # is said "nothing measured" (publish_not_measured: a loop's estimator need not wait)
        assert [stamp_to_ns(m.header.stamp) // 1_000_000 for m in probe.received] == stamps
        model = make_model(LIDAR['model'], LIDAR['measurement_noise'])
        measured = [stamp_to_ns(m.header.stamp) // 1_000_000 for m in probe.received
                    if message_to_measurement(model, m) is not None]
        assert measured == [100, 400, 600, 900]
        values = probe.diagnostics()
        assert values['measurement_rejected'] == '0' and values['truth_rejected'] == '0'


def test_with_publish_not_measured_false_a_sample_out_of_view_is_not_published():
    """The older behaviour, kept as an option: only measurements leave the sensor."""
    truths = [np.array([20.0, 60.0, 0.0, 0.0, 0.0, 0.0]), np.array([70.0, 10.0, -5.0, -0.5, 0.1, 0.0])]
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes, Vector3Stamped)
        make(SensorNode, context, executor, nodes, 'position_sensor', cli_args=REMAP,
             **dict(LIDAR, publish_not_measured=False))
        assert spin_until(executor, probe.ready)
        for k, x in enumerate(truths):
            probe.truth.publish(state_to_odometry(x, None, (k + 1) * 100_000_000, 'lvlh', 'chaser'))
            assert spin_until(executor, lambda k=k: len(probe.statuses) >= k + 1)
        assert spin_until(executor, lambda: len(probe.received) == 1)
        spin_until(executor, lambda: False, timeout=0.3)
        assert [stamp_to_ns(m.header.stamp) for m in probe.received] == [200_000_000]
        assert probe.diagnostics()['measurement_rejected.out_of_view'] == '1'


#: Ranges (m) behind the target on V-bar across the approach's sensors, and which of them each
#: sensor of the by_range suite measures (docs/decisions.md, 72: relative GPS from 500 m out,
#: the LIDAR 1.8 m - 3 km, the docking camera 5 cm - 30 m).
BY_RANGE_RANGES = (5000.0, 3100.0, 2900.0, 600.0, 400.0, 40.0, 20.0, 1.0, 0.03)
BY_RANGE_MEASURES = {'relative_gps': (1, 1, 1, 1, 0, 0, 0, 0, 0), 'lidar': (0, 0, 1, 1, 1, 1, 1, 0, 0),
                     'camera': (0, 0, 0, 0, 0, 0, 1, 1, 0)}


@pytest.mark.parametrize('name', list(BY_RANGE_MEASURES))
def test_each_sensor_node_of_the_approach_by_range_answers_every_truth_and_measures_only_in_its_range(name):
    """The by_range suite's sensor nodes (config/sensor_by_range.yaml's values), each alone: a
    truth within its range gives a measurement, one outside it "nothing measured" at that stamp
    (relative GPS: a PointStamped of NaN; the LIDAR and the camera: a Vector3Stamped of NaN),
    counted as too_close / too_far; nothing is left unanswered."""
    from geometry_msgs.msg import PointStamped

    from scenario_nodes.parameter_tables import sensor_suites
    values = {**sensor_suites()['by_range'][name], 'diagnostics_period': 0.0}
    model = make_model(values['model'], values['measurement_noise'], min_range=values['min_range'],
                       max_range=values['max_range'])
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes, PointStamped if model.message_form == 'point' else Vector3Stamped)
        make(SensorNode, context, executor, nodes, 'position_sensor', cli_args=REMAP, **values)
        assert spin_until(executor, probe.ready)
        for k, r in enumerate(BY_RANGE_RANGES):
            probe.truth.publish(state_to_odometry(np.array([-r, 0.0, 0.0, 0.0, 0.0, 0.0]), None,
                                                  (k + 1) * 1_000_000_000, 'lvlh', 'chaser'))
        assert spin_until(executor, lambda: len(probe.received) == len(BY_RANGE_RANGES))
        spin_until(executor, lambda: probe.diagnostics().get('measurements_published') == str(len(BY_RANGE_RANGES)))
        samples = [message_to_measurement(model, m) for m in probe.received]
        assert [stamp_to_ns(m.header.stamp) for m in probe.received] == [
            (k + 1) * 1_000_000_000 for k in range(len(BY_RANGE_RANGES))]
        assert tuple(int(z is not None) for z in samples) == BY_RANGE_MEASURES[name]
        for z, r in zip(samples, BY_RANGE_RANGES):
            if z is not None:  # x (position) or the range (angle sensors) within a few sigmas
                assert abs(abs(z[0]) - r) < 5.0 + 1e-3 * r, (name, r, z)
        values = probe.diagnostics()
        unmeasured = BY_RANGE_MEASURES[name].count(0)
        assert int(values['measurement_rejected.too_close']) + int(values.get('measurement_rejected.too_far', 0)) \
            == int(values['measurement_rejected']) == unmeasured


def test_the_far_camera_node_of_the_angles_suite_measures_the_line_of_sight_from_1_km_out_within_its_cone():
    """config/sensor_angles_far.yaml's far_camera alone: on V-bar it measures the line of sight
    (azimuth and elevation within 5 sigma of zero) at 5 km, 3.1 km, 2.9 km and 1.2 km, and says
    "nothing measured" at 900 m and 40 m (too_close: closer, the target is resolved); 1 km off
    V-bar at 5 km (11.3 deg off the boresight, outside the 18 deg cone) is out of view; every
    truth answered."""
    from scenario_nodes.parameter_tables import sensor_suites
    values = {**sensor_suites()['angles_far']['far_camera'], 'diagnostics_period': 0.0}
    model = make_model(values['model'], values['measurement_noise'], min_range=values['min_range'])
    positions = [(-r, 0.0) for r in (5000.0, 3100.0, 2900.0, 1200.0, 900.0, 40.0)] + [(-5000.0, 1000.0)]
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes, Vector3Stamped)
        make(SensorNode, context, executor, nodes, 'position_sensor', cli_args=REMAP, **values)
        assert spin_until(executor, probe.ready)
        for k, (x, y) in enumerate(positions):
            probe.truth.publish(state_to_odometry(np.array([x, y, 0.0, 0.0, 0.0, 0.0]), None,
                                                  (k + 1) * 1_000_000_000, 'lvlh', 'chaser'))
        assert spin_until(executor, lambda: len(probe.received) == len(positions))
        spin_until(executor, lambda: probe.diagnostics().get('measurements_published') == str(len(positions)))
        samples = [message_to_measurement(model, m) for m in probe.received]
        assert [int(z is not None) for z in samples] == [1, 1, 1, 1, 0, 0, 0]
        for z in samples[:4]:
            assert z.shape == (2,) and np.all(np.abs(z) < 5.0 * 2e-4), z
        values = probe.diagnostics()
        assert int(values['measurement_rejected.too_close']) == 2
        assert int(values['measurement_rejected.out_of_view']) == 1 == int(values['measurement_rejected']) - 2
