"""The approach's angles-only far phase (issue 39, item 2; docs/decisions.md, 73-75): the suite's
sensors by range, the out-of-plane observability hop alone and in the guidance, and the hop's
effect on the range's 3-sigma at the 5 km hold."""

import numpy as np
import pytest
from scipy.linalg import expm

from snn_estimator.models import ClohessyWiltshire
from snn_estimator.plant.approach import (
    ApproachGuidance,
    Corridor,
    HoldPoint,
    Leg,
    ObservabilityManoeuvre,
    OutOfPlaneHop,
)
from snn_estimator.plant.sensors import FusedSensor
from snn_estimator.sim.approach import (
    ANGLES_HOP,
    ANGLES_RANGE_UNCERTAINTY,
    FAR_CAMERA_MIN_RANGE,
    FAR_CAMERA_NOISE,
    HOLDS,
    LEGS,
    approach_scenario,
    fly_approach,
    range_figures,
)

N = ClohessyWiltshire().mean_motion


def on_v_bar(ranges, lateral=0.01):
    """States behind the target at ``ranges`` m, ``lateral`` of the range off V-bar in y and z."""
    ranges = np.asarray(ranges, dtype=float)
    return np.stack([-ranges, lateral * ranges, -lateral * ranges] + [np.zeros_like(ranges)] * 3, axis=-1)


# ------------------------------------------------------------------ the suite
#: (sensor, range inside its limit, range outside it): the far camera from 1 km out (no maximum),
#: the LIDAR 1.8 m - 3 km, the docking camera 5 cm - 30 m; margins of several sigmas.
def test_the_angles_suite_is_a_far_camera_the_lidar_and_the_docking_camera_and_no_relative_gps():
    sensor = approach_scenario(sensors='angles_far').sensor
    assert [p.name for p in sensor.parts] == ['line_of_sight', 'range_azimuth_elevation', 'docking_camera']
    camera = sensor.parts[0]
    assert camera.min_range == FAR_CAMERA_MIN_RANGE == 1000.0 and camera.max_range == 0.0
    np.testing.assert_allclose(np.diag(camera.noise), [FAR_CAMERA_NOISE ** 2] * 2, rtol=1e-12)


def test_the_angles_suite_hands_over_by_range_with_the_far_camera_alone_at_the_5_km_hold():
    sensor = approach_scenario(sensors='angles_far').sensor
    ranges = [20000.0, 5000.0, 3500.0, 2000.0, 900.0, 250.0, 20.0, 1.0, 0.2]
    z = FusedSensor(sensor, seeds=range(len(ranges))).measure(on_v_bar(ranges)).z
    present = [[bool(np.isfinite(z[b, part]).all()) for part in sensor.slices] for b in range(len(ranges))]
    assert present == [[True, False, False], [True, False, False], [True, False, False], [True, True, False],
                       [False, True, False], [False, True, False], [False, True, True], [False, False, True],
                       [False, False, True]]


def test_the_far_camera_sees_the_target_only_inside_its_18_degree_cone():
    """At 5 km, 700 m off V-bar is 8.0 deg off the boresight (inside the 9 deg half cone), 900 m
    10.2 deg (outside)."""
    sensor = approach_scenario(sensors='angles_far').sensor
    x = np.zeros((2, 6))
    x[:, 0], x[:, 1] = -5000.0, (700.0, 900.0)
    z = FusedSensor(sensor, seeds=[0, 1]).measure(x).z[:, sensor.slices[0]]
    assert np.isfinite(z[0]).all() and np.isnan(z[1]).all()


def test_the_angles_suite_starts_with_its_range_uncertainty_along_track():
    config = approach_scenario(sensors='angles_far', range_uncertainty=0.03).estimator
    assert config.initial_covariance[0] == pytest.approx((0.03 * 5000.0) ** 2)
    assert approach_scenario(sensors='angles_far').manoeuvre == ANGLES_HOP
    assert approach_scenario(sensors='angles_far', manoeuvre=None).manoeuvre is None
    assert approach_scenario(sensors='by_range').manoeuvre is None


@pytest.mark.parametrize('changes, message', [
    ({'sensors': 'angles'}, 'sensors must be one of position, by_range, angles_far'),
    ({'sensors': 'angles_far', 'range_uncertainty': 1.5}, 'range_uncertainty'),
    ({'sensors': 'by_range', 'range_uncertainty': 7.0}, 'range_uncertainty'),  # checked on every suite
    ({'sensors': 'angles_far', 'manoeuvre': 'none'}, "manoeuvre must be 'suite'.*None.*got 'none'"),
])
def test_a_bad_suite_or_range_uncertainty_is_refused_with_the_choices(changes, message):
    with pytest.raises(ValueError, match=message):
        approach_scenario(**changes)


@pytest.mark.parametrize('size, delay, message', [(0.0, 300.0, 'non-zero size'), (np.nan, 300.0, 'finite'),
                                                   (200.0, -1.0, 'delay'), (200.0, np.inf, 'delay')])
def test_a_hop_without_a_size_or_with_a_negative_delay_is_refused(size, delay, message):
    with pytest.raises(ValueError, match=message):
        ObservabilityManoeuvre('5 km', size, delay)


def test_the_angles_suite_started_inside_the_5_km_hold_has_no_hop_to_fly():
    scenario = approach_scenario(sensors='angles_far', holds=HOLDS[1:], legs=LEGS[1:])
    assert scenario.manoeuvre is None
    assert scenario.guidance().active  # built: no 'hold must be one of' for a hop nobody asked for


def test_a_manoeuvre_at_a_hold_the_guidance_does_not_fly_is_refused_with_the_holds():
    with pytest.raises(ValueError, match="hold must be one of 5 km, 2 km, 250 m, 20 m; got '4 km'"):
        approach_scenario(manoeuvre=ObservabilityManoeuvre('4 km', 200.0, 0.0)).guidance()


def test_the_range_figures_are_the_range_error_and_three_sigma_along_the_estimated_line_of_sight():
    """On V-bar the line of sight is x: the 3-sigma is 3 sqrt(P_xx); 3-4-0 m off V-bar it is
    3 sqrt(l^T P l) with l = (-0.6, 0.8, 0) for the estimate at (-3, 4, 0) (range 5)."""
    p = np.diag([100.0, 4.0, 9.0, 1.0, 1.0, 1.0])
    figures = range_figures([-5010.0, 0, 0, 0, 0, 0], [-5000.0, 0, 0, 0, 0, 0], p)
    assert figures == {'range_error': pytest.approx(10.0), 'range_three_sigma': pytest.approx(30.0)}
    figures = range_figures([-3.0, 4.0, 0.5, 0, 0, 0], [-3.0, 4.0, 0.0, 0, 0, 0], p)
    assert figures['range_error'] == pytest.approx(np.sqrt(25.25) - 5.0)
    assert figures['range_three_sigma'] == pytest.approx(3.0 * np.sqrt(0.36 * 100.0 + 0.64 * 4.0))


# ------------------------------------------------------------------ the hop alone
def test_the_hop_flies_the_free_out_of_plane_oscillation_for_half_an_orbit_on_two_burns_of_n_size():
    """The hop's accelerations fed to y'' = -n^2 y + a (exact zero-order-hold discretisation,
    independent of the hop's own sine): nothing before arrival + delay, then y peaks at the
    hop's size (to 0.1 %), is back on V-bar after pi / n s at rest (< 0.3 m, < 1e-3 m/s: the
    burns act over a 1 s step), and the two burns add to 2 n size m/s."""
    size, delay, arrived, dt = 200.0, 300.0, 50.0, 1.0
    hop = OutOfPlaneHop(ObservabilityManoeuvre('5 km', size, delay), N, arrived)
    a = np.array([[0.0, 1.0], [-N * N, 0.0]])
    block = expm(np.block([[a, np.array([[0.0], [1.0]])], [np.zeros((1, 3))]]) * dt)
    phi, gamma = block[:2, :2], block[:2, 2]
    state, peak, delta_v, phases = np.zeros(2), 0.0, 0.0, []
    for k in range(int(arrived), int(arrived + delay + np.pi / N) + 10):
        _, _, burn = hop.update(float(k), dt)
        phases.append(hop.phase)
        state = phi @ state + gamma * burn
        peak, delta_v = max(peak, state[0]), delta_v + abs(burn) * dt
    assert phases.index('flying') == delay and hop.started == arrived + delay
    assert hop.done and hop.ended - hop.started == pytest.approx(np.pi / N, abs=1.0)
    assert peak == pytest.approx(size, rel=1e-3)
    assert abs(state[0]) < 0.3 and abs(state[1]) < 1e-3
    assert delta_v == pytest.approx(2.0 * N * size, rel=1e-3)


def test_the_go_no_go_of_a_hold_with_a_hop_starts_only_when_the_hop_is_done():
    """A perfect, still estimate at the hold: without the hop the go comes after the dwell;
    with it the guidance first flies the hop (its setpoint off V-bar in y) and goes one dwell
    after the hop's end, though the estimate met every bound all along."""
    hold = HoldPoint('5 km', 5000.0, 25.0, 10.0, 0.05, 300.0, 3000.0)
    holds, legs = (hold, HoldPoint('2 km', 2000.0, 10.0, 5.0, 0.05, 300.0, 3000.0)), (Leg(1.0, 300.0, 0.02),)
    small = 1e-2 * np.eye(6)
    for manoeuvre in (None, ObservabilityManoeuvre('5 km', 200.0, 100.0)):
        guidance = ApproachGuidance(holds, legs, Corridor(), N, manoeuvre=manoeuvre)
        offsets = []
        for t in range(0, 4000):
            x_ref, _, _ = guidance.update(float(t), 1.0, hold.state, small)
            offsets.append(x_ref[1])
            if guidance.phase != 'hold':
                break
        names = [(e.time, e.name) for e in guidance.events]
        if manoeuvre is None:
            assert names == [(300.0, 'go 5 km')] and max(np.abs(offsets)) == 0.0
        else:
            end = guidance.hop.ended
            # the first estimate judged is the next step's, after the hop's last burn
            assert names == [(100.0, 'hop 5 km'), (end, 'hop done 5 km'), (end + 1.0 + 300.0, 'go 5 km')]
            assert max(offsets) == pytest.approx(200.0, rel=1e-3)


# ------------------------------------------------------------------ the hop makes the range observable
def test_the_hop_shrinks_the_range_three_sigma_that_without_it_stays_at_its_start():
    """EKF, CW filter on a CW truth, seed 0, to the hop's end (~3080 s). Without the hop the chaser
    sits on V-bar, the bearings of x and k x agree and the range 3-sigma stays within 2 % of its
    start (3 x 2 % x 5 km = 300 m; Q adds sqrt(q t^3 / 3) ~ 0.1 m). With it the 3-sigma falls
    below 15 % of its start, yet stays above what the azimuth could give if nothing else were
    unknown: 3 r^2 sigma_hat / (size sqrt(sum sin^2)) over the hop's samples (~4.5 m)."""
    sigmas = {}
    for manoeuvre in ('suite', None):
        scenario = approach_scenario('cw', plant='cw', sensors='angles_far', manoeuvre=manoeuvre)
        flight, = fly_approach(scenario, 'ekf', runs=1, seed=0, max_duration=3090.0, record=True)
        p, x_hat = flight['trajectory']['covariance'], flight['trajectory']['estimate']
        line = x_hat[:, :3] / np.linalg.norm(x_hat[:, :3], axis=1, keepdims=True)
        sigmas[manoeuvre] = 3.0 * np.sqrt(np.einsum('ki,kij,kj->k', line, p[:, :3, :3], line))
    start = 3.0 * ANGLES_RANGE_UNCERTAINTY * 5000.0
    assert sigmas[None][0] == pytest.approx(start, rel=1e-6)
    assert sigmas[None][-1] > 0.98 * start
    r_hat_sigma = np.sqrt(5.0) * FAR_CAMERA_NOISE  # R_hat = measurement_noise_scale R
    bound = 3.0 * 5000.0 ** 2 * r_hat_sigma / (ANGLES_HOP.size * np.sqrt(0.5 * np.pi / (N * 1.0)))
    assert bound < sigmas['suite'][-1] < 0.15 * start

