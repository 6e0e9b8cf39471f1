"""Several sensors in one filter (issue 22, measurements.stacked): the stacked model is its
parts side by side, an absent sensor drops out of every gain law exactly, the fused offline
sensor keeps each part's own noise and rate, and the camera -> LIDAR hand-over docks."""

import dataclasses

import numpy as np
import pytest
from test_measurements import central_differences

from snn_estimator import FILTER_KINDS, make_estimator, simulate
from snn_estimator.measurements import make_model
from snn_estimator.measurements.stacked import Stacked
from snn_estimator.plant.sensors import FUSED_SEED_OFFSET, FusedSensor, MeasurementSensor, docking_sensors
from snn_estimator.sim.scenarios import docking_scenario, handover_scenario, sensor_rendezvous_scenario

MOUNTING = (0.0, 0.0, 1.0, 0.0)
LIDAR_NOISE, CAMERA_NOISE = [1e-2, 1e-6, 1e-6], [1e-6, 1e-6]


def camera_and_lidar():
    camera = make_model('line_of_sight', CAMERA_NOISE, mounting_rotation=MOUNTING)
    lidar = make_model('range_azimuth_elevation', LIDAR_NOISE, mounting_rotation=MOUNTING, min_range=0.3)
    return camera, lidar


def test_a_stacked_measurement_is_its_sensors_side_by_side():
    camera, lidar = camera_and_lidar()
    stacked = Stacked([camera, lidar])
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.uniform(10.0, 80.0, size=(8, 3)), rng.normal(size=(8, 3))], axis=1)
    assert stacked.dim == 5 and stacked.angle_components == (0, 1, 3, 4)
    np.testing.assert_array_equal(stacked.h(x), np.concatenate([camera.h(x), lidar.h(x)], axis=1))
    np.testing.assert_array_equal(stacked.noise[:2, :2], camera.noise)
    np.testing.assert_array_equal(stacked.noise[2:, 2:], lidar.noise)
    assert not stacked.noise[:2, 2:].any()
    steps = np.full(x.shape, 1e-5)  # ranges 10-80 m, far from every singular direction
    numeric = central_differences(stacked, x, steps)
    np.testing.assert_allclose(stacked.jacobian(x), numeric, rtol=0, atol=1e-6 * np.abs(numeric).max())
    z = stacked.h(x)
    z[:4, 2:] = np.nan  # the LIDAR absent in four runs
    np.testing.assert_array_equal(stacked.present(z)[:, 2:].any(axis=1), [False] * 4 + [True] * 4)
    assert stacked.position_of(z[:4]) is None  # bearings alone give no position
    np.testing.assert_allclose(stacked.position_of(z[4:]), x[4:, :3], atol=1e-9)
    with pytest.raises(ValueError, match='stacked'):
        Stacked([stacked, lidar])


@pytest.mark.parametrize('kind', list(FILTER_KINDS))
def test_a_sensor_absent_every_step_leaves_exactly_the_filter_of_the_other(kind):
    """LIDAR and camera stacked, the camera never present: every filter kind gives the
    LIDAR-only filter's estimates (its rows of H zero, its innovation zero, R block-diagonal)."""
    camera, lidar = camera_and_lidar()
    base = dataclasses.replace(sensor_rendezvous_scenario(initial_state_dispersion=True), duration=8.0)
    stacked = Stacked([lidar, camera])
    config = base.estimator.replace(measurement_noise=stacked.noise,
                                    boundary_layer=tuple(np.sqrt(np.diag(stacked.noise))))
    alone = make_estimator(kind, base.estimator, base.model, measurement=base.sensor)
    fused = make_estimator(kind, config, base.model, measurement=stacked)
    meter = MeasurementSensor(base.sensor, [0])
    x = np.array([[70.0, 30.0, -5.0, -0.5, -0.2, 0.05]])
    for _ in range(80):
        z = meter.measure(x).z[0]
        alone.step(z, np.zeros(3), 0.1)
        fused.step(np.concatenate([z, [np.nan, np.nan]]), np.zeros(3), 0.1)
        np.testing.assert_allclose(fused.x_hat, alone.x_hat, rtol=0, atol=1e-9)
        x = base.model.transition(x[0], np.zeros(3), 0.1)[None]
    if alone.has_covariance:
        np.testing.assert_allclose(fused.P, alone.P, rtol=0, atol=1e-12)
    assert fused.total_spikes == alone.total_spikes


def test_the_fused_sensor_keeps_each_sensors_noise_stream_and_rate():
    camera, lidar = camera_and_lidar()
    stacked = Stacked([camera, lidar])
    fused = FusedSensor(stacked, seeds=[4, 5], periods=(1, 3))
    alone = [MeasurementSensor(camera, [4, 5]),
             MeasurementSensor(lidar, [4 + FUSED_SEED_OFFSET, 5 + FUSED_SEED_OFFSET])]
    x = np.array([[50.0, 10.0, -3.0, 0, 0, 0], [40.0, -5.0, 2.0, 0, 0, 0]])
    for k in range(7):
        sample = fused.measure(x)
        np.testing.assert_array_equal(sample.z[:, :2], alone[0].measure(x).z)
        if k % 3:
            assert np.isnan(sample.z[:, 2:]).all()
        else:
            np.testing.assert_array_equal(sample.z[:, 2:], alone[1].measure(x).z)
        assert sample.valid.all()
    np.testing.assert_array_equal(fused.counts[1], [3, 3])


def test_the_camera_to_lidar_hand_over_docks_from_the_dispersed_start():
    """Bearings only beyond 30 m (the LQR's known burns make the range observable), then the
    LIDAR: the default filter docks (4 dispersed runs)."""
    scenario = handover_scenario(initial_state_dispersion=True)
    result = simulate(scenario, 'snn_ekf', runs=4)
    final_range = np.linalg.norm(result.truth[:, -1, :3], axis=1)
    assert final_range.max() < 0.1, final_range
    ranges = np.linalg.norm(result.truth[0, :, :3], axis=1)
    assert ranges[0] > 30.0 and ranges[-1] < 30.0  # a camera-only phase, then the hand-over


def test_the_docking_suite_hands_over_from_the_lidar_to_the_camera_by_range():
    """The LIDAR alone beyond the camera's 30 m, both down to the LIDAR's 1.8 m, the camera alone
    to its 5 cm, nothing inside; each sensor with its own noise at that range."""
    lidar, camera = docking_sensors(field_of_view=False)
    fused = FusedSensor(Stacked([lidar, camera]), seeds=range(6))
    ranges = np.array([500.0, 31.0, 29.0, 2.0, 1.7, 0.04])
    x = np.zeros((6, 6))
    x[:, 0] = ranges  # ahead of the target on V-bar, as the sensors look back along -x
    sample = fused.measure(x)
    lidar_seen = np.isfinite(sample.z[:, :3]).all(axis=1)
    camera_seen = np.isfinite(sample.z[:, 3:]).all(axis=1)
    assert lidar_seen.tolist() == [True, True, True, True, False, False]
    assert camera_seen.tolist() == [False, False, True, True, True, False]
    assert sample.valid.tolist() == [True] * 5 + [False]
    for part, seen, column in ((lidar, lidar_seen, 0), (camera, camera_seen, 3)):  # within 4 sigma of R(range)
        sigma = np.sqrt(part.noise_at(x[seen])[:, 0, 0])
        assert np.all(np.abs(sample.z[seen, column] - ranges[seen]) < 4.0 * sigma)


def test_the_docking_suite_docks_from_the_dispersed_start_where_the_lidar_alone_ends_blind():
    """The docking camera measures to 5 cm: the default filter and the weighted MSIF end within
    0.1 m (3 dispersed runs each), where on the LIDAR alone EMSIF-W ends ~0.18 m off."""
    scenario = docking_scenario(initial_state_dispersion=True)
    for kind in ('snn_ekf', 'emsif_weighted'):
        result = simulate(scenario, kind, runs=3)
        assert not result.diverged.any()
        assert result.final_range().max() < 0.1, (kind, result.final_range())


def test_the_weighted_inverse_switches_to_the_pseudo_inverse_only_where_c_p_ct_is_singular():
    """EMSIF-W's (C P C^T)^-1: the inverse for one sensor (its numbers unchanged to the bit),
    the pseudo-inverse for dependent or zero rows; the compiled piece uses the same threshold."""
    import inspect

    from snn_estimator.gains import msif_weighted
    rng = np.random.default_rng(5)
    a = rng.normal(size=(3, 3))
    full = a @ a.T + np.eye(3)
    np.testing.assert_array_equal(msif_weighted._inverse(full), np.linalg.inv(full))
    c = np.vstack([rng.normal(size=(2, 6)), np.zeros((1, 6))])  # a zero row: an absent sensor
    dependent = np.vstack([c[:2], c[:1]])  # the same angle twice: a camera and a LIDAR
    p = np.eye(6)
    for rows in (c, dependent):
        np.testing.assert_allclose(msif_weighted._inverse(rows @ p @ rows.T), np.linalg.pinv(rows @ p @ rows.T))
    assert f'<= {msif_weighted.SINGULAR_CORRELATION!r} * diagonal' in inspect.getsource(msif_weighted.gain)


def test_the_assembler_hands_a_stamp_on_once_every_sensor_reported_it():
    """Complete stamps in order, a lost report completed by the next stamp or by the wait, a
    repeat recognised, NaN for a sensor that measured nothing, None when none did."""
    from snn_estimator.runners.assembly import SampleAssembler
    camera, lidar = camera_and_lidar()
    stacked = Stacked([camera, lidar])
    wall = [0.0]
    assembler = SampleAssembler(stacked, wait=0.25, wall_clock=lambda: wall[0])
    a, b = np.array([0.1, 0.2]), np.array([50.0, 0.1, 0.2])
    assert assembler.offer(1, 0, b) == ('new', [])
    kind, ready = assembler.offer(0, 0, None)
    assert kind == 'new' and ready[0][0] == 0
    np.testing.assert_array_equal(ready[0][1], [np.nan, np.nan, 50.0, 0.1, 0.2])
    assert assembler.offer(0, 0, a) == ('repeat', [])  # a lockstep resend of a stamp handed on
    assert assembler.offer(0, 100, None)[1] == [] and assembler.offer(1, 100, None)[1] == [(100, None)]
    assert assembler.offer(0, 200, a)[1] == []  # the LIDAR's report of 200 is lost
    assert assembler.offer(0, 300, a)[1] == []
    ready = assembler.offer(1, 300, b)[1]
    assert [stamp for stamp, _ in ready] == [200, 300] and assembler.incomplete == 1
    assert assembler.offer(1, 200, b) == ('late', [])  # its stamp went on without it
    assert assembler.offer(0, 200, a) == ('repeat', [])
    np.testing.assert_array_equal(ready[0][1][:2], a)
    assert np.isnan(ready[0][1][2:]).all()
    assembler.offer(1, 400, b)
    wall[0] = 0.2
    assert assembler.expired() == []
    wall[0] = 0.3
    assert [stamp for stamp, _ in assembler.expired()] == [400] and assembler.pending == 0


def test_a_sensors_mahalanobis_gate_drops_only_its_own_wild_sample():
    from snn_estimator.runners.assembly import gate
    camera, lidar = camera_and_lidar()
    stacked = Stacked([camera, lidar])
    base = sensor_rendezvous_scenario()
    config = base.estimator.replace(measurement_noise=stacked.noise,
                                    boundary_layer=tuple(np.sqrt(np.diag(stacked.noise))))
    estimator = make_estimator('ekf', config, base.model, measurement=stacked)
    x = np.asarray(estimator.x_hat, dtype=float)
    z = stacked.h(x[None])[0]
    wild = z.copy()
    wild[2] += 20.0  # the LIDAR's range 20 m off: 200 sigma
    kept, gated = gate(estimator, stacked, wild, estimator.settings.r_hat, [25.0, 25.0])
    assert gated == [1] and np.isnan(kept[2:]).all()
    np.testing.assert_array_equal(kept[:2], z[:2])
    assert gate(estimator, stacked, z, estimator.settings.r_hat, [25.0, 25.0])[1] == []
    assert gate(estimator, stacked, wild, estimator.settings.r_hat, [25.0, 0.0])[1] == []  # 0: no gate
