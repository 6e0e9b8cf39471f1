"""The approach (issue 39, parts 2-3): the go/no-go of a hold alone, the corridor and its abort,
the CAM's direction, and a closed loop from the 5 km hold to the go at the 2 km hold."""

import numpy as np
import pytest

from snn_estimator.filters.estimators import make_estimator
from snn_estimator.models import ClohessyWiltshire
from snn_estimator.plant.approach import ApproachGuidance, Corridor, GoNoGo, HoldPoint, Leg, position_three_sigma
from snn_estimator.plant.sensors import FusedSensor
from snn_estimator.plant.truth import Plant
from snn_estimator.sim.approach import (
    HOLDS,
    LEGS,
    RELATIVE_GPS_MIN_RANGE,
    approach_scenario,
    fly_approach,
    passive_safety,
)

HOLD = HoldPoint('250 m', 250.0, error_bound=1.0, sigma_bound=0.5, speed_bound=0.01, dwell=100.0, timeout=1000.0)
SMALL_P = np.diag([1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-6])  # 3-sigma 0.095 m


def at_hold(offset=(0.0, 0.0, 0.0), velocity=(0.0, 0.0, 0.0)):
    return np.concatenate([HOLD.state[:3] + np.array(offset), velocity])


def test_the_position_three_sigma_is_three_roots_of_the_largest_eigenvalue_of_the_position_block():
    rotation = np.linalg.qr(np.random.default_rng(0).standard_normal((3, 3)))[0]
    covariance = np.eye(6) * 5.0  # velocities do not count
    covariance[:3, :3] = rotation @ np.diag([0.01, 0.04, 0.0025]) @ rotation.T
    assert position_three_sigma(covariance) == pytest.approx(3 * 0.2, rel=1e-12)


def test_a_hold_is_a_go_after_its_dwell_of_good_estimates_and_a_bad_one_restarts_the_dwell():
    gonogo = GoNoGo(HOLD, arrived=0.0)
    for t in range(0, 100):
        assert gonogo.update(float(t), at_hold((0.5, 0.0, 0.0)), SMALL_P) is None
    assert gonogo.update(100.0, at_hold(), SMALL_P) == 'go'
    assert gonogo.decided_at == 100.0
    assert gonogo.update(101.0, at_hold((50.0, 0.0, 0.0)), SMALL_P) == 'go'  # final

    gonogo = GoNoGo(HOLD, arrived=0.0)
    for t in range(0, 60):
        assert gonogo.update(float(t), at_hold(), SMALL_P) is None
    assert gonogo.update(60.0, at_hold((0.0, 1.1, 0.0)), SMALL_P) is None  # 1.1 m off: the dwell restarts
    for t in range(61, 161):
        assert gonogo.update(float(t), at_hold(), SMALL_P) is None
    assert gonogo.update(161.0, at_hold(), SMALL_P) == 'go'


@pytest.mark.parametrize('estimate, covariance', [
    (at_hold((0.0, 0.0, 1.01)), SMALL_P),  # hold error above 1 m
    (at_hold(velocity=(0.0, 0.011, 0.0)), SMALL_P),  # 1.1 cm/s
    (at_hold(), np.diag([0.03, 1e-3, 1e-3, 1e-6, 1e-6, 1e-6])),  # 3-sigma 0.52 m
])
def test_a_hold_whose_estimate_stays_outside_one_bound_is_a_no_go_at_its_timeout(estimate, covariance):
    gonogo = GoNoGo(HOLD, arrived=10.0)
    for t in np.arange(10.0, 1010.0, 10.0):
        assert gonogo.update(t, estimate, covariance) is None
    assert gonogo.update(1010.0, estimate, covariance) == 'no_go'


def test_the_corridor_is_a_ten_degree_cone_from_the_port_within_the_keep_out_sphere():
    corridor = Corridor()
    radius = 0.1 + 100.0 * np.tan(np.radians(10.0))  # 17.73 m at 100 m
    assert corridor.radius(-100.0) == pytest.approx(radius, rel=1e-12)
    assert corridor.contains([-100.0, 0.99 * radius * 0.6, 0.99 * radius * 0.8])
    assert not corridor.contains([-100.0, 1.01 * radius * 0.6, 1.01 * radius * 0.8])
    assert corridor.contains([-250.0, 100.0, 0.0])  # outside the keep-out sphere it does not apply
    x_hat = np.array([-100.0, radius - 0.5, 0.0, 0.0, 0.0, 0.0])
    assert not corridor.estimate_leaves(x_hat, np.diag([1.0, 0.02, 0.02, 1.0, 1.0, 1.0]))  # 3-sigma 0.42 m
    assert corridor.estimate_leaves(x_hat, np.diag([1e-6, 1e-6, 0.03, 1.0, 1.0, 1.0]))  # 0.52 m across


def two_hold_guidance():
    holds = (HoldPoint('250 m', 250.0, 1.0, 0.5, 0.01, 0.0, 100.0),
             HoldPoint('20 m', 20.0, 0.2, 0.1, 0.005, 0.0, 100.0))
    return ApproachGuidance(holds, (Leg(0.1, 300.0, 0.01),), Corridor(), mean_motion=1.1e-3, cam_delta_v=0.4)


def test_an_estimate_whose_three_sigma_leaves_the_corridor_aborts_with_a_cam_only_after_the_keep_out_go():
    outside = np.array([-150.0, 27.0, 0.0, 0.0, 0.0, 0.0])  # the cone is 26.6 m wide at 150 m
    guidance = two_hold_guidance()
    guidance.update(0.0, 1.0, outside, SMALL_P)
    assert guidance.phase == 'hold'  # no go to enter the keep-out sphere yet: no corridor either
    guidance = two_hold_guidance()
    x_ref, u_ff, cam = guidance.update(0.0, 1.0, at_hold(), SMALL_P)  # go at 250 m (dwell 0)
    assert guidance.phase == 'transfer' and not cam.any()
    assert x_ref[3] > 0.0 and x_ref[0] > -250.0  # moving in along V-bar
    np.testing.assert_allclose(u_ff, [x_ref[3] / 1.0, 0.0, 2 * 1.1e-3 * x_ref[3]], rtol=1e-12)  # CW: z'' = -2n x'
    _, _, cam = guidance.update(2.0, 2.0, outside, SMALL_P)
    assert guidance.phase == 'abort' and not guidance.active
    np.testing.assert_allclose(cam, [-0.4 / 2.0, 0.0, 0.0])


def test_the_cam_backs_away_from_the_port_and_never_returns_where_a_posigrade_one_would_hit_it():
    """CW from 20 m behind on V-bar: a retrograde 0.4 m/s (the CAM) leaves the keep-out sphere
    for good over two orbits; a posigrade one first closes (x ~ dv t) and passes the port within
    a few metres (docs/decisions.md, 56)."""
    cw = ClohessyWiltshire()
    away = passive_safety(cw, [-20.0, 0.0, 0.0, -0.4, 0.0, 0.0])
    toward = passive_safety(cw, [-20.0, 0.0, 0.0, 0.4, 0.0, 0.0])
    assert not away['enters_keep_out'] and away['min_range'] == pytest.approx(20.0)
    assert toward['min_range'] < 5.0


def test_a_closed_loop_from_the_5_km_hold_reaches_the_2_km_hold_and_its_go_on_the_nonlinear_truth():
    """EKF on the CW model, nonlinear truth: the go at 5 km, the transfer, the go at 2 km. A
    straight V-bar transfer needs f_z = 2 n v_x all the way, so its delta-v is at least
    2 n 3000 m (6.79 m/s); speeding up to the leg's 1 m/s and braking add at most 2 m/s, the
    LQR's corrections of noise and model error (CW on a nonlinear truth) the rest."""
    scenario = approach_scenario('cw', plant='nonlinear_circular')
    flight, = fly_approach(scenario, 'ekf', runs=1, seed=3, max_duration=5300.0)
    names = [name for _, name in flight['events']]
    assert names[:3] == ['go 5 km', 'arrive 2 km', 'go 2 km'], names
    for decision in flight['holds']:
        assert decision['hold_error'] < 1.0 and decision['estimate_error'] < 0.5, decision
    assert flight['keep_out_entry'] is None and flight['ellipsoid_depth_before_go'] < 0.5
    floor = 2.0 * scenario.model.mean_motion * 3000.0
    assert floor < flight['delta_v'] < floor + 2.0 * scenario.legs[0].max_speed + 0.5


def test_a_stuck_thruster_after_the_keep_out_go_ends_in_an_abort_whose_drift_stays_out_of_the_keep_out_sphere():
    """From the 250 m hold, 2 mm/s^2 along y from 400 s that neither the filter nor the guidance
    knows: the estimate's 3-sigma leaves the cone, the guidance aborts and commands the CAM
    (0.4 m/s back along -x, in the delta-v); its two-orbit free drift does not enter the
    keep-out sphere."""
    scenario = approach_scenario('cw', plant='nonlinear_circular', holds=HOLDS[2:], legs=LEGS[2:],
                                 disturbance=(400.0, (0.0, 2e-3, 0.0)))
    flight, = fly_approach(scenario, 'ekf', runs=1, seed=0, max_duration=2000.0)
    assert [name for _, name in flight['events']] == ['go 250 m', 'abort']
    assert flight['outcome'] == 'abort' and flight['contact'] is None
    assert flight['cam'] is not None and not flight['cam']['enters_keep_out']
    np.testing.assert_allclose(flight['cam']['delta_v'], [-scenario.cam_delta_v, 0.0, 0.0], rtol=1e-12)
    assert flight['delta_v'] > scenario.cam_delta_v


def test_a_filter_without_a_covariance_cannot_fly_the_approach():
    with pytest.raises(ValueError, match='esif has none'):
        fly_approach(approach_scenario(), 'esif', max_duration=10.0)


# ------------------------------------------------------------------ the sensors by range (decision 72)
#: (sensor, range inside its limit, range outside it), margins of several of the sensor's sigmas
#: at that range so that the noise never moves a sample across (LIDAR: 1 m at 3 km).
#: (suite, sensor, a range inside its limits, one just outside), m: the far sensor of each suite
#: (relative GPS from 500 m out, the far camera from 1 km out), the LIDAR and the docking camera.
CLOSE_LIMITS = (('range_azimuth_elevation', 2990.0, 3010.0), ('range_azimuth_elevation', 2.0, 1.6),
                ('docking_camera', 29.0, 31.0), ('docking_camera', 0.08, 0.03))
RANGE_LIMITS = tuple((suite, *limits) for suite, far in (('by_range', ('relative_gps', 520.0, 480.0)),
                                                         ('angles_far', ('line_of_sight', 1100.0, 900.0)))
                     for limits in (far, *CLOSE_LIMITS))


def on_v_bar(ranges):
    """States on V-bar behind the target at ``ranges`` m, 1 % off the axis (inside the cone)."""
    ranges = np.asarray(ranges, dtype=float)
    return np.stack([-ranges, 0.01 * ranges, -0.01 * ranges] + [np.zeros_like(ranges)] * 3, axis=-1)


def test_the_by_range_sensors_are_relative_gps_the_lidar_and_the_docking_camera_at_their_stated_ranges():
    sensor = approach_scenario(sensors='by_range').sensor
    gps, lidar, camera = sensor.parts
    assert [p.name for p in sensor.parts] == ['relative_gps', 'range_azimuth_elevation', 'docking_camera']
    assert gps.min_range == RELATIVE_GPS_MIN_RANGE == 500.0 and gps.max_range == 0.0
    assert (lidar.min_range, lidar.max_range) == (1.8, 3000.0)  # docs/sensors.md, the docking suite
    assert (camera.min_range, camera.max_range) == (0.05, 30.0)
    assert approach_scenario().sensor is None  # the default: Table 6's position sensor


@pytest.mark.parametrize('suite, name, inside, outside', RANGE_LIMITS)
def test_each_sensor_of_a_suite_gives_finite_components_inside_its_range_and_nan_outside(suite, name, inside,
                                                                                       outside):
    sensor = approach_scenario(sensors=suite).sensor
    index = [p.name for p in sensor.parts].index(name)
    fused = FusedSensor(sensor, seeds=range(8))
    for distance, present in ((inside, True), (outside, False)):
        z = fused.measure(on_v_bar(np.full(8, distance))).z[:, sensor.slices[index]]
        assert np.isfinite(z).all() if present else np.isnan(z).all(), (name, distance, z)


def test_the_hand_over_follows_the_range_from_5_km_to_contact():
    """Which sensors give a sample at each range: relative GPS alone beyond 3 km, with the LIDAR
    to 500 m, the LIDAR alone to 30 m, with the camera to 1.8 m, the camera alone inside."""
    sensor = approach_scenario(sensors='by_range').sensor
    ranges = [5000.0, 3500.0, 2000.0, 600.0, 250.0, 40.0, 20.0, 5.0, 1.0, 0.2]
    z = FusedSensor(sensor, seeds=range(len(ranges))).measure(on_v_bar(ranges)).z
    present = [[bool(np.isfinite(z[b, part]).all()) for part in sensor.slices] for b in range(len(ranges))]
    assert present == [[True, False, False], [True, False, False], [True, True, False], [True, True, False],
                       [False, True, False], [False, True, False], [False, True, True], [False, True, True],
                       [False, False, True], [False, False, True]]


@pytest.mark.parametrize('kind', ['ekf', 'snn_ekf'])
def test_across_the_camera_s_arrival_at_30_m_p_stays_positive_definite_and_shrinks_and_the_estimate_converges(kind):
    """Free drift from 34 m to ~26 m at 2 cm/s on the nonlinear truth: the LIDAR alone, then the
    LIDAR and the docking camera. Every step P is positive definite; once the camera's ranges
    (5 mm floor against the LIDAR's 3.3 cm) come in, the along-track sigma falls below what the
    LIDAR alone gave, and the estimate ends within 5 cm of the truth. (Not within a few of the
    filter's sigmas: the camera's R_hat is its R at 10 m, and its range sigma grows as r^2, 19 cm
    at 30 m: the filter is optimistic there by ~3x; decision 72.)"""
    x0 = np.array([-34.0, 0.0, 0.0, 0.02, 0.0, 0.0])
    scenario = approach_scenario('nonlinear_circular', sensors='by_range', initial_state=tuple(x0))
    seeds = [0, 1, 2]
    estimator = make_estimator(kind, scenario.estimator, scenario.model, runs=3, seeds=seeds,
                               measurement=scenario.sensor)
    plant = Plant(scenario.truth, x0, scenario.process_noise, seeds)
    fused, u = FusedSensor(scenario.sensor, seeds), np.zeros((3, 3))
    sigma_x, camera = [], scenario.sensor.slices[2]
    for _ in range(400):
        sample = fused.measure(plant.x)
        estimator.step(sample.z, u, 1.0, valid=sample.valid)
        plant.step(u, 1.0)
        assert (np.linalg.eigvalsh(estimator.batch_P) > 0.0).all()
        sigma_x.append((np.isfinite(sample.z[:, camera]).all(), np.sqrt(estimator.batch_P[:, 0, 0]).max()))
    with_camera = [s for seen, s in sigma_x if seen]
    lidar_alone = [s for seen, s in sigma_x if not seen]
    assert 100 < len(lidar_alone) < 300 and len(with_camera) > 100
    assert max(with_camera[50:]) < 0.7 * min(lidar_alone[-50:])
    error = np.abs(estimator.batch_x_hat[:, 0] - plant.x[:, 0])
    assert error.max() < 0.05, error  # from the start's 0.2 m sigma (FAR_RANGE_ESTIMATOR's dispersion)
