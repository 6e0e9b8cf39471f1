"""The runner that feeds a filter from a message stream, without ROS: pairing, gating,
start-up strategies and recovery, at unit speed."""

import numpy as np
import pytest

from snn_estimator import make_estimator, rendezvous_scenario, simulate
from snn_estimator.plant.control import lqr_control, lqr_gain
from snn_estimator.plant.sensors import PositionSensor
from snn_estimator.plant.truth import Plant
from snn_estimator.runners.filter_runner import FilterRunner, RunnerSettings
from snn_estimator.runners.gates import NS
from snn_estimator.runners.start_up import History

DT = 100_000_000
R = 1e-2 * np.eye(3)
X0 = np.array([70.0, 30.0, -5.0])


class Clock:
    """A wall clock the test moves by hand."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def make_runner(kind='ekf', dispersion=False, **settings):
    scenario = rendezvous_scenario(initial_state_dispersion=dispersion)
    estimator = make_estimator(kind, scenario.estimator, scenario.model)
    published = []
    wall = Clock()
    runner = FilterRunner(estimator, RunnerSettings(time_step=0.1, **settings), R,
                          publish=lambda stamp: published.append((stamp, estimator.x_hat.copy())),
                          wall_clock=wall)
    return runner, published, wall


def test_the_first_estimate_answers_the_first_measurement_and_steps_pair_z_with_u():
    runner, published, _ = make_runner()
    assert runner.start('auto') == 'waiting' and published == []
    assert runner.measurement(3 * DT, X0) is None
    assert [stamp for stamp, _ in published] == [3 * DT]  # x_hat0 at t0, from the parameters
    np.testing.assert_allclose(published[0][1], [70, 30, -5, -1.7, -0.9, 0.25])
    assert runner.estimator.steps == 0  # no control yet
    runner.control(3 * DT, np.zeros(3))
    assert [stamp for stamp, _ in published] == [3 * DT, 4 * DT] and runner.estimator.steps == 1


def test_bad_inputs_are_rejected_with_their_reason_and_counted():
    runner, published, _ = make_runner(max_input_age=0.25)
    runner.start('auto')
    runner.measurement(0, X0)
    for k in range(1, 5):
        runner.control((k - 1) * DT, np.zeros(3))
        runner.measurement(k * DT, X0)
    assert runner.time_ns == 4 * DT
    assert runner.measurement(4 * DT, X0) == 'duplicate'
    assert runner.measurement(3 * DT, X0) == 'duplicate'  # z_3 was used
    assert runner.measurement(2 * DT + DT // 2, X0) == 'stale'
    assert runner.measurement(5 * DT + DT // 2, X0) == 'misaligned'
    assert runner.measurement(DT, X0) == 'too_old'
    assert runner.measurement(100 * DT, X0, now_ns=5 * DT) == 'future'  # 9.5 s ahead of the clock
    assert runner.control(-DT, np.zeros(3)) == 'before_init'
    values = runner.values()
    assert values['measurements_rejected'] == 6 and values['controls_rejected'] == 1
    assert values['measurements_received'] == (values['measurements_rejected'] + values['measurements_used']
                                               + values['measurements_dropped'] + values['measurements_pending'])


def test_a_control_missing_two_measurements_later_is_held_and_counted():
    runner, published, _ = make_runner()
    runner.start('auto')
    runner.measurement(0, X0)
    runner.control(0, np.array([0.01, 0.0, 0.0]))
    runner.measurement(DT, X0)
    runner.measurement(2 * DT, X0)
    assert runner.estimator.steps == 1  # u_1 may still come
    runner.measurement(3 * DT, X0)
    assert runner.estimator.steps == 2 and runner.control_book.missing == 1


def test_a_sensor_dropout_is_predicted_over_once_the_clock_is_two_steps_ahead():
    runner, published, wall = make_runner(dropout_wait=0.25)
    runner.start('auto')
    runner.measurement(0, X0)
    runner.control(0, np.zeros(3))
    runner.watchdog(now_ns=5 * DT)
    assert runner.estimator.steps == 1  # a measurement came less than dropout_wait ago
    wall.now = 1.0
    runner.watchdog(now_ns=5 * DT)
    assert runner.time_ns == 5 * DT and runner.measurement_queue.dropout_steps == 4


def loop_history(steps, seed=3):
    """What the topics of a running closed loop held after ``steps`` steps: the sensor's
    measurements, the controller's controls, the estimates of an EKF; and the truth one step
    past the newest measurement (where a filter that has used that measurement stands)."""
    scenario = rendezvous_scenario()
    model = scenario.model
    plant = Plant(model, scenario.x0, scenario.process_noise, [seed])
    sensor = PositionSensor(model, scenario.measurement_noise, [seed])
    gain = lqr_gain(model, scenario.lqr_state_weight, scenario.lqr_input_weight)
    ekf = make_estimator('ekf', scenario.estimator, model)
    history = History({}, {}, {})
    for k in range(steps):
        history.estimates[k * DT] = (ekf.x_hat.copy(), ekf.P.copy())
        u = lqr_control(gain, ekf.x_hat)
        z = sensor.measure(plant.x)[0]
        history.measurements[k * DT] = z
        history.controls[k * DT] = u
        ekf.step(z, u, 0.1)
        plant.step(u, 0.1)
    return history, plant.x[0], ekf


def test_a_hot_swap_starts_from_the_newest_estimate_and_replays_the_measurements_since():
    history, _, ekf = loop_history(150)
    newest = max(history.estimates)
    # the earlier estimator's estimate 5 steps back; the measurements since are replayed
    estimates = {t: v for t, v in history.estimates.items() if t <= newest - 5 * DT}
    runner, published, _ = make_runner('ekf')
    mode = runner.start('auto', History(history.measurements, history.controls, estimates))
    assert mode == 'last_estimate' and runner.start_ns == newest - 5 * DT
    assert runner.time_ns == newest + DT  # every queued measurement replayed with its control
    # the same EKF from the same estimate and covariance on the same inputs: the same estimate
    np.testing.assert_allclose(runner.estimator.x_hat, ekf.x_hat, rtol=0, atol=1e-9)


def test_a_restart_fits_the_measurement_history_and_its_error_is_within_its_covariance():
    history, truth, _ = loop_history(200)
    runner, published, _ = make_runner('ekf', initial_fit_window=10.0)
    mode = runner.start('auto', History(history.measurements, history.controls, {}))
    assert mode == 'history'
    assert runner.start_ns == max(history.measurements) and published[0][0] == runner.start_ns
    assert runner.values()['history_measurements'] == 200 and runner.values()['measurements_dropped'] == 0
    # the fit (published at the newest stamp) was then stepped with the newest measurement: the
    # filter stands one step past it, where the truth is compared
    assert runner.time_ns == runner.start_ns + DT and runner.estimator.steps == 1
    error = runner.estimator.x_hat - truth
    covariance = runner.estimator.P
    # every state (positions and velocities) within 4 sigma, and the NEES below chi2(6) at 99.9 %
    assert np.all(np.abs(error) < 4 * np.sqrt(np.diag(covariance)))
    assert error @ np.linalg.solve(covariance, error) < 22.46


def test_a_short_history_is_a_fresh_loop_that_starts_at_its_first_measurement_and_loses_nothing():
    history, _, _ = loop_history(12)  # 1.2 s: shorter than the fit window
    runner, published, _ = make_runner('ekf')
    mode = runner.start('auto', History(history.measurements, history.controls, {}))
    assert mode == 'parameters' and runner.start_ns == 0
    assert runner.time_ns == 12 * DT and runner.estimator.steps == 12  # every step replayed


@pytest.mark.parametrize('kind, timing', [('snn_emsif_weighted', 'grid'), ('ekf', 'any')])
def test_the_runner_fed_the_offline_loop_equals_the_offline_simulator(kind, timing):
    """One source of truth: the runner steps exactly as simulate() does. With measurement_timing
    any the controller answers the estimate published at each measurement's own stamp, and
    every estimate is the same (the last one waits for a next measurement)."""
    scenario = rendezvous_scenario(initial_state_dispersion=True)
    steps = 200
    offline = simulate(scenario.__class__(**{**scenario.__dict__, 'duration': steps * 0.1}), kind)
    model = scenario.model
    plant = Plant(model, scenario.x0, scenario.process_noise, [0])
    sensor = PositionSensor(model, scenario.measurement_noise, [0])
    gain = lqr_gain(model, scenario.lqr_state_weight, scenario.lqr_input_weight)
    runner, published, _ = make_runner(kind, dispersion=True, measurement_timing=timing)
    runner.start('auto')
    for k in range(steps):
        runner.measurement(k * DT, sensor.measure(plant.x)[0])
        assert timing == 'grid' or published[-1][0] == k * DT  # answered at its own stamp
        u = lqr_control(gain, published[-1][1])
        runner.control(k * DT, u)
        plant.step(u, 0.1)
    estimates = np.array([x for _, x in published])
    expected = offline.estimate[0] if timing == 'grid' else offline.estimate[0][:steps]
    np.testing.assert_allclose(estimates, expected, rtol=0, atol=1e-12)


def test_a_persistently_inconsistent_innovation_re_initialises_from_the_measurement():
    runner, published, _ = make_runner('ekf', nis_threshold=25.0, nis_window=3)
    runner.start('auto')
    far = X0 + 50.0
    runner.measurement(0, X0)
    for k in range(1, 5):
        runner.control((k - 1) * DT, np.zeros(3))
        runner.measurement(k * DT, far)
    assert runner.events['reinitialisations.inconsistent_innovation'] == 1
    np.testing.assert_allclose(runner.estimator.x_hat[:3], far, atol=1.0)


def test_without_a_clock_a_stamp_far_back_restarts_the_filter():
    runner, published, _ = make_runner(time_jump_threshold=1.0)
    runner.start('auto')
    runner.measurement(40 * DT, X0)
    runner.control(40 * DT, np.zeros(3))
    assert runner.measurement(0, X0, now_ns=0) is None
    assert runner.events['time_jumps'] == 1 and runner.start_ns == 0


@pytest.mark.parametrize('mode', ['sideways', ''])
def test_an_unknown_start_mode_is_refused(mode):
    runner, _, _ = make_runner()
    with pytest.raises(ValueError, match='start mode'):
        runner.start(mode)


def test_has_measurement_tells_a_resend_from_new_information():
    runner, _, _ = make_runner()
    runner.start('auto')
    runner.measurement(0, X0)
    assert runner.has_measurement(0) and not runner.has_measurement(DT)
    runner.control(0, np.zeros(3))
    runner.measurement(DT, X0)
    assert runner.has_measurement(0) and runner.has_measurement(DT) and not runner.has_measurement(2 * DT)
    assert NS == 10 * DT


class Loop:
    """The closed loop around a runner (truth, sensor, LQR on the published estimate), seeded."""

    def __init__(self, kind='ekf', seed=5, **settings):
        scenario = rendezvous_scenario()
        self.model = scenario.model
        self.plant = Plant(self.model, scenario.x0, scenario.process_noise, [seed])
        self.sensor = PositionSensor(self.model, scenario.measurement_noise, [seed])
        self.gain = lqr_gain(self.model, scenario.lqr_state_weight, scenario.lqr_input_weight)
        self.runner, self.published, _ = make_runner(kind, **settings)
        self.runner.start('auto')
        self.k = 0
        self.sensor_offset = np.zeros(3)

    def run(self, steps):
        for _ in range(steps):
            truth = self.plant.x[0].copy()
            self.runner.measurement(self.k * DT, self.sensor.measure(self.plant.x)[0] + self.sensor_offset)
            u = lqr_control(self.gain, self.published[-1][1])
            self.runner.control(self.k * DT, u)
            self.plant.step(u, 0.1)
            self.k += 1
        return truth  # the truth at the last measurement's stamp


WRONG = np.array([170.0, -40.0, 20.0, 1.0, -1.0, 0.5])  # 100 m and ~1.5 m/s off


def test_a_reset_mid_flight_starts_from_the_recent_measurements_near_the_truth():
    loop = Loop()
    loop.run(150)
    loop.runner.set_state(WRONG, np.eye(6))  # whatever the filter holds now, the reset ignores it
    assert loop.runner.reset('test') == 'data'
    loop.run(1)  # the next step re-initialises from the measurements of the last 10 s, then updates
    error = loop.published[-1][1] - loop.plant.x[0]
    assert loop.runner.events['restarts_from.least_squares'] == 1
    assert np.abs(error[:3]).max() < 0.2 and np.abs(error[3:]).max() < 0.02, error
    parameters = loop.runner.estimator.settings.initial_state
    assert np.abs(parameters[:3] - loop.plant.x[0, :3]).max() > 10.0  # the parameters are far from here


def test_an_inconsistent_filter_is_re_initialised_from_the_recent_measurements_velocity_included():
    loop = Loop(nis_window=5)
    loop.run(150)
    loop.runner.set_state(WRONG, np.diag([1e-2] * 3 + [1e-4] * 3))  # confidently wrong
    loop.run(6)  # five inconsistent steps, then the re-initialisation and one update
    assert loop.runner.events['reinitialisations.inconsistent_innovation'] == 1
    error = loop.published[-1][1] - loop.plant.x[0]
    assert np.abs(error[:3]).max() < 0.2 and np.abs(error[3:]).max() < 0.02, error  # velocity from the fit
    assert loop.runner.values()['reset_storms'] == 0


def test_a_reset_storm_is_detected_and_reported():
    loop = Loop(nis_window=3)
    loop.run(100)
    for jump in range(4):  # the sensor jumps 50 m every 2 s: the filter is re-initialised each time
        loop.sensor_offset = np.full(3, 50.0 * (jump + 1))
        loop.run(20)
    values = loop.runner.values()
    assert values['reinitialisations'] >= 3 and values['reset_storms'] == 1
    assert '1 reset storms' in '; '.join(loop.runner.problems())


@pytest.mark.parametrize('clock_ns, cause', [(1_700_000_000 * NS, 'use_sim_time'), (50 * DT, 'arrive late')])
def test_stamps_off_the_clock_name_the_likely_cause(clock_ns, cause):
    """A wall clock against simulated stamps is a configuration error; a few seconds apart,
    a process lagging (a starved CPU) is the likely cause."""
    logs = []
    scenario = rendezvous_scenario()
    runner = FilterRunner(make_estimator('ekf', scenario.estimator, scenario.model), RunnerSettings(time_step=0.1),
                          R, publish=lambda stamp: None, log=lambda level, message: logs.append(message))
    runner.start('auto')
    runner.measurement(10 * DT, X0, now_ns=clock_ns)
    assert sum(cause in m for m in logs) == 1 and runner.measurement_queue.events['stamps_off_the_clock'] == 1


# ------------------------------------------------------------------ measurement_timing: any
def _open_loop_streams(steps, skipped=(), seed=3):
    """Measurements and controls of a free-ish rendezvous (LQR on the truth), on the grid."""
    scenario = rendezvous_scenario()
    model = scenario.model
    plant = Plant(model, scenario.x0, scenario.process_noise, [seed])
    sensor = PositionSensor(model, scenario.measurement_noise, [seed])
    gain = lqr_gain(model, scenario.lqr_state_weight, scenario.lqr_input_weight)
    measurements, controls = {}, {}
    for k in range(steps):
        z = sensor.measure(plant.x)[0]
        if k not in skipped:
            measurements[k * DT] = z
        controls[k * DT] = lqr_control(gain, plant.x[0])
        plant.step(controls[k * DT], 0.1)
    return measurements, controls


def test_any_timing_on_grid_stamps_publishes_the_grid_estimates_dropouts_included():
    """measurement_timing any holds z_k until the next stamp; on grid stamps that is exactly
    the grid runner's step z_k over [t_k, t_k + dt), published when z_{k+1} comes instead of
    at once; a gap of three steps is one held step and two predictions in both."""
    measurements, controls = _open_loop_streams(60, skipped=(20, 21, 40))
    results = {}
    for timing in ('grid', 'any'):
        runner, published, _ = make_runner('snn_emsif_weighted', measurement_timing=timing)
        runner.start('auto')
        for k in range(60):
            runner.control(k * DT, controls[k * DT])
            if k * DT in measurements:
                assert runner.measurement(k * DT, measurements[k * DT]) is None
        results[timing] = dict((stamp, x) for stamp, x in published)
    grid, any_ = results['grid'], results['any']
    assert sorted(any_) == [k * DT for k in range(60)]  # x_hat at every stamp up to the last z
    assert set(any_) <= set(grid)
    for stamp, x in any_.items():
        np.testing.assert_allclose(x, grid[stamp], rtol=0, atol=1e-12, err_msg=f'{stamp / NS} s')


def _jittered_stamps(count, jitter, seed=11):
    rng = np.random.default_rng(seed)
    return (np.arange(count) * 0.1 + rng.uniform(-jitter, jitter, count) + 5.0) * NS // 1


def _jittered_loop(jitter, kind='snn_ekf', count=600):
    """The closed loop with the sensor on its own clock: truth propagated exactly between the
    stamps, the LQR answering each estimate; returns the runner, the stamps and the errors."""
    scenario = rendezvous_scenario()
    model = scenario.model
    stamps = [int(t) for t in _jittered_stamps(count, jitter)]
    plant = Plant(model, scenario.x0, scenario.process_noise, [4])
    sensor = PositionSensor(model, scenario.measurement_noise, [4])
    gain = lqr_gain(model, scenario.lqr_state_weight, scenario.lqr_input_weight)
    runner, published, _ = make_runner(kind, measurement_timing='any')
    runner.start('auto')
    errors, answered = [], []
    for j, stamp in enumerate(stamps):
        truth = plant.x[0].copy()
        assert runner.measurement(stamp, sensor.measure(plant.x)[0]) is None
        answered.append(published[-1][0])
        errors.append(published[-1][1] - truth)
        u = lqr_control(gain, published[-1][1])
        runner.control(stamp, u)
        if j + 1 < len(stamps):
            plant.step(u, (stamps[j + 1] - stamp) / NS)
    return runner, stamps, answered, np.array(errors)


def test_any_timing_fuses_jittered_stamps_answers_each_at_its_stamp_and_tracks_the_truth():
    """A sensor on its own clock (~10 Hz, +-30 ms jitter): every measurement is answered once,
    at its own stamp, with nothing rejected or predicted over, and the error over 30-60 s
    stays within 1.3x of the same loop's with the sensor on a 10 Hz grid."""
    runner, stamps, answered, errors = _jittered_loop(0.03)
    assert answered == stamps
    assert runner.measurement_queue.rejected == {} and runner.measurement_queue.used == len(stamps) - 1
    assert runner.measurement_queue.dropout_steps == 0 and runner.control_book.missing == 0
    assert len(set(np.diff(stamps))) > 500  # really off any grid
    # steps of 600 lengths: the per-dt caches stay bounded (a node runs for days)
    estimator = runner.estimator
    assert len(estimator.model.__dict__.get('_zoh_cache', {})) <= 64
    assert estimator.program.dynamics.cached_steps <= 64
    _, _, _, grid_errors = _jittered_loop(0.0)
    rmse, grid_rmse = (np.sqrt((e[300:] ** 2).mean(axis=0)) for e in (errors, grid_errors))
    assert np.all(rmse < 1.3 * grid_rmse), rmse / grid_rmse


def test_any_timing_rejects_a_late_measurement_as_stale_and_never_as_misaligned():
    runner, published, _ = make_runner('ekf', measurement_timing='any')
    runner.start('auto')
    for stamp in (1_000_000_000, 1_093_000_000, 1_207_000_000):
        runner.control(stamp, np.zeros(3))
        assert runner.measurement(stamp, X0) is None
    assert [s for s, _ in published] == [1_000_000_000, 1_093_000_000, 1_207_000_000]
    assert runner.measurement(1_150_000_000, X0) == 'stale'  # older than the newest fused
    assert runner.measurement_queue.rejected == {'stale': 1}
    with pytest.raises(ValueError, match='measurement_timing'):
        RunnerSettings(time_step=0.1, measurement_timing='sometimes')


def test_a_grid_runner_names_measurement_timing_for_a_stamp_off_its_grid():
    logs = []
    scenario = rendezvous_scenario()
    runner = FilterRunner(make_estimator('ekf', scenario.estimator, scenario.model), RunnerSettings(time_step=0.1),
                          R, publish=lambda stamp: None, log=lambda level, message: logs.append(message))
    runner.start('auto')
    runner.measurement(0, X0)
    assert runner.measurement(DT + 7, X0) == 'misaligned'
    assert 'measurement_timing: any' in logs[-1]


def make_lidar_runner(kind='ekf'):
    """A runner whose filter takes a LIDAR's range, azimuth and elevation (H(x_hat) each step)."""
    from snn_estimator.sim.scenarios import sensor_rendezvous_scenario
    scenario = sensor_rendezvous_scenario()
    estimator = make_estimator(kind, scenario.estimator, scenario.model, measurement=scenario.sensor)
    published = []
    runner = FilterRunner(estimator, RunnerSettings(time_step=0.1), scenario.sensor.noise,
                          publish=lambda stamp: published.append(stamp), wall_clock=Clock())
    return runner, published, scenario


def test_a_covariance_the_step_cannot_keep_reinitialises_the_filter_counted_and_never_published():
    """The step's guard (docs/decisions.md, 43): a filter whose gain overflows (a LIDAR whose H
    blows up beyond 1 km) raises CovarianceLost; the runner re-initialises it from the data,
    counts it as reinitialisations.covariance_lost, and every estimate it publishes is finite
    with a positive definite P."""
    from test_measurement_filters import MOUNTING, OverflowingLidar
    scenario = rendezvous_scenario()
    model = OverflowingLidar([1e-2, 1e-6, 1e-6], mounting_rotation=MOUNTING)
    estimator = make_estimator('ekf', scenario.estimator.replace(measurement_noise=model.noise), scenario.model,
                               measurement=model)
    published = []
    runner = FilterRunner(estimator, RunnerSettings(time_step=0.1), model.noise,
                          publish=lambda stamp: published.append((estimator.x_hat.copy(), estimator.P.copy())),
                          wall_clock=Clock())
    x = np.array([70.0, 30.0, -5.0, -1.7, -0.9, 0.25])
    runner.start('auto')
    for k in range(6):
        if k == 3:  # the estimate thrown beyond 1 km: the next step's H overflows
            runner.set_state(x + np.array([5e3, 0.0, 0.0, 0.0, 0.0, 0.0]), None)
        with np.errstate(all='ignore'):
            runner.measurement(k * DT, model.h(x))
            runner.control(k * DT, np.zeros(3))
    assert runner.events['reinitialisations.covariance_lost'] == 1
    assert len(published) >= 6
    for x_hat, covariance in published:
        assert np.isfinite(x_hat).all() and np.linalg.eigvalsh(covariance).min() > 0.0


def test_a_sample_the_sensor_could_not_measure_is_predicted_over_at_once_and_answered_again():
    """The LIDAR below its minimum range says "nothing measured" (docs/sensors.md): the filter
    predicts over that step as soon as its control is here, with no dropout wait (the wall
    clock never moves here), exactly as a step without a measurement; a resend of that sample
    is recognised and a stale one rejected, outside the measurement counts."""
    runner, published, scenario = make_lidar_runner()
    twin = make_estimator('ekf', scenario.estimator, scenario.model, measurement=scenario.sensor)
    x = np.array([[70.0, 30.0, -5.0, 0.0, 0.0, 0.0]])
    z0 = scenario.sensor.h(x)[0]
    runner.start('auto')
    runner.measurement(0, z0)
    runner.control(0, np.zeros(3))
    twin.step(z0, np.zeros(3), 0.1)
    assert runner.no_measurement(DT) is None and published == [0, DT]  # waits for u_1
    runner.control(DT, np.zeros(3))
    twin.step(None, np.zeros(3), 0.1)
    queue = runner.measurement_queue
    assert published == [0, DT, 2 * DT] and queue.dropout_steps == 1 and queue.not_measured == 1
    np.testing.assert_array_equal(runner.estimator.x_hat, twin.x_hat)
    assert runner.has_measurement(DT)  # a resend: answered with the estimate it got
    assert runner.no_measurement(DT) == 'stale' and runner.measurement_queue.events['not_measured_rejected.stale'] == 1
    values = runner.values()
    assert values['measurements_received'] == 1 and values['not_measured'] == 2
    assert values['measurements_rejected'] == 0 and values['measurements_pending'] == 0


def test_a_nonlinear_sensor_restarts_from_the_position_its_sample_gives_and_never_fits_z_as_cx():
    """No least-squares start or restart (those fit z = C x); a re-initialisation takes the
    position the LIDAR sample determines (position_of), not C^+ z of (range, angles)."""
    runner, _, scenario = make_lidar_runner()
    x = np.array([70.0, 30.0, -5.0, 0.0, 0.0, 0.0])
    model = scenario.model
    measurements, truth = {}, x
    for k in range(120):  # 12 s of history, more than initial_fit_window
        measurements[k * DT] = scenario.sensor.h(truth[None])[0]
        truth = model.transition(truth, np.zeros(3), 0.1)
    assert runner.start('history', History(measurements, {}, {})) == 'parameters'
    assert runner.events['history_starts'] == 0
    z = scenario.sensor.h(truth[None])[0]
    restart, _, source = runner.recovery.restart_state(120 * DT, z)
    np.testing.assert_allclose(restart[:3], truth[:3], rtol=0, atol=1e-9)
    assert source != 'least_squares'


# ------------------------------------------------------------------ provisional steps (issue 25, 4)
def _realtime_stream(steps, late=(), seed=3, silent_from=None, validity=0.5):
    """What a realtime plant's loop delivers: z_k, the controller's u_k (a fixed sequence, the
    same whatever the estimates; none from ``silent_from`` on) and the plant's report of what it
    stepped with from t_k (PlantRunner); the controls of ``late`` reach the plant after its tick
    (it applies the one in force) while the estimator has them before the report."""
    from snn_estimator.runners.plant_runner import PlantRunner, PlantSettings
    scenario = rendezvous_scenario()
    plant = Plant(scenario.model, scenario.x0, scenario.process_noise, [seed])
    sensor = PositionSensor(scenario.model, scenario.measurement_noise, [seed])
    reports = {}
    ticker = PlantRunner(plant, PlantSettings(time_step=0.1, mode='realtime', control_validity=validity),
                         publish=lambda stamp, resend: None,
                         applied=lambda stamp, u: reports.__setitem__(stamp, np.array(u, dtype=float)))
    ticker.begin()
    measurements, controls = {}, {}
    for k in range(steps):
        measurements[k * DT] = sensor.measure(plant.x)[0]
        if silent_from is None or k < silent_from:
            controls[k * DT] = np.array([2e-3, -1e-3, 5e-4]) * np.sin(0.3 * k + 1.0)
        commanded = k * DT in controls
        if commanded and k not in late:
            ticker.control(k * DT, controls[k * DT])
        ticker.tick()
        if commanded and k in late:
            ticker.control(k * DT, controls[k * DT])
    return measurements, controls, reports


def _feed(runner, out, stream, report_delay=1, lost=(), lost_controls=()):
    """Feed a runner in a realtime order: at tick k the report of step k - report_delay (unless
    lost), then z_k; the controller's u_k (unless lost) came before z_k (it answered x_hat(t_k),
    published at tick k - 1). Returns the tick at which each stamp was first published."""
    measurements, controls, reports = stream
    steps = len(measurements)
    first_tick = {}
    for k in range(steps + report_delay + 3):
        reported = k - report_delay
        if 0 <= reported < steps and reported not in lost:
            runner.applied(reported * DT, reports[reported * DT])
        if k < steps:
            if k * DT in controls and k not in lost_controls:
                runner.control(k * DT, controls[k * DT])
            runner.measurement(k * DT, measurements[k * DT])
        for stamp in out.first:
            first_tick.setdefault(stamp, k)
        out.most_held = max(out.most_held, runner.provisional_log.held_count)
    return first_tick


class Published:
    """What a runner published: every estimate in order, the stamps as first published, and the
    stamps published again after a correction."""

    def __init__(self):
        self.estimates, self.first, self.again = [], [], []
        self.most_held = 0  # steps held at once, at most (after a tick)


def _provisional_runner(kind='ekf', provisional=True, **settings):
    scenario = rendezvous_scenario()
    estimator = make_estimator(kind, scenario.estimator, scenario.model)
    out = Published()

    def publish(stamps):
        return lambda stamp: (stamps.append(stamp), out.estimates.append((stamp, estimator.x_hat.copy())))
    runner = FilterRunner(estimator, RunnerSettings(time_step=0.1, provisional_steps=provisional, **settings), R,
                          publish=publish(out.first), republish=publish(out.again))
    runner.start('auto')
    return runner, out


def _final(published):
    """Stamp -> the last estimate published under it (a correction replaces the first)."""
    return {stamp: x for stamp, x in published}


def _stepped_with(kind, stream, used):
    """The estimates of a bare estimator stepped with z_k and the control ``used[k]``: what
    waiting for every report gives (an independent loop, no runner)."""
    measurements = stream[0]
    estimator = make_estimator(kind, rendezvous_scenario().estimator, rendezvous_scenario().model)
    estimates = {0: estimator.x_hat.copy()}
    for k in range(len(measurements)):
        estimator.step(measurements[k * DT], used[k], 0.1)
        estimates[(k + 1) * DT] = estimator.x_hat.copy()
    return estimates


def test_a_provisional_step_the_plant_confirms_gives_exactly_the_estimates_of_waiting_one_step_sooner():
    """Every report equals the controller's u_k: the estimate of t_{k+1} is published at the tick
    of z_k (waiting for the report: one tick later), once, and the very same numbers."""
    stream = _realtime_stream(60)
    runs = {}
    for provisional in (True, False):
        runner, out = _provisional_runner('snn_ekf', provisional)
        runs[provisional] = (runner, out, _feed(runner, out, stream))
    (runner, out, ticks), (waiting, waited, waited_ticks) = runs[True], runs[False]
    assert out.again == [] and runner.values()['provisional_corrected'] == 0
    stamps = [k * DT for k in range(61)]
    assert [stamp for stamp, _ in out.estimates] == [stamp for stamp, _ in waited.estimates] == stamps
    for (stamp, x), (_, y) in zip(out.estimates, waited.estimates):
        np.testing.assert_array_equal(x, y, err_msg=f'{stamp / NS} s')
    assert all(ticks[(k + 1) * DT] == k for k in range(60))
    assert all(waited_ticks[(k + 1) * DT] == k + 1 for k in range(1, 60))  # the report's tick
    assert runner.values()['provisional_steps'] == 59  # step 0 came before the plant's first report
    assert runner.provisional_log.held_count == 0 and runner.values()['provisional_held'] == 0
    for key in ('measurements_used', 'controls_missing', 'dropout_steps', 'spikes_total', 'steps'):
        assert runner.values()[key] == waiting.values()[key], key


@pytest.mark.parametrize('kind', ['snn_ekf', 'ekf'])
def test_a_report_that_differs_restores_the_step_and_takes_it_again_exactly_as_waiting_would(kind):
    """u_k came after the plant's tick at three steps: the plant flew the control in force and says
    so; the estimator had stepped with u_k, so it goes back, takes the step with what was applied
    and publishes the corrected estimate again under its stamp. Every stamp's last estimate is
    the bare estimator stepped with the reports, bit for bit, as the runner that waits."""
    late = {7, 8, 20}
    stream = _realtime_stream(40, late=late)
    measurements, controls, reports = stream
    differing = [k for k in sorted(late) if not np.array_equal(reports[k * DT], controls[k * DT])]
    assert differing == sorted(late)
    expected = _stepped_with(kind, stream, [reports[k * DT] for k in range(40)])
    finals = {}
    for provisional in (True, False):
        runner, out = _provisional_runner(kind, provisional)
        _feed(runner, out, stream)
        finals[provisional] = _final(out.estimates)
        assert sorted(finals[provisional]) == sorted(expected)
        for stamp, x in expected.items():
            np.testing.assert_array_equal(finals[provisional][stamp], x, err_msg=f'{provisional}: {stamp / NS} s')
        if provisional:
            assert out.again == [(k + 1) * DT for k in differing]  # each corrected stamp once more
            values = runner.values()
            assert values['provisional_corrected'] == len(differing) and values['provisional_held'] == 0
            assert values['provisional_unconfirmed'] == 0 and 'applied_missing' not in values
            first = dict(out.estimates[::-1])  # the first estimate of each stamp
            assert not np.array_equal(first[8 * DT], expected[8 * DT])  # published with the late u_7
        else:
            assert out.again == []


def test_lost_reports_leave_the_commanded_control_and_never_hold_more_than_the_limit():
    """Reports of steps 10 and 30-59 lost (a plant that stopped reporting): each held step is
    accepted as applied once PROVISIONAL_LIMIT later steps are held behind it, counted; memory
    stays bounded; the estimates are those of the controller's controls, as the waiting runner's."""
    from snn_estimator.runners.provisional import PROVISIONAL_LIMIT
    lost = {10, *range(30, 60)}
    stream = _realtime_stream(60)
    measurements, controls, reports = stream
    expected = _stepped_with('ekf', stream, [controls[k * DT] for k in range(60)])
    runner, out = _provisional_runner('ekf')
    _feed(runner, out, stream, lost=lost)
    assert out.most_held == PROVISIONAL_LIMIT
    final = _final(out.estimates)
    for stamp, x in expected.items():
        np.testing.assert_array_equal(final[stamp], x, err_msg=f'{stamp / NS} s')
    values = runner.values()
    assert values['provisional_unconfirmed'] == 1 + (60 - 30 - PROVISIONAL_LIMIT)
    assert values['provisional_held'] == PROVISIONAL_LIMIT and values['provisional_corrected'] == 0
    waiting, waited = _provisional_runner('ekf', provisional=False)
    _feed(waiting, waited, stream, lost=lost)
    for stamp, x in _final(waited.estimates).items():
        np.testing.assert_array_equal(final[stamp], x, err_msg=f'waiting: {stamp / NS} s')


def test_several_held_steps_corrected_in_order_with_reports_three_ticks_late():
    """Reports come three ticks after their step (z_{k+1}, z_{k+2} came first), two of them
    differing: three steps are held, a correction takes its step and every later one again
    in order, and the last estimate of every stamp is the estimator stepped with the reports."""
    late = {12, 13, 25}
    stream = _realtime_stream(40, late=late)
    measurements, controls, reports = stream
    expected = _stepped_with('snn_ekf', stream, [reports[k * DT] for k in range(40)])
    runner, out = _provisional_runner('snn_ekf')
    ticks = _feed(runner, out, stream, report_delay=3)
    final = _final(out.estimates)
    for stamp, x in expected.items():
        np.testing.assert_array_equal(final[stamp], x, err_msg=f'{stamp / NS} s')
    assert all(ticks[(k + 1) * DT] == k for k in range(40))  # never waited for a report
    assert out.most_held == 3
    values = runner.values()
    assert values['provisional_corrected'] == 3 and values['provisional_held'] == 0
    # each correction republished its step and the two (three at the end) held behind it
    assert out.again[:3] == [13 * DT, 14 * DT, 15 * DT] and len(out.again) == 9
    assert values['measurements_used'] == 40 and values['steps'] == 40
    assert values['provisional_steps'] == 37  # steps 0-2 came before the plant's first report


def test_set_state_accepts_the_held_steps_so_a_later_report_never_undoes_it():
    """Steps 1-7 held (no report yet), then the state is set: they are accepted as they are
    (counted), and step 5's differing report that comes afterwards goes back to nothing."""
    stream = _realtime_stream(8, late={5})
    measurements, controls, reports = stream
    runner, out = _provisional_runner('ekf')
    for k in range(8):
        runner.control(k * DT, controls[k * DT])
        runner.measurement(k * DT, measurements[k * DT])
        if k == 0:
            runner.applied(0, reports[0])
    assert runner.provisional_log.held_count == 7
    runner.set_state(WRONG, np.eye(6))
    assert runner.provisional_log.held_count == 0 and runner.values()['provisional_unconfirmed'] == 7
    for k in range(1, 8):
        runner.applied(k * DT, reports[k * DT])  # step 5's differs: nothing to go back to
    np.testing.assert_array_equal(runner.estimator.x_hat, WRONG)
    assert runner.values()['provisional_corrected'] == 0 and out.again == []


def test_a_correction_leaves_the_counters_and_the_recovery_data_as_if_the_applied_control_came():
    """The controller dies after step 20, whose control the plant got but the estimator lost;
    control_validity 0.15 s; reports five ticks late. The estimator steps 20 with the control in
    force (u_19) and predicts 21-22 with zero thrust (u_19 expired), all held; step 20's report
    says u_20: the three are taken again (u_20, then u_20 in force, then expired). Counters, the
    estimates and a least-squares restart from the recovery's data afterwards are those of an
    estimator that had u_20."""
    stream = _realtime_stream(40, silent_from=21, validity=0.15)
    runs = {}
    for lost in ((), (20,)):
        runner, out = _provisional_runner('ekf', control_validity=0.15)
        _feed(runner, out, stream, report_delay=5, lost_controls=lost)
        runs[lost] = (runner, out)
    (runner, out), (reference, expected) = runs[(20,)], runs[()]
    assert runner.values()['provisional_corrected'] == 1 and out.again[0] == 21 * DT
    assert reference.values()['provisional_corrected'] == 0
    for key in ('controls_missing', 'controls_expired', 'measurements_used', 'provisional_steps', 'steps'):
        assert runner.values()[key] == reference.values()[key], key
    assert runner.values()['controls_expired'] == 16  # 22-37 (38 and 39 waited for their reports)
    final, wanted = _final(out.estimates), _final(expected.estimates)
    assert sorted(final) == sorted(wanted)
    for stamp in wanted:
        np.testing.assert_array_equal(final[stamp], wanted[stamp], err_msg=f'{stamp / NS} s')
    measurements = stream[0]
    for each in (runner, reference):  # a reset: the next step restarts from the recovery's data
        assert each.reset('test') == 'data'
        each.control(40 * DT, np.zeros(3))
        each.measurement(40 * DT, measurements[39 * DT] + 0.01)
    assert runner.values()['restarts_from.least_squares'] == 1
    np.testing.assert_array_equal(runner.estimator.x_hat, reference.estimator.x_hat)
