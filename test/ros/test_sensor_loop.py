"""The closed loop over ROS on a LIDAR (range, azimuth, elevation) instead of Table 6's position
sensor (issue 22; ``make demo SENSOR=lidar``): the estimator re-linearises H(x_hat) every step,
the sensor says "nothing measured" below its minimum range, and the run equals the offline
loop on the same sensor (docs/sensors.md)."""

import numpy as np
import pytest

pytest.importorskip('rclpy')

from snn_estimator import make_estimator, simulate  # noqa: E402
from snn_estimator.sim.scenarios import sensor_rendezvous_scenario  # noqa: E402
from snn_tools.bags.data import read_bag, summarize  # noqa: E402
from snn_tools.run.demo import run_pipeline  # noqa: E402

pytestmark = pytest.mark.slow
#: The default estimator and the robust one the issue names (22), and the EKF that filterpy's
#: checks (36).
KINDS = ('snn_ekf', 'snn_emsif_weighted', 'ekf')


@pytest.fixture(scope='module')
def lidar_runs(tmp_path_factory):
    results = {}
    for kind in KINDS:
        run_dir = tmp_path_factory.mktemp(f'lidar_{kind}')
        run_pipeline(run_dir, estimator=kind, sensor='lidar', timeout=240.0)
        data = read_bag(run_dir / 'bag')
        results[kind] = (data, summarize(data))
    return results


@pytest.mark.parametrize('kind', KINDS)
def test_the_lidar_loop_over_ros_equals_the_offline_loop_on_the_same_sensor(lidar_runs, kind):
    data, summary = lidar_runs[kind]
    offline = simulate(sensor_rendezvous_scenario(initial_state_dispersion=True), kind)
    stamps = np.round(data.estimate_t / 0.1).astype(int)
    inside = stamps <= 3600
    assert inside.sum() == 3601 and summary['recording_complete'], summary['messages']
    np.testing.assert_allclose(data.estimate[inside], offline.estimate[0, stamps[inside]], rtol=0, atol=1e-9)
    np.testing.assert_allclose(data.truth, offline.truth[0], rtol=0, atol=1e-9)
    assert summary['control_timeouts'] == 0 and summary['measurements_rejected'] == 0


def test_the_default_estimator_docks_on_the_lidar_from_the_dispersed_start(lidar_runs):
    _, summary = lidar_runs['snn_ekf']
    assert summary['final_range_m'] < 0.1
    assert all(summary['rmse_last_60s'][s] < 0.05 for s in ('x', 'y', 'z'))


@pytest.mark.parametrize('kind', KINDS)
def test_below_its_minimum_range_the_lidar_says_nothing_measured_and_the_filter_predicts(lidar_runs, kind):
    """Every truth stamp has a measurement message: a LIDAR sample in range, or "nothing
    measured" (NaN components) below 0.3 m, which the estimator counts and predicts over."""
    data, _ = lidar_runs[kind]
    assert data.types['/measurement'] == 'geometry_msgs/msg/Vector3Stamped'
    np.testing.assert_allclose(data.measurement_t, data.truth_t, rtol=0, atol=1e-9)
    empty = np.isnan(data.measurement).all(axis=1)
    assert 0 < empty.sum() < empty.size and not np.isnan(data.measurement[~empty]).any()
    true_range = np.linalg.norm(data.truth[:, :3], axis=1)
    assert empty[true_range < 0.3].all()
    assert not empty[true_range > 0.3 + 6 * 0.1].any()  # near it, a noisy range (sigma 0.1 m) below 0.3 m too
    sensor, estimator = data.last_diagnostics('position_sensor'), data.last_diagnostics('estimator')
    assert int(sensor['measurement_rejected.too_close']) == empty.sum()
    assert int(estimator['not_measured']) == empty.sum()
    assert int(estimator['dropout_steps']) >= empty.sum() - 1  # the last one needs no step
    assert int(estimator['measurements_used']) == (~empty).sum()


def test_the_ekf_over_ros_is_filterpys_discrete_ekf_fed_the_bag(lidar_runs):
    """issue 36: filterpy's ExtendedKalmanFilter (update, then predict), given the LIDAR model's
    h, H and wrapped residual, CW's Phi and Gamma, the sampled step's Q_d (Van Loan) and R_d =
    R_hat / dt (R_hat a density, Eq. 5-6; docs/decisions.md, 43) and the estimator's start, fed
    the bag's measurements ("nothing measured": predict only) and controls, gives the estimator's
    estimates to 1e-6 m and its position RMSE against the bag's truth within 2 %."""
    from filterpy.kalman import ExtendedKalmanFilter
    data, _ = lidar_runs['ekf']
    scenario = sensor_rendezvous_scenario(initial_state_dispersion=True)
    model, sensor, dt = scenario.model, scenario.sensor, scenario.dt
    start = make_estimator('ekf', scenario.estimator, model, measurement=sensor)  # the node's x_hat0 and P0
    ekf = ExtendedKalmanFilter(dim_x=6, dim_z=3, dim_u=3)
    ekf.x, ekf.P = start.x_hat.copy(), start.P.copy()
    ekf.F, ekf.B = model.discrete_matrices(dt)
    ekf.Q = model.process_noise_discrete(start.settings.q_hat, dt)
    ekf.R = start.settings.r_hat / dt
    for stamps in (data.control_t, data.measurement_t, data.truth_t):  # a sample per stamp from 0 on
        np.testing.assert_array_equal(np.round(stamps[:3601] / dt), np.arange(3601))
    theirs = []
    for z, u in zip(data.measurement[:3600], data.control[:3600]):
        if np.isfinite(z).all():
            ekf.update(z, sensor.jacobian, sensor.h, residual=sensor.residual)
        ekf.predict(u=u)
        theirs.append(ekf.x.copy())
    ours, theirs, truth = data.estimate[1:3601], np.array(theirs), data.truth[1:3601]
    np.testing.assert_allclose(ours[:, :3], theirs[:, :3], rtol=0, atol=1e-6)

    def rmse(estimates):
        return np.sqrt(np.mean((estimates[:, :3] - truth[:, :3]) ** 2))
    assert rmse(ours) == pytest.approx(rmse(theirs), rel=0.02)


@pytest.fixture(scope='module')
def fused_run(tmp_path_factory):
    """``make demo SENSOR=camera+lidar``: two sensor processes on their own topics, one estimator."""
    run_dir = tmp_path_factory.mktemp('camera_lidar')
    run_pipeline(run_dir, estimator='snn_ekf', sensor='camera+lidar', timeout=240.0)
    data = read_bag(run_dir / 'bag')
    return data, summarize(data)


def test_the_camera_and_lidar_fused_over_ros_equal_the_offline_hand_over_and_dock(fused_run):
    """Camera 10 Hz, LIDAR 5 Hz within 30 m, each its own node and topic: the estimator assembles
    each stamp from both and the run equals handover_scenario() offline to 1e-9; it docks."""
    from snn_estimator.sim.scenarios import handover_scenario
    data, summary = fused_run
    offline = simulate(handover_scenario(initial_state_dispersion=True), 'snn_ekf')
    stamps = np.round(data.estimate_t / 0.1).astype(int)
    inside = stamps <= 3600
    assert inside.sum() == 3601 and summary['recording_complete'], summary['messages']
    np.testing.assert_allclose(data.estimate[inside], offline.estimate[0, stamps[inside]], rtol=0, atol=1e-9)
    np.testing.assert_allclose(data.truth, offline.truth[0], rtol=0, atol=1e-9)
    assert summary['final_range_m'] < 0.1 and summary['control_timeouts'] == 0
    assert set(summary['messages']) >= {'camera', 'lidar'} and 'measurement' not in summary['messages']
    estimator = data.last_diagnostics('estimator')
    assert estimator['sensors'] == 'camera,lidar' and estimator['assembled_incomplete'] == '0'
    lidar = data.last_diagnostics('lidar')
    assert int(lidar['measurement_rejected.too_far']) > 0  # beyond 30 m at the start: bearings only
    assert data.types['/camera'] == data.types['/lidar'] == 'geometry_msgs/msg/Vector3Stamped'
    # the controller watched both sensors, not `measurement`, and never lost them while flying (at
    # the end every peer goes quiet: the nodes are stopped one by one)
    flying = [values for t, values in data.diagnostics['lqr_controller'] if t < data.truth_t[-1]]
    assert flying and all(v['peer.camera'] == v['peer.lidar'] == 'OK' and 'peer.measurement' not in v
                          for v in flying)
    assert data.last_diagnostics('lqr_controller')['safe_mode_steps'] == '0'


def test_each_sensor_of_the_fused_run_reported_every_stamp_of_its_schedule(fused_run):
    """The per-sensor check of the summary on the real run: both sensors answered every truth
    (a sample or "nothing measured"), the camera measured at every stamp but those too close,
    the LIDAR only on its 0.2 s grid and within 30 m, as each sensor counted itself."""
    data, summary = fused_run
    sensors = summary['sensors']
    assert set(sensors) == {'camera', 'lidar'}
    for name, period in (('camera', 0.1), ('lidar', 0.2)):
        values, own = sensors[name], data.last_diagnostics(name)
        assert values['expected'] == values['recorded'] == 3601 and values['every_truth'], (name, values)
        assert values['gaps'] == [] and values['lost'] == 0 and values['off_schedule'] == 0
        assert values['period_s'] == pytest.approx(period) and values['node'] == name
        due = -(-3601 // round(period / 0.1))  # samples due on its grid, from the first truth
        assert values['measured'] == due - int(own['measurement_rejected']), (name, values, own)
    stamps, measured = data.reports['lidar']
    assert np.all((stamps[measured] // 100_000_000) % 2 == 0)  # LIDAR samples only at even steps
    assert summary['gaps'] == {'camera': [], 'lidar': [], 'control': [], 'estimate': []}


def test_single_process_mode_runs_the_two_sensor_nodes_of_the_suite(tmp_path):
    """--single-process builds the nodes of the pipeline description, a suite's two sensors under
    their names and on their own topics included: its first 30 s are the offline hand-over's."""
    from snn_estimator.sim.scenarios import handover_scenario
    result = run_pipeline(tmp_path, estimator='snn_ekf', sensor='camera+lidar', duration=30.0, single_process=True,
                          timeout=240.0)
    assert result['exit_codes'] == {'cw_plant': 0}
    data = read_bag(result['bag'])
    summary = summarize(data)
    assert set(summary['sensors']) == {'camera', 'lidar'} and summary['recording_complete'], summary['messages']
    offline = simulate(handover_scenario(initial_state_dispersion=True), 'snn_ekf')
    stamps = np.round(data.estimate_t / 0.1).astype(int)
    inside = stamps <= 300
    assert inside.sum() == 301
    np.testing.assert_allclose(data.estimate[inside], offline.estimate[0, stamps[inside]], rtol=0, atol=1e-9)


def test_the_docking_suite_over_ros_equals_the_offline_docking_scenario_through_the_hand_over(tmp_path):
    """``--sensor docking`` (config/sensor_docking.yaml), single process, 60 s: the LIDAR alone
    beyond 30 m, both sensors, then the camera alone inside the LIDAR's 1.8 m; each sensor draws
    R at the true range. The estimates equal docking_scenario() offline to 1e-9."""
    from snn_estimator.sim.scenarios import docking_scenario
    result = run_pipeline(tmp_path, estimator='snn_ekf', sensor='docking', duration=60.0, single_process=True,
                          timeout=300.0)
    assert result['exit_codes'] == {'cw_plant': 0}
    data = read_bag(result['bag'])
    summary = summarize(data)
    assert set(summary['sensors']) == {'lidar', 'camera'} and summary['recording_complete'], summary['messages']
    offline = simulate(docking_scenario(initial_state_dispersion=True), 'snn_ekf')
    truth_range = np.linalg.norm(offline.truth[0, :601, :3], axis=1)
    assert truth_range[0] > 30.0 and truth_range.min() < 1.8  # the run crosses both hand-overs
    stamps = np.round(data.estimate_t / 0.1).astype(int)
    inside = stamps <= 600
    assert inside.sum() == 601
    np.testing.assert_allclose(data.estimate[inside], offline.estimate[0, stamps[inside]], rtol=0, atol=1e-9)


@pytest.fixture(scope='module')
def lidar_dropout_run(tmp_path_factory):
    """The fused loop for 60 s with the LIDAR dropping 5 % of its samples (not published)."""
    run_dir = tmp_path_factory.mktemp('camera_lidar_dropout')
    run_pipeline(run_dir, estimator='snn_ekf', sensor='camera+lidar', duration=60.0, timeout=240.0,
                 extra={'lidar': {'dropout_probability': 0.05}})
    data = read_bag(run_dir / 'bag')
    return data, summarize(data)


def test_a_sensors_own_dropouts_are_its_gaps_and_explained_by_its_count(lidar_dropout_run):
    data, summary = lidar_dropout_run
    lidar, own = summary['sensors']['lidar'], data.last_diagnostics('lidar')
    dropped = int(own['measurement_rejected.dropout'])
    assert dropped > 0 and lidar['missing'] == lidar['not_published'] == dropped and lidar['lost'] == 0
    assert len(lidar['gaps']) == dropped and all(a == b for a, b in lidar['gaps'])  # one stamp each
    assert all(round(a * 10) % 2 == 0 for a, _ in lidar['gaps'])  # on its 0.2 s grid
    assert summary['sensors']['camera']['gaps'] == [] and summary['recording_complete']
