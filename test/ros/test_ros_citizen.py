"""The package among other ROS 2 software: any publisher reaches the loop, QoS overrides and
incompatibilities, the estimator's lifecycle through the standard services, hot standby.

Nodes run as `ros2 run` starts them (their console script, no parameter file: no sim time);
this process plays the user's tools with plain rclpy publishers of each common profile and the
standard lifecycle_msgs and parameter services, as `ros2 topic pub`, `ros2 lifecycle` and
`ros2 param` do.
"""

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('rclpy')

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import AccelStamped, PointStamped  # noqa: E402
from lifecycle_msgs.msg import State, Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, qos_profile_sensor_data  # noqa: E402
from ros_helpers import latest_status  # noqa: E402

from scenario_nodes import qos  # noqa: E402
from scenario_nodes.conversions import (  # noqa: E402
    control_to_accel,
    measurement_to_point,
    odometry_to_state,
    stamp_to_ns,
    state_to_odometry,
)

pytestmark = pytest.mark.slow
BIN = Path(sys.executable).parent
DT = 100_000_000
DEFAULT = QoSProfile(depth=10)  # what ros2 topic pub and robot_localization publish with


class User:
    """The user's side: a node in this process with publishers of a chosen profile, a
    collector of what the pipeline publishes, and service calls."""

    def __init__(self, namespace: str):
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = Node('user', namespace=namespace, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.received = {qos.ESTIMATE: [], qos.CONTROL: [], qos.DIAGNOSTICS: []}
        self.readers = {topic: self.node.create_subscription(kind, topic, self.received[topic].append, DEFAULT)
                        for topic, kind in ((qos.ESTIMATE, Odometry), (qos.CONTROL, AccelStamped),
                                            (qos.DIAGNOSTICS, DiagnosticArray))}

    def matched(self, *publishers, reading=()):
        """Wait until our ``publishers`` and the readers of ``reading`` topics matched the node,
        then a little more: DDS matches one end of a pair before the other, and a best-effort
        reader drops what comes before its own end matched."""
        ok = self.spin_until(lambda: all(p.get_subscription_count() > 0 for p in publishers)
                             and all(self.readers[t].get_publisher_count() > 0 for t in reading))
        self.spin_until(lambda: False, timeout=0.5)
        return ok

    def spin_until(self, predicate, timeout=30.0):
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.02)
        return True

    def call(self, service_type, name, request, timeout=30.0, idempotent=False):
        """Call a service as ``ros2 service call`` does. An idempotent query is sent again
        every 2 s: a response the server writes before its writer has matched our reader
        (discovery is slow on a loaded machine) is lost, and the client would wait forever."""
        client = self.node.create_client(service_type, name)
        assert self.spin_until(client.service_is_ready, timeout), name
        deadline = time.monotonic() + timeout
        while True:
            future = client.call_async(request)
            if self.spin_until(future.done, 2.0 if idempotent else timeout):
                return future.result()
            client.remove_pending_request(future)
            assert idempotent and time.monotonic() < deadline, name

    def diagnostics(self, name):
        return latest_status(self.received[qos.DIAGNOSTICS], name)

    def close(self):
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def namespace(request):
    """Each test's nodes and topics in a namespace of their own: a node of an earlier test
    that is still leaving the graph is never mistaken for this test's."""
    return '/' + re.sub(r'\W+', '_', request.node.name).strip('_')


@pytest.fixture
def user(namespace):
    person = User(namespace)
    yield person
    person.close()


@pytest.fixture
def start(tmp_path, namespace):
    """Start a node's console script as `ros2 run` does; always stopped."""
    processes = []

    def run(executable, *arguments):
        log = open(tmp_path / f'{executable}_{len(processes)}.log', 'w')
        command = [str(BIN / executable), '--ros-args', '-r', f'__ns:={namespace}', *arguments]
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ),
                                   cwd=tmp_path)
        processes.append((process, log))
        return process

    yield run
    for process, log in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(15)
            except subprocess.TimeoutExpired:
                process.kill()
        log.close()


#: A target that holds still, and a filter that starts where it is (the inputs are synthetic).
STILL = ('-p', 'initial_state:=[70.0, 30.0, -5.0, 0.0, 0.0, 0.0]', '-p', 'initial_state_dispersion:=false',
         '-p', 'history_wait:=0.0')


def feed(user, publisher_z, publisher_u, steps, start_k=0):
    """Measurements and controls of a still target, stamped k * dt."""
    x0 = np.array([70.0, 30.0, -5.0])
    for k in range(start_k, start_k + steps):
        publisher_z.publish(measurement_to_point(x0, (0, 1, 2), k * DT, 'lvlh'))
        publisher_u.publish(control_to_accel(np.zeros(3), k * DT, 'lvlh'))
        user.spin_until(lambda: False, timeout=0.02)


@pytest.mark.parametrize('profile', [DEFAULT, qos_profile_sensor_data], ids=['default', 'sensor_data'])
def test_publishers_with_the_common_profiles_drive_a_standalone_estimator(user, start, profile):
    start('estimator', *STILL)
    measurements = user.node.create_publisher(PointStamped, qos.MEASUREMENT, profile)
    controls = user.node.create_publisher(AccelStamped, qos.CONTROL, profile)
    assert user.matched(measurements, controls, reading=(qos.ESTIMATE,))
    feed(user, measurements, controls, 20)
    assert user.spin_until(lambda: len(user.received[qos.ESTIMATE]) >= 20)
    stamps = sorted({stamp_to_ns(m.header.stamp) for m in user.received[qos.ESTIMATE]})
    assert stamps[:3] == [0, DT, 2 * DT]  # the first estimate answers the first measurement
    assert all(np.all(np.isfinite(odometry_to_state(m)[0])) for m in user.received[qos.ESTIMATE])


@pytest.mark.parametrize('timing', ['any', 'grid'])
def test_a_sensor_stamping_with_the_wall_clock_at_a_jittered_10_hz(user, start, timing, tmp_path):
    """As `ros2 topic pub -r 10 /measurement ... stamp: now` or a driver on its own clock:
    with measurement_timing any every measurement is answered at its own stamp (and none
    rejected); the grid estimator rejects them as misaligned and says which parameter to set."""
    start('estimator', *STILL, '-p', f'measurement_timing:={timing}', '-p', 'diagnostics_period:=0.0')
    measurements = user.node.create_publisher(PointStamped, qos.MEASUREMENT, DEFAULT)
    controls = user.node.create_publisher(AccelStamped, qos.CONTROL, DEFAULT)
    assert user.matched(measurements, controls, reading=(qos.ESTIMATE, qos.DIAGNOSTICS))
    rng = np.random.default_rng(2)
    stamps = []
    for _ in range(30):
        stamps.append(user.node.get_clock().now().nanoseconds)
        measurements.publish(measurement_to_point(np.array([70.0, 30.0, -5.0]), (0, 1, 2), stamps[-1], 'lvlh'))
        controls.publish(control_to_accel(np.zeros(3), stamps[-1], 'lvlh'))
        user.spin_until(lambda: False, timeout=0.1 + rng.uniform(-0.03, 0.03))
    assert len(set(np.diff(stamps))) == len(stamps) - 1  # off any grid
    if timing == 'grid':
        # off the grid (the estimate meanwhile predicted over the wall clock: one or two are
        # older than it, 'stale', instead)
        assert user.spin_until(lambda: int(user.diagnostics('estimator').get(
            'measurements_rejected.misaligned', 0)) >= len(stamps) - 4), user.diagnostics('estimator')
        log = next(tmp_path.glob('estimator_*.log')).read_text()
        assert 'measurement_timing: any' in log
        return
    assert user.spin_until(lambda: len(user.received[qos.ESTIMATE]) >= len(stamps))
    answered = sorted(stamp_to_ns(m.header.stamp) for m in user.received[qos.ESTIMATE])
    assert answered == stamps
    assert user.spin_until(lambda: user.diagnostics('estimator').get('measurements_rejected') == '0')
    for message in user.received[qos.ESTIMATE]:
        position = odometry_to_state(message)[0][:3]
        assert np.all(np.abs(position - [70.0, 30.0, -5.0]) < 0.05)  # the still target


def test_a_third_party_estimator_with_the_default_profile_drives_the_controller(user, start):
    start('lqr_controller')
    estimates = user.node.create_publisher(Odometry, qos.ESTIMATE, DEFAULT)
    assert user.matched(estimates, reading=(qos.CONTROL,))
    # stamped as robot_localization stamps them: with its clock (no sim time: the wall clock)
    stamps = []
    for _ in range(5):
        stamps.append(user.node.get_clock().now().nanoseconds)
        state = np.array([70.0, 30.0, -5.0, -1.7, -0.9, 0.25])
        estimates.publish(state_to_odometry(state, None, stamps[-1], 'lvlh', 'c'))
        user.spin_until(lambda: False, timeout=0.05)
    assert user.spin_until(lambda: len(user.received[qos.CONTROL]) >= 5)
    assert sorted(stamp_to_ns(m.header.stamp) for m in user.received[qos.CONTROL])[:5] == stamps


def test_bad_input_from_a_best_effort_publisher_is_rejected_and_counted(user, start):
    start('estimator', *STILL, '-p', 'diagnostics_period:=0.0')
    measurements = user.node.create_publisher(PointStamped, qos.MEASUREMENT, qos_profile_sensor_data)
    controls = user.node.create_publisher(AccelStamped, qos.CONTROL, qos_profile_sensor_data)
    assert user.matched(measurements, controls, reading=(qos.DIAGNOSTICS,))
    feed(user, measurements, controls, 3)
    measurements.publish(measurement_to_point(np.array([np.nan, 0.0, 0.0]), (0, 1, 2), 3 * DT, 'lvlh'))
    measurements.publish(measurement_to_point(np.zeros(3), (0, 1, 2), 4 * DT, 'map'))
    assert user.spin_until(lambda: user.diagnostics('estimator').get('measurements_rejected') == '2')
    values = user.diagnostics('estimator')
    assert values['measurements_rejected.non_finite'] == '1' and values['measurements_rejected.wrong_frame'] == '1'
    assert all(np.all(np.isfinite(odometry_to_state(m)[0])) for m in user.received[qos.ESTIMATE])


def test_a_qos_override_applies_and_an_incompatible_publisher_is_counted_and_named_once(user, start, tmp_path,
                                                                                       namespace):
    # the override names the topic as resolved: here under the test's namespace
    start('estimator', *STILL, '-p', 'diagnostics_period:=0.0',
          '-p', f'qos_overrides.{namespace}/measurement.subscription.reliability:=reliable')
    sensor_data = user.node.create_publisher(PointStamped, qos.MEASUREMENT, qos_profile_sensor_data)
    assert user.spin_until(lambda: user.node.count_subscribers(qos.MEASUREMENT) > 0)
    info = user.node.get_subscriptions_info_by_topic(f'{namespace}/measurement')
    assert info and info[0].qos_profile.reliability.name == 'RELIABLE'  # the override took
    reliable = user.node.create_publisher(PointStamped, qos.MEASUREMENT, DEFAULT)
    controls = user.node.create_publisher(AccelStamped, qos.CONTROL, DEFAULT)
    assert user.matched(reliable, controls, reading=(qos.DIAGNOSTICS,))
    feed(user, reliable, controls, 2)  # the compatible publisher drives it; the diagnostics say the rest
    assert user.spin_until(lambda: int(user.diagnostics('estimator').get('qos_incompatible.measurement', 0)) >= 1)
    assert sensor_data.get_subscription_count() == 0
    log = next(tmp_path.glob('estimator_*.log')).read_text()
    assert log.count("'measurement': a publisher with incompatible QoS") == 1
    assert 'qos_overrides' in log


def lifecycle_state(user, node='estimator'):
    return user.call(GetState, f'{node}/get_state', GetState.Request(), idempotent=True).current_state.label


def change(user, transition, node='estimator'):
    request = ChangeState.Request(transition=Transition(id=transition))
    return user.call(ChangeState, f'{node}/change_state', request).success


def test_the_estimator_walks_its_lifecycle_through_the_standard_services(user, start):
    start('estimator', *STILL, '-p', 'autostart:=false')
    measurements = user.node.create_publisher(PointStamped, qos.MEASUREMENT, DEFAULT)
    controls = user.node.create_publisher(AccelStamped, qos.CONTROL, DEFAULT)
    assert lifecycle_state(user) == 'unconfigured'
    assert user.node.count_publishers(qos.ESTIMATE) == 0 and user.node.count_subscribers(qos.MEASUREMENT) == 0
    assert change(user, Transition.TRANSITION_CONFIGURE) and lifecycle_state(user) == 'inactive'
    assert user.matched(measurements, controls)
    # inactive: no `estimate` publisher in the graph, so a plant does not start for it
    assert user.node.count_publishers(qos.ESTIMATE) == 0
    feed(user, measurements, controls, 5)  # inactive: runs on its inputs, publishes nothing
    user.spin_until(lambda: False, timeout=0.5)
    assert user.received[qos.ESTIMATE] == []
    assert change(user, Transition.TRANSITION_ACTIVATE) and lifecycle_state(user) == 'active'
    assert user.spin_until(lambda: user.received[qos.ESTIMATE])  # its current estimate at once
    assert stamp_to_ns(user.received[qos.ESTIMATE][0].header.stamp) == 5 * DT  # warm: it ran while inactive
    feed(user, measurements, controls, 5, start_k=5)
    assert user.spin_until(lambda: max(stamp_to_ns(m.header.stamp) for m in user.received[qos.ESTIMATE]) == 10 * DT)
    assert change(user, Transition.TRANSITION_DEACTIVATE) and lifecycle_state(user) == 'inactive'
    published = len(user.received[qos.ESTIMATE])
    feed(user, measurements, controls, 5, start_k=10)
    user.spin_until(lambda: False, timeout=0.5)
    assert len(user.received[qos.ESTIMATE]) == published
    assert change(user, Transition.TRANSITION_CLEANUP) and lifecycle_state(user) == 'unconfigured'
    assert user.spin_until(lambda: user.node.count_publishers(qos.ESTIMATE) == 0)
    assert change(user, Transition.TRANSITION_UNCONFIGURED_SHUTDOWN) and lifecycle_state(user) == 'finalized'


def test_a_bad_value_fails_the_configure_transition_naming_the_parameter(user, start, tmp_path):
    start('estimator', '-p', 'autostart:=false', '-p', 'boundary_layer:=[-0.1]')
    assert lifecycle_state(user) == 'unconfigured'
    assert not change(user, Transition.TRANSITION_CONFIGURE)
    assert lifecycle_state(user) == 'unconfigured'
    log = next(tmp_path.glob('estimator_*.log'))
    assert user.spin_until(lambda: 'boundary_layer (delta) must be > 0' in log.read_text())
    assert State.PRIMARY_STATE_UNCONFIGURED == 1
