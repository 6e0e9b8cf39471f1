"""The approach (issue 39, parts 2-3): the go/no-go of a hold alone, the corridor and its abort,
the CAM's direction, and a closed loop from the 5 km hold to the go at the 2 km hold."""

import numpy as np
import pytest

from snn_estimator.models import ClohessyWiltshire
from snn_estimator.plant.approach import ApproachGuidance, Corridor, GoNoGo, HoldPoint, Leg, position_three_sigma
from snn_estimator.sim.approach import HOLDS, LEGS, approach_scenario, fly_approach, passive_safety

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
