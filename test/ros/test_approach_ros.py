"""The approach over ROS (issue 39, part 4): the four nodes with the approach scenario's
parameters (scenario_nodes.parameter_tables.scenarios) fly the offline loop
(snn_estimator.sim.approach.fly_approach) step for step, guidance events included; the
multi-process demo flies 5 km to contact within the Done-when limits (slow)."""

import numpy as np
import pytest

pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from ros_helpers import Probe, make, ros_context, spin_until  # noqa: E402

from scenario_nodes import qos  # noqa: E402
from scenario_nodes.controller_node import ControllerNode  # noqa: E402
from scenario_nodes.conversions import (  # noqa: E402
    GUIDANCE_STATUS,
    diagnostic_values,
    guidance_end,
    guidance_event,
    odometry_to_state,
    stamp_to_ns,
)
from scenario_nodes.core_objects import observability_manoeuvre  # noqa: E402
from scenario_nodes.estimator_node import EstimatorNode  # noqa: E402
from scenario_nodes.parameter_tables import APPROACH_MODEL, CONTROLLER, scenarios, sensor_suites  # noqa: E402
from scenario_nodes.plant_node import PlantNode  # noqa: E402
from scenario_nodes.sensor_node import SensorNode  # noqa: E402
from snn_estimator.catalog import DEFAULT_FILTER  # noqa: E402
from snn_estimator.sim.approach import approach_scenario, fly_approach  # noqa: E402
from snn_tools.bags.approach import ros_results  # noqa: E402
from snn_tools.bags.data import read_bag  # noqa: E402
from snn_tools.run.demo import run_pipeline  # noqa: E402

NS = 1_000_000_000


def fly_over_ros(steps: int, kind: str = DEFAULT_FILTER, changes=None):
    """The approach's four nodes in one process for ``steps`` 1 s steps (``changes``: node ->
    parameter values): estimates and truths by stamp, the guidance events (stamp, event,
    phase) and the plant's final values."""
    values = scenarios()['approach']
    for node, node_changes in (changes or {}).items():
        values[node] = {**values[node], **node_changes}
    with ros_context() as (context, executor, nodes):
        probe = Probe(context, executor, nodes, publish=False)
        events = []
        probe.node.create_subscription(DiagnosticArray, qos.GUIDANCE, events.append, qos.LISTENER_QOS)
        make(ControllerNode, context, executor, nodes, 'lqr_controller', **values['lqr_controller'])
        make(EstimatorNode, context, executor, nodes, 'estimator', filter_type=kind, **values['estimator'])
        make(SensorNode, context, executor, nodes, 'position_sensor', **values['position_sensor'])
        plant = make(PlantNode, context, executor, nodes, 'cw_plant',
                     **{'duration': float(steps), **values['cw_plant'], 'control_timeout': 30.0})
        finished = spin_until(executor, lambda: plant.values()['done'] and max(
            (stamp_to_ns(m.header.stamp) for m in probe.received[qos.ESTIMATE]), default=-1)
            >= plant.values()['steps'] * NS, timeout=300.0)
        assert finished, 'the in-process approach did not complete'
        spin_until(executor, lambda: False, timeout=0.3)  # the last events
        estimates = {stamp_to_ns(m.header.stamp): odometry_to_state(m) for m in probe.received[qos.ESTIMATE]}
        truths = {stamp_to_ns(m.header.stamp): odometry_to_state(m)[0] for m in probe.received[qos.TRUTH]}
        said = [(stamp_to_ns(m.header.stamp) / NS, diagnostic_values(s)['event'], diagnostic_values(s)['phase'])
                for m in events for s in m.status if s.name == GUIDANCE_STATUS]
        return estimates, truths, said, plant.values()


def test_the_ros_lockstep_approach_equals_the_offline_loop_through_the_first_go_and_into_the_transfer():
    """1200 s: the 5 km hold, its go (from the estimate and its covariance, sent over Odometry),
    and the transfer toward 2 km, where the estimator node's NIS recovery would re-initialise
    the SNN-EKF at 1085 s (the approach turns it off, as offline): the same estimates, truths
    and events as offline."""
    steps = 1200
    estimates, truths, said, plant = fly_over_ros(steps, changes={'cw_plant': {'duration': float(steps)}})
    assert plant['steps'] == steps and plant['control_timeouts'] == 0
    offline = fly_approach(approach_scenario(APPROACH_MODEL, plant=APPROACH_MODEL), DEFAULT_FILTER,
                           max_duration=float(steps), record=True)[0]
    trajectory = offline['trajectory']
    assert len(trajectory['time']) == steps + 1
    for k in range(steps + 1):
        x_hat, covariance = estimates[k * NS]
        np.testing.assert_allclose(truths[k * NS], trajectory['truth'][k], rtol=0, atol=1e-9)
        np.testing.assert_allclose(x_hat, trajectory['estimate'][k], rtol=0, atol=1e-9)
        np.testing.assert_allclose(covariance[:3, :3], trajectory['covariance'][k][:3, :3], rtol=1e-12, atol=1e-15)
    # the go at 5 km was decided, then the transfer flown, as offline
    assert [(t, name) for t, name, _ in said] == [tuple(e) for e in offline['events']]
    assert said and said[0][1] == 'go 5 km' and said[0][2] == 'transfer'
    assert truths[steps * NS][0] > -5000.0 + 10.0  # moving toward the 2 km hold


def test_the_plant_ends_the_run_at_the_port_whatever_its_duration():
    """stop_at_port: the run ends with the step that brings the truth to the port's plane (a
    start 0.5 m behind it at 4 cm/s, steered to 1 m beyond it: a few of the 40 steps asked for)."""
    start = [-0.5, 0.0, 0.0, 0.04, 0.0, 0.0]
    _, truths, _, plant = fly_over_ros(40, changes={
        'cw_plant': {'initial_state': start, 'duration': 40.0}, 'estimator': {'initial_state': start},
        'lqr_controller': {'guidance': 'none', 'setpoint': [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]}})
    assert plant['ended_by'] == 'stop' and plant['steps'] < 40
    last = max(truths)
    assert last == plant['steps'] * NS and truths[last][0] >= 0.0 > truths[last - NS][0]
    assert plant['contact_closing_speed'] == truths[last][3]  # in the plant's final diagnostics
    assert plant['contact_lateral'] == np.hypot(truths[last][1], truths[last][2])


def test_a_guidance_event_ends_the_run_only_when_the_approach_ended_without_contact():
    assert guidance_end(guidance_event(7 * NS, 'c', 'abort', 'abort', {'corridor_radius': 1.0})) == 7 * NS
    assert guidance_end(guidance_event(8 * NS, 'c', 'no_go 5 km', 'no_go', {})) == 8 * NS
    assert guidance_end(guidance_event(9 * NS, 'c', 'go 5 km', 'transfer', {'error': 0.1})) is None


@pytest.mark.slow
def test_make_demo_scenario_approach_flies_5_km_to_contact_within_the_limits_as_the_offline_loop(tmp_path):
    """The Done-when of issue 39's demo: snn_demo --scenario approach (five processes, lockstep,
    the default estimator) reaches contact within 0.1 m laterally below 5 cm/s, enters the
    keep-out sphere only after its go and never leaves the corridor; and it is the offline run
    of the same seed, step for step (13472 steps, ~50 s of loop here)."""
    result = run_pipeline(tmp_path / 'run', scenario='approach', timeout=900.0)
    approach = ros_results(read_bag(result['bag']))
    contact = approach['contact']
    assert approach['outcome'] == 'contact' and approach['success']
    assert contact['closing_speed'] < 0.05 and contact['lateral'] < 0.1
    assert approach['keep_out_entry'] is not None and not approach['keep_out_entry']['before_go']
    assert approach['corridor_exit_steps'] == 0
    offline = fly_approach(approach_scenario(APPROACH_MODEL, plant=APPROACH_MODEL), DEFAULT_FILTER)[0]
    assert approach['steps'] == offline['steps']
    assert contact == pytest.approx(offline['contact'], rel=0, abs=1e-9)
    assert [(e['time'], e['event']) for e in approach['events']] == [tuple(e) for e in offline['events']][:-1]
    assert offline['events'][-1][1] == 'contact'  # which the plant, seeing the truth, ends the run on


@pytest.mark.slow
def test_a_no_go_at_the_first_hold_ends_the_run_after_its_step():
    """end_on_guidance over ROS: a filter started with 100 m of sigma on a sensor of 1 km never
    brings its 3-sigma under the 5 km hold's 10 m (54 m after 3000 samples), so the hold is a
    no-go at its 3000 s timeout; the plant ends the run after that step instead of flying on
    to its duration (~40-60 s here)."""
    noise = {'measurement_noise': [1e6]}
    _, truths, said, plant = fly_over_ros(4000, changes={
        'cw_plant': {'duration': 4000.0}, 'position_sensor': noise,
        'estimator': {**noise, 'initial_covariance': [1e4, 1e4, 1e4, 1e-4, 1e-4, 1e-4]}})
    assert [(t, name, phase) for t, name, phase in said] == [(3000.0, 'no_go 5 km', 'no_go'),
                                                             (3000.0, 'no_go', 'no_go')]
    assert plant['ended_by'] == 'requested' and plant['steps'] == 3001 and max(truths) == 3001 * NS


def _over_ros_and_offline(tmp_path, sensor: str, steps: int):
    """The first ``steps`` s of the approach on the sensor suite ``sensor``: the bag of the ROS
    run (a node per sensor, lockstep) and the offline loop's recorded run of the same scenario."""
    result = run_pipeline(tmp_path / 'run', scenario='approach', sensor=sensor, duration=float(steps),
                          timeout=300.0)
    offline = fly_approach(approach_scenario(APPROACH_MODEL, plant=APPROACH_MODEL, sensors=sensor),
                           DEFAULT_FILTER, max_duration=float(steps), record=True)[0]
    return read_bag(result['bag']), offline


@pytest.mark.slow
def test_the_approach_on_a_sensor_node_per_sensor_equals_the_offline_by_range_loop_through_the_lidars_arrival(
        tmp_path):
    """``make demo SCENARIO=approach SENSOR=by_range``: relative GPS, the LIDAR and the docking
    camera each their own node and topic, the estimator fusing them with the offline R_hat
    (by_range_noise). Over the first 2600 s, through the LIDAR's arrival inside 3 km (2548 s),
    every estimate and truth is fly_approach(approach_scenario(sensors='by_range'))'s, and every
    sensor answered every truth, "nothing measured" outside its range (~25 s here)."""
    steps = 2600
    data, offline = _over_ros_and_offline(tmp_path, 'by_range', steps)
    trajectory = offline['trajectory']
    ranges = np.linalg.norm(np.asarray(trajectory['truth'])[:, :3], axis=1)
    assert ranges[0] > 3000.0 > ranges[-1]  # the window crosses the LIDAR's 3 km
    for times, values, expected in ((data.truth_t, data.truth, trajectory['truth']),
                                    (data.estimate_t, data.estimate, trajectory['estimate'])):
        k = np.round(times).astype(int)
        inside = k <= steps
        assert sorted(k[inside]) == list(range(steps + 1))
        np.testing.assert_allclose(values[inside], np.asarray(expected)[k[inside]], rtol=0, atol=1e-9)
    # every truth answered; the samples offline took (its loop measures the truths before the last)
    for name, offline_name in (('relative_gps', 'relative_gps'), ('lidar', 'range_azimuth_elevation'),
                               ('camera', 'docking_camera')):
        stamps, said = data.reports[name]
        assert len(stamps) == steps + 1, name
        assert said[stamps < steps * NS].sum() == offline['sensor_samples'][offline_name], name
    assert offline['sensor_samples']['range_azimuth_elevation'] > 0 == offline['sensor_samples']['docking_camera']


def test_the_angles_only_approach_over_ros_equals_the_offline_loop_through_the_hops_first_burn(tmp_path):
    """``make demo SCENARIO=approach SENSOR=angles_far``: the far camera (line of sight only, from
    1 km out), the LIDAR and the docking camera each their own node, the estimator started with
    the range uncertainty's P0, the controller's guidance flying the out-of-plane hop the suite
    file sets (observability_manoeuvre). Over the first 600 s, through the hop's first burn 300 s
    after the start on the 5 km hold, every truth, estimate and position variance is
    fly_approach(approach_scenario(sensors='angles_far'))'s, the hop's event comes on `guidance`
    at the same second, and only the far camera measured (10-25 s here)."""
    steps = 600
    data, offline = _over_ros_and_offline(tmp_path, 'angles_far', steps)
    trajectory = offline['trajectory']
    variance = np.diagonal(np.asarray(trajectory['covariance']), axis1=1, axis2=2)
    for times, values, expected, tolerance in (
            (data.truth_t, data.truth, trajectory['truth'], 1e-9),
            (data.estimate_t, data.estimate, trajectory['estimate'], 1e-9),
            (data.estimate_t, data.estimate_variance, variance, 1e-9 * variance[0, 0])):
        k = np.round(times).astype(int)
        inside = k <= steps
        assert sorted(k[inside]) == list(range(steps + 1))
        np.testing.assert_allclose(values[inside], np.asarray(expected)[k[inside]], rtol=0, atol=tolerance)
    assert variance[0, 0] == pytest.approx((0.02 * 5000.0) ** 2)  # the range uncertainty's P0
    # the hop's first burn, said on `guidance` as offline; the truth leaves V-bar out of plane
    assert [(t, event) for t, event, _ in data.guidance] == [tuple(e) for e in offline['events']] == [
        (300.0, 'hop 5 km')]
    assert abs(trajectory['truth'][300][1]) < 1.0 < 50.0 < abs(trajectory['truth'][steps][1])
    for name, offline_name in (('far_camera', 'line_of_sight'), ('lidar', 'range_azimuth_elevation'),
                               ('camera', 'docking_camera')):
        stamps, said = data.reports[name]
        assert len(stamps) == steps + 1, name
        assert said[stamps < steps * NS].sum() == offline['sensor_samples'][offline_name], name
    assert offline['sensor_samples']['line_of_sight'] == steps  # angles only at 5 km


def test_the_controller_refuses_an_observability_manoeuvre_it_does_not_fly():
    """A bad manoeuvre name names the choices; a hop without the approach guidance says what to
    set; a hop at a hold the approach has not names its holds (the core's check)."""
    with ros_context() as (context, executor, nodes):
        with pytest.raises(ValueError, match=r"observability_manoeuvre must be one of none \| out_of_plane_hop; "
                                             r"got 'hop'"):
            make(ControllerNode, context, executor, nodes, 'lqr_controller', guidance='approach',
                 observability_manoeuvre='hop')
        with pytest.raises(ValueError, match='is flown by the approach guidance: set guidance approach'):
            make(ControllerNode, context, executor, nodes, 'lqr_controller', observability_manoeuvre='out_of_plane_hop')
        with pytest.raises(ValueError, match="hold must be one of 5 km, 2 km, 250 m, 20 m; got '3 km'"):
            make(ControllerNode, context, executor, nodes, 'lqr_controller', guidance='approach',
                 observability_manoeuvre='out_of_plane_hop', observability_hold='3 km')
        with pytest.raises(ValueError, match='non-zero size'):
            make(ControllerNode, context, executor, nodes, 'lqr_controller', guidance='approach',
                 observability_manoeuvre='out_of_plane_hop', observability_hop_size=0.0)


def test_the_angles_suite_file_sets_the_offline_scenarios_hop_and_the_others_fly_none():
    """The controller's manoeuvre from the angles_far suite's values is approach_scenario's
    (ANGLES_HOP); the by_range suite and the approach scenario leave it at none."""
    suites = sensor_suites()
    values = {spec.name: spec.default for spec in CONTROLLER}
    hop = observability_manoeuvre({**values, **suites['angles_far']['lqr_controller']})
    assert hop == approach_scenario(APPROACH_MODEL, plant=APPROACH_MODEL, sensors='angles_far').manoeuvre
    for changes in (suites['by_range']['lqr_controller'], scenarios()['approach']['lqr_controller']):
        assert observability_manoeuvre({**values, **changes}) is None
