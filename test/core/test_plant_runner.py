"""The plant's stepping without ROS: start gate, lockstep pairing, resend, timeouts, realtime
ticks, pause, and the control in force (commands expire)."""

import numpy as np
import pytest

from snn_estimator import rendezvous_scenario
from snn_estimator.plant.truth import Plant
from snn_estimator.runners.plant_runner import STARTUP_STEPS, PlantRunner, PlantSettings, StartGate, control_in_force

DT = 100_000_000


class Clock:
    """A wall clock the test moves by hand."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def make_runner(**settings):
    scenario = rendezvous_scenario()
    plant = Plant(scenario.model, scenario.x0, np.zeros((6, 6)))
    sent, logs, finished = [], [], []
    wall = Clock()
    runner = PlantRunner(plant, PlantSettings(time_step=0.1, **settings),
                         publish=lambda stamp, resend: sent.append((stamp, resend, plant.x[0].copy())),
                         finished=lambda: finished.append(True),
                         log=lambda level, message: logs.append((level, message)), wall_clock=wall)
    return runner, sent, logs, wall, finished


def expected_after(controls, dt=0.1):
    """The truth after applying ``controls`` in turn, stepped by an independent Plant."""
    scenario = rendezvous_scenario()
    plant = Plant(scenario.model, scenario.x0, np.zeros((6, 6)))
    for u in controls:
        plant.step(u, dt)
    return plant.x[0]


def test_lockstep_sends_x0_then_steps_once_per_control_and_takes_early_ones_in_order():
    runner, sent, _, _, _ = make_runner(duration=0.5)
    runner.begin()
    assert [s[0] for s in sent] == [0]
    u = [np.array([1e-3 * k, 0.0, 0.0]) for k in range(5)]
    assert runner.control(2 * DT, u[2]) is None  # early: kept for its step
    assert runner.control(0, u[0]) is None
    assert [s[0] for s in sent] == [0, DT]
    runner.control(DT, u[1])  # steps 1 and then the early step 2 at once
    assert [s[0] for s in sent] == [0, DT, 2 * DT, 3 * DT]
    np.testing.assert_allclose(sent[-1][2], expected_after(u[:3]), rtol=0, atol=1e-12)
    assert runner.control(DT, u[1]) == ('stale', 'control stamped 0.100 s, plant at 0.300 s')
    assert runner.control(-DT, u[1])[0] == 'before_init'


def test_lockstep_resends_a_state_whose_control_is_late_and_times_out_after_the_start_up_steps():
    runner, sent, logs, wall, _ = make_runner(resend_period=0.25, control_timeout=1.0, control_validity=10.0)
    runner.begin()
    wall.now = 0.3
    runner.watchdog()
    assert sent[-1][:2] == (0, True) and runner.values()['truth_resent'] == 1
    for k in range(STARTUP_STEPS):
        runner.control(k * DT, np.array([2e-3, 0.0, 0.0]))
    wall.now = 10.0  # start-up over: no control for step 10 within control_timeout
    runner.watchdog()
    assert runner.values()['control_timeouts'] == 1 and runner.step == STARTUP_STEPS + 1
    # the control of step 9 is still in force (younger than control_validity): applied again
    np.testing.assert_allclose(runner.plant.x[0], expected_after([np.array([2e-3, 0, 0])] * 11), atol=1e-12)
    assert any('no control for t = 1.000 s' in m for _, m in logs)


def test_a_realtime_tick_applies_the_control_of_its_step_or_the_one_in_force_and_counts_it_late():
    runner, sent, _, _, _ = make_runner(mode='realtime', control_validity=10.0)
    runner.tick()
    assert sent == []  # not started
    runner.begin()
    runner.control(0, np.array([1e-3, 0, 0]))
    runner.tick()
    runner.tick()  # no control for step 1: the one of step 0 is in force
    runner.control(2 * DT, np.array([0, 1e-3, 0]))
    runner.tick()
    assert runner.values()['late_controls'] == 1
    np.testing.assert_allclose(
        runner.plant.x[0], expected_after([np.array([1e-3, 0, 0])] * 2 + [np.array([0, 1e-3, 0])]), atol=1e-12)


def test_a_paused_plant_holds_its_time_and_applies_the_control_that_came_on_resume():
    runner, sent, _, _, _ = make_runner()
    runner.begin()
    runner.set_paused(True)
    runner.control(0, np.zeros(3))
    runner.control(DT, np.zeros(3))
    assert len(sent) == 1
    runner.set_paused(False)
    assert [s[0] for s in sent] == [0, DT, 2 * DT]


def test_the_run_finishes_after_its_duration_and_steps_no_more():
    runner, sent, _, _, finished = make_runner(mode='realtime', duration=0.3)
    runner.begin()
    for _ in range(10):
        runner.tick()
    assert finished == [True] and runner.step == 3 and len(sent) == 4 and runner.values()['done']


def test_the_start_gate_waits_for_the_whole_loop_then_start_delay_and_says_what_is_missing():
    wall, logs = Clock(), []
    gate = StartGate(0.3, 5.0, lambda level, message: logs.append(message), wall)
    assert not gate.check(['a sensor'])
    wall.now = 6.0
    assert not gate.check(['a sensor']) and logs == ['waiting for a sensor before the first step']
    assert not gate.check([])  # complete now: start_delay to go
    wall.now = 6.2
    assert not gate.check([])
    wall.now = 6.31
    assert gate.check([])


def test_the_control_in_force_is_the_newest_one_until_it_expires_then_zero():
    controls = {0: np.ones(3), DT: 2 * np.ones(3), 9 * DT: 9 * np.ones(3)}
    u, stamp = control_in_force(controls, 3 * DT, 5 * DT, 3)
    assert stamp == DT and np.all(u == 2)  # the newest at or before t, not the future one
    u, stamp = control_in_force(controls, 6 * DT - 1, 5 * DT, 3)
    assert stamp == DT  # 0.5 s - 1 ns old: still in force
    u, stamp = control_in_force(controls, 6 * DT, 5 * DT, 3)
    assert stamp is None and np.all(u == 0)  # expired
    assert control_in_force({}, 0, 5 * DT, 3)[1] is None


@pytest.mark.parametrize('field, value, message', [
    ('mode', 'fast', 'mode'), ('control_validity', 0.0, 'control_validity'), ('time_step', 0.0, 'time_step')])
def test_bad_settings_are_refused_naming_the_field(field, value, message):
    values = {'time_step': 0.1, field: value}
    with pytest.raises(ValueError, match=message):
        PlantSettings(**values)


class Spy:
    """Records the control of every step an estimator takes (and passes it on); a step taken
    again (a provisional step corrected: the estimator restored) replaces its record, so
    ``controls[k]`` is the control step k finally used."""

    def __init__(self, estimator):
        self.controls = []
        step = estimator.step

        def recording(z, u, dt):
            del self.controls[estimator.steps:]
            self.controls.append(np.array(u, dtype=float))
            return step(z, u, dt)
        estimator.step = recording


@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
def test_a_dead_controllers_last_command_expires_to_zero_thrust_in_plant_and_estimator_alike(mode):
    """Controls for steps 0-14, then none (the controller died): both the plant and the
    estimator apply the control of 1.4 s until it is control_validity (0.5 s) old, then zero
    thrust; counted and logged once each."""
    from snn_estimator import make_estimator
    from snn_estimator.runners.filter_runner import FilterRunner, RunnerSettings
    runner, sent, logs, wall, _ = make_runner(mode=mode, control_timeout=0.2, control_validity=0.5)
    scenario = rendezvous_scenario()
    estimator = make_estimator('ekf', scenario.estimator, scenario.model)
    spy = Spy(estimator)
    filter_logs = []
    filter_runner = FilterRunner(estimator, RunnerSettings(time_step=0.1, control_validity=0.5), 1e-2 * np.eye(3),
                                 publish=lambda stamp: None, log=lambda level, m: filter_logs.append(m),
                                 wall_clock=wall)
    filter_runner.start('parameters')
    applied = []
    runner.begin()
    for k in range(25):
        u = np.array([2e-3, -1e-3, 0.0]) * (k + 1)
        filter_runner.measurement(k * DT, runner.plant.x[0, :3])
        if k < 15:
            runner.control(k * DT, u)
            filter_runner.control(k * DT, u)
        if mode == 'realtime':
            runner.tick()
        else:
            while runner.step == k:
                wall.now += 0.05
                runner.watchdog()
        applied.append(runner.plant.applied[0].copy())
    last = np.array([2e-3, -1e-3, 0.0]) * 15
    for k in range(15, 25):
        expected = last if k < 19 else np.zeros(3)
        np.testing.assert_array_equal(applied[k], expected, err_msg=f'plant, step {k}')
    assert runner.values()['expired_control_steps'] == 6
    assert sum('expired' in m for _, m in logs) == 1
    filter_runner.measurement(25 * DT, runner.plant.x[0, :3])
    filter_runner.measurement(26 * DT, runner.plant.x[0, :3])  # steps up to 24 without controls
    assert len(spy.controls) == 25
    for k in range(25):
        np.testing.assert_array_equal(spy.controls[k], applied[k], err_msg=f'estimator, step {k}')
    assert filter_runner.values()['controls_expired'] == 6
    assert sum('expired' in m for m in filter_logs) == 1


@pytest.mark.parametrize('provisional', [True, False])
def test_a_realtime_plant_reports_the_control_it_stepped_with_and_the_estimator_predicts_with_it(provisional):
    """A control that comes after the realtime plant's tick is not applied (the one in force
    is); the plant reports what it stepped with, and an estimator fed the reports predicts with
    exactly that, where the controller's late u_k alone would have made it predict with u_k.
    With provisional steps it first steps with u_k and takes the step again with the report."""
    from snn_estimator import make_estimator
    from snn_estimator.runners.filter_runner import FilterRunner, RunnerSettings
    scenario = rendezvous_scenario()
    plant = Plant(scenario.model, scenario.x0, np.zeros((6, 6)))
    reports = []
    runner = PlantRunner(plant, PlantSettings(time_step=0.1, mode='realtime', control_validity=10.0),
                         publish=lambda stamp, resend: None,
                         applied=lambda stamp, u: reports.append((stamp, np.array(u, dtype=float))))

    def controls(k):
        return np.array([1e-3, -2e-3, 5e-4]) * (k + 1)
    spies = {}
    for told in (True, False):
        estimator = make_estimator('ekf', scenario.estimator, scenario.model)
        spies[told] = Spy(estimator)
        filter_runner = FilterRunner(estimator, RunnerSettings(time_step=0.1, provisional_steps=provisional),
                                     1e-2 * np.eye(3), publish=lambda stamp: None)
        filter_runner.start('parameters')
        spies[told].runner = filter_runner
    runner.begin()
    late = {3, 4, 7}
    for k in range(10):
        for filter_runner in (spy.runner for spy in spies.values()):
            filter_runner.measurement(k * DT, plant.x[0, :3])
        if k not in late:
            runner.control(k * DT, controls(k))
        runner.tick()
        if k in late:  # after the tick: the plant stepped with the one in force
            runner.control(k * DT, controls(k))
        for told, spy in spies.items():
            spy.runner.control(k * DT, controls(k))
            if told:
                spy.runner.applied(*reports[-1])
    assert [stamp for stamp, _ in reports] == [k * DT for k in range(10)]
    for k in range(10):
        expected = controls(k - 1) if k in late else controls(k)  # the newest one there at the tick
        np.testing.assert_array_equal(reports[k][1], expected, err_msg=f'plant, step {k}')
    for spy in spies.values():
        spy.runner.measurement(10 * DT, plant.x[0, :3])
        spy.runner.measurement(11 * DT, plant.x[0, :3])
    told, untold = spies[True].controls, spies[False].controls
    assert len(told) == len(untold) == 10
    for k in range(10):
        np.testing.assert_array_equal(told[k], reports[k][1], err_msg=f'estimator told, step {k}')
        np.testing.assert_array_equal(untold[k], controls(k), err_msg=f'estimator untold, step {k}')
    assert any(not np.array_equal(reports[k][1], controls(k)) for k in late)
    corrected = spies[True].runner.values().get('provisional_corrected', 0)
    assert corrected == (sum(not np.array_equal(reports[k][1], controls(k)) for k in late) if provisional else 0)


@pytest.mark.parametrize('event_first', [True, False], ids=['end_before_the_control', 'end_after_the_control'])
def test_an_end_announced_at_a_stamp_ends_the_run_after_the_step_from_it_whichever_comes_first(event_first):
    """The guidance's abort at t_k (end_after) and the control of t_k come on two topics in either
    order: the run ends at t_k+1 both ways, the step from t_k taken with that control."""
    runner, sent, _, _, finished = make_runner(duration=10.0)
    runner.begin()
    runner.control(0, np.zeros(3))
    if event_first:
        runner.end_after(DT)
        assert not finished
    runner.control(DT, np.array([1e-3, 0.0, 0.0]))
    if not event_first:
        assert not finished
        runner.end_after(DT)
    assert finished == [True] and runner.ended_by == 'requested'
    assert [s[0] for s in sent] == [0, DT, 2 * DT]
    assert runner.control(2 * DT, np.zeros(3)) is None and len(sent) == 3  # no step after the end


def test_a_stop_condition_on_the_truth_ends_the_run_with_the_step_that_meets_it():
    scenario = rendezvous_scenario()
    plant = Plant(scenario.model, scenario.x0, np.zeros((6, 6)))
    sent, finished = [], []
    runner = PlantRunner(plant, PlantSettings(time_step=0.1, duration=100.0),
                         publish=lambda stamp, resend: sent.append(plant.x[0].copy()),
                         finished=lambda: finished.append(True), stop=lambda x: x[0] < 69.9)
    runner.begin()
    k = 0
    while not finished:
        runner.control(k * DT, np.zeros(3))
        k += 1
    assert runner.ended_by == 'stop' and sent[-1][0] < 69.9 <= sent[-2][0] and runner.step == len(sent) - 1
