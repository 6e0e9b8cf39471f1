"""The parts of the FilterRunner, each alone (no runner, no ROS): the measurement queue's gate,
the control book's rule for the control of a step, the start-up strategy, the provisional-step
log, the restart trigger and the report."""

from collections import Counter

import numpy as np
import pytest
from test_runner import Clock

from snn_estimator import make_estimator, rendezvous_scenario
from snn_estimator.runners.control_book import ControlBook
from snn_estimator.runners.filter_runner import RunnerSettings
from snn_estimator.runners.measurement_queue import MeasurementQueue
from snn_estimator.runners.provisional import PROVISIONAL_LIMIT, HeldStep, ProvisionalLog
from snn_estimator.runners.recovery import Recovery, RestartTrigger
from snn_estimator.runners.reporting import RunnerReport
from snn_estimator.runners.start_up import StartUp

DT = 100_000_000
Z = np.array([70.0, 30.0, -5.0])
U = np.array([1e-3, -2e-3, 5e-4])
SETTINGS = RunnerSettings(time_step=0.1, max_input_age=0.25)


class Logs:
    """A log callback that keeps (level, message)."""

    def __init__(self):
        self.lines = []

    def __call__(self, level, message):
        self.lines.append((level, message))


# ------------------------------------------------------------------ the measurement queue
def test_the_gate_names_each_reason_counts_it_and_queues_the_rest():
    logs = Logs()
    queue = MeasurementQueue(0.1, logs)
    estimate = 4 * DT  # the runner's estimate time; the newest measurement is z_4
    assert queue.offer(4 * DT, Z, 0, estimate, SETTINGS) is None
    reasons = {stamp: queue.offer(stamp, Z, now, estimate, SETTINGS) for stamp, now in [
        (4 * DT, 0), (DT, 0), (3 * DT, 0), (5 * DT + DT // 2, 0), (100 * DT, 5 * DT), (6 * DT, 5 * DT)]}
    assert reasons == {4 * DT: 'duplicate', DT: 'too_old', 3 * DT: 'stale', 5 * DT + DT // 2: 'misaligned',
                       100 * DT: 'future', 6 * DT: None}
    assert queue.rejected == {'duplicate': 1, 'too_old': 1, 'stale': 1, 'misaligned': 1, 'future': 1}
    assert queue.received == 7 and queue.pending_count == 2 and queue.first_stamp() == 4 * DT
    assert [level for level, _ in logs.lines] == ['warning'] * 5
    assert all(message.startswith('rejected') for _, message in logs.lines)
    assert 'measurement_timing: any' in logs.lines[3][1]  # a stamp off the grid names the setting that allows it


def test_before_the_start_and_off_the_grid_only_duplicates_and_the_future_are_refused():
    queue = MeasurementQueue(0.1)
    any_timing = RunnerSettings(time_step=0.1, max_input_age=0.25, measurement_timing='any')
    assert queue.offer(40 * DT, Z, 0, None, SETTINGS) is None
    assert queue.offer(DT + 7, Z, 0, None, SETTINGS) is None  # no estimate time: nothing is stale
    assert queue.offer(40 * DT, Z, 0, None, SETTINGS) == 'duplicate'
    assert queue.offer(60 * DT + 7, Z, 0, 40 * DT, any_timing) is None  # off the grid, fine with 'any'
    assert queue.offer(90 * DT, Z, 60 * DT, None, SETTINGS) == 'future'


def test_a_stamp_far_back_without_a_clock_is_a_restarted_time_base():
    queue = MeasurementQueue(0.1)
    assert queue.time_base_restarted(0, 0, 40 * DT, threshold=1.0)
    assert not queue.time_base_restarted(35 * DT, 0, 40 * DT, threshold=1.0)  # within the threshold
    assert not queue.time_base_restarted(0, 41 * DT, 40 * DT, threshold=1.0)  # a clock: only a late input
    assert not queue.time_base_restarted(0, 0, None, threshold=1.0)  # not started


def test_history_measurements_the_start_did_not_need_are_dropped_uncounted():
    logs = Logs()
    queue = MeasurementQueue(0.1, logs)
    queue.add_history({0: Z, DT: Z, 2 * DT: Z})
    assert queue.offer(3 * DT, Z, 0, None, SETTINGS) is None
    queue.drop_before(4 * DT, 'test')
    assert queue.dropped == 1 and queue.pending_count == 0  # only z_3 came as a measurement
    assert queue.events['history_measurements'] == 3 and len(logs.lines) == 1 and '0.300 s' in logs.lines[0][1]


def test_a_resend_is_a_stamp_queued_or_used_since_the_start():
    queue = MeasurementQueue(0.1)
    queue.offer(2 * DT, Z, 0, None, SETTINGS)
    assert queue.has(2 * DT, start_ns=None) and not queue.has(DT, start_ns=0)
    queue.stepped(2 * DT, queue.pop(2 * DT))
    queue.put_unmeasured(3 * DT)
    assert queue.has(2 * DT, 0) and queue.has(3 * DT, 0) and not queue.has(4 * DT, 0) and not queue.has(2 * DT, None)
    assert queue.used == 1
    queue.restart()
    assert not queue.has(2 * DT, 0) and queue.dropped == 1  # the unmeasured step was still queued


def test_stamps_off_the_clock_are_noted_once_with_their_likely_cause_and_the_wall_clock_says_quiet():
    logs, wall = Logs(), Clock()
    queue = MeasurementQueue(0.1, logs, wall)
    queue.offer(0, Z, 0, None, SETTINGS)
    assert queue.clock_agrees is None  # no clock yet
    queue.offer(DT, Z, 1_700_000_000 * 10 * DT, None, SETTINGS)
    queue.offer(2 * DT, Z, 1_700_000_000 * 10 * DT, None, SETTINGS)
    assert queue.clock_agrees is False and queue.events['stamps_off_the_clock'] == 1
    assert len(logs.lines) == 1 and 'use_sim_time' in logs.lines[0][1]
    queue.offer(3 * DT, Z, 3 * DT, None, SETTINGS)
    assert queue.clock_agrees is True
    assert not queue.quiet_for(0.25)
    wall.now = 0.3
    assert queue.quiet_for(0.25)


def test_the_step_counts_restore_to_a_checkpoint():
    queue = MeasurementQueue(0.1)
    queue.offer(0, Z, 0, None, SETTINGS)
    before = queue.step_state()
    queue.stepped(0, queue.pop(0))
    queue.stepped(DT, None)
    assert (queue.used, queue.dropout_steps) == (1, 1)
    queue.restore_step_state(before)
    assert (queue.used, queue.dropout_steps) == (0, 0) and queue.received == 1
    assert queue.offer(0, Z, 0, None, SETTINGS) is None  # z_0 no longer counts as used


# ------------------------------------------------------------------ the control book
VALIDITY = 250_000_000  # 0.25 s


def test_a_missing_control_is_the_last_one_used_until_control_validity_then_zero_thrust():
    """The plant's rule (plant_runner.control_in_force): u_0 in force for 0.1 and 0.2 s, zero thrust
    from 0.3 s (0.25 s old); each step without its control counted missing, each expired one
    counted, the expiry logged once."""
    logs = Logs()
    book = ControlBook(0.1, 3, logs)
    assert book.offer(0, U, start_ns=0) is None
    used = [book.step_control(k * DT, provisional=False, validity_ns=VALIDITY) for k in range(5)]
    for k, (u, final) in enumerate(used):
        np.testing.assert_array_equal(u, U if k < 3 else np.zeros(3), err_msg=f'step {k}')
        assert final
    assert book.missing == 4 and book.events == {'controls_expired': 2}
    assert sum('expired' in message for _, message in logs.lines) == 1
    book.offer(5 * DT, 2 * U, start_ns=0)
    np.testing.assert_array_equal(book.step_control(5 * DT, False, VALIDITY)[0], 2 * U)
    np.testing.assert_array_equal(book.step_control(6 * DT, False, VALIDITY)[0], 2 * U)  # in force again
    assert book.events == {'controls_expired': 2}


def test_once_a_plant_reports_its_report_settles_a_step_and_without_one_the_command_is_provisional():
    book = ControlBook(0.1, 3)
    book.offer(0, U, start_ns=0)
    book.offer(DT, U, start_ns=0)
    assert book.step_control(0, provisional=True, validity_ns=VALIDITY)[1]  # no plant reports yet: final
    assert book.offer_applied(0, 3 * U, start_ns=0) is None and book.plant_reports
    np.testing.assert_array_equal(book.final(0), 3 * U)  # the report, not the command
    assert book.final(DT) is None and book.before_report(DT, provisional=True)
    assert book.can_step(DT, provisional=True) and not book.can_step(DT, provisional=False)
    u, final = book.step_control(DT, provisional=True, validity_ns=VALIDITY)
    np.testing.assert_array_equal(u, U)
    assert not final and 'applied_missing' not in book.events
    u, final = book.step_control(DT, provisional=False, validity_ns=VALIDITY)  # waited, report lost
    assert final and book.events['applied_missing'] == 1 and book.applied_received == 1


def test_a_control_pairs_with_the_step_within_half_a_step_and_one_before_the_start_is_refused():
    logs = Logs()
    book = ControlBook(0.1, 3, logs)
    book.offer(DT + 4 * DT // 10, U, start_ns=None)
    assert book.commanded(DT) is not None and book.commanded(2 * DT) is None
    book.offer(3 * DT + 6 * DT // 10, U, start_ns=None)
    assert book.commanded(3 * DT) is None and book.commanded(4 * DT) is not None
    assert book.offer(-DT, U, start_ns=0) == 'before_init' and 'predates the start' in logs.lines[-1][1]
    assert book.offer_applied(-DT, U, start_ns=0) == 'applied_before_init'
    book.unreadable('malformed')
    assert book.rejected == {'before_init': 1, 'applied_before_init': 1, 'malformed': 1}
    assert book.applied_received == 0 and not book.plant_reports


def test_used_controls_are_forgotten_but_those_of_held_steps_and_the_fit_takes_the_one_in_force():
    book = ControlBook(0.1, 3)
    for k in range(6):
        book.offer(k * DT, (k + 1) * U, start_ns=0)
    book.forget_used(4 * DT, held_from=2 * DT)
    assert book.commanded(DT) is None and book.commanded(2 * DT) is not None and book.commanded(5 * DT) is not None
    book.forget_used(4 * DT)
    assert book.commanded(4 * DT) is None and book.commanded(5 * DT) is not None
    fitted = book.controls_over([5 * DT, 6 * DT, 9 * DT], validity_ns=VALIDITY)
    np.testing.assert_array_equal(np.array(fitted), [6 * U, 6 * U, np.zeros(3)])
    assert book.missing == 0 and not book.events  # a fit counts nothing


def test_the_step_state_of_the_book_restores_the_control_in_force_and_its_counts():
    book = ControlBook(0.1, 3)
    book.offer(0, U, start_ns=0)
    book.step_control(0, False, VALIDITY)
    before = book.step_state()
    for k in range(1, 5):
        book.step_control(k * DT, False, VALIDITY)
    assert book.missing == 4 and book.events['controls_expired'] == 2
    book.restore_step_state(before)
    assert book.missing == 0 and not book.events
    np.testing.assert_array_equal(book.step_control(DT, False, VALIDITY)[0], U)  # u_0 in force again


# ------------------------------------------------------------------ the start-up strategy
def _ekf():
    scenario = rendezvous_scenario()
    return make_estimator('ekf', scenario.estimator, scenario.model)


def test_a_received_covariance_is_used_only_if_it_is_one():
    estimator = _ekf()
    start_up = StartUp(estimator, 1e-2 * np.eye(3))
    p0 = estimator.settings.initial_covariance
    good = np.diag([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    np.testing.assert_array_equal(start_up.usable_covariance(good), good)
    asymmetric = good.copy()
    asymmetric[0, 1] = 0.5
    for bad in (None, np.full((6, 6), np.nan), asymmetric, -good):
        np.testing.assert_array_equal(start_up.usable_covariance(bad), p0)


def test_a_warm_start_sets_the_estimate_or_says_why_not():
    estimator, logs = _ekf(), Logs()
    start_up = StartUp(estimator, 1e-2 * np.eye(3), logs)
    x = np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    assert start_up.from_estimate(x, None)
    np.testing.assert_array_equal(estimator.x_hat, x)
    np.testing.assert_array_equal(estimator.P, estimator.settings.initial_covariance)
    assert not start_up.from_estimate(np.full(6, np.nan), None) and 'cannot warm start' in logs.lines[-1][1]


def test_a_fit_needs_a_full_window_and_starts_at_its_newest_stamp():
    """Measurements of a state moving freely: the fit over 1 s recovers the state at the newest
    stamp (the last measurement is left for the filter's next step)."""
    estimator = _ekf()
    model = estimator.model
    start_up = StartUp(estimator, 1e-6 * np.eye(3))
    assert start_up.fit_window([k * DT for k in range(5)], window_ns=10 * DT, dt_ns=DT) is None
    stamps = start_up.fit_window([k * DT for k in range(20)], window_ns=10 * DT, dt_ns=DT)
    assert stamps == [k * DT for k in range(9, 20)]
    x, truth = np.array([70.0, 30.0, -5.0, -0.2, 0.1, 0.05]), {}
    for k in range(9, 20):
        truth[k * DT] = x
        x = model.transition(x, np.zeros(3), 0.1)
    zs = [model.measurement_matrix @ truth[t] for t in stamps]
    assert start_up.from_fit(stamps, zs, [np.zeros(3)] * len(stamps))
    np.testing.assert_allclose(estimator.x_hat, truth[19 * DT], atol=1e-6)


def test_the_start_waits_for_the_first_measurement_until_it_begins():
    start_up = StartUp(_ekf(), 1e-2 * np.eye(3))
    assert not start_up.waiting
    start_up.wait_for_first_measurement()
    assert start_up.waiting
    start_up.begun()
    assert not start_up.waiting


# ------------------------------------------------------------------ the provisional-step log
def _held(k, final=False, u=U):
    return HeldStep(k * DT, Z, f'checkpoint {k}', u, final, Counter())


def test_a_confirming_report_releases_the_step_and_a_differing_one_hands_back_it_and_the_later_ones():
    log = ProvisionalLog(0.1)
    for k in range(3):
        log.hold(_held(k))
    assert log.held_count == 3 and log.oldest_stamp == 0 and log.events['provisional_steps'] == 3
    assert log.report(DT, U) == [] and log.held_count == 3  # step 1 final, behind step 0 that is not
    assert log.report(0, U) == [] and log.held_count == 1 and log.oldest_stamp == 2 * DT
    redo = log.report(2 * DT + DT // 3, 2 * U)  # pairs within half a step
    assert [step.checkpoint for step in redo] == ['checkpoint 2'] and log.held_count == 0
    assert log.events['provisional_corrected'] == 1
    assert log.report(2 * DT, 2 * U) == []  # nothing held any more


def test_at_most_the_limit_is_held_and_settling_accepts_every_held_step():
    logs = Logs()
    log = ProvisionalLog(0.1, logs)
    for k in range(PROVISIONAL_LIMIT + 2):
        log.hold(_held(k))
    assert log.held_count == PROVISIONAL_LIMIT and log.events['provisional_unconfirmed'] == 2
    log.hold(_held(PROVISIONAL_LIMIT + 2, final=True))  # held (earlier ones are not final): one more out
    assert log.held_count == PROVISIONAL_LIMIT and log.events['provisional_unconfirmed'] == 3
    log.settle('test')  # the final one is not counted
    assert log.held_count == 0 and log.events['provisional_unconfirmed'] == 3 + PROVISIONAL_LIMIT - 1
    assert sum('taken as applied' in message for _, message in logs.lines) == 3 + PROVISIONAL_LIMIT - 1
    log.hold(_held(20))
    log.forget()
    assert log.held_count == 0 and log.events['provisional_unconfirmed'] == 3 + PROVISIONAL_LIMIT - 1


def test_a_step_taken_again_is_not_counted_as_a_new_provisional_step():
    log = ProvisionalLog(0.1)
    with log.replay():
        assert log.replaying
        log.hold(_held(0))
    assert not log.replaying and log.held_count == 1 and 'provisional_steps' not in log.events


# ------------------------------------------------------------------ the restart trigger
def test_the_trigger_fires_after_the_window_of_inconsistent_steps_in_a_row_and_on_request():
    trigger = RestartTrigger()
    assert [trigger.check(nis, 25.0, 3) for nis in (30.0, 30.0, 1.0, 30.0, 30.0)] == [None] * 5
    assert not trigger.consistent
    why, reason = trigger.check(40.0, 25.0, 3)
    assert reason == 'inconsistent_innovation' and '40.0 > 25.0 for 3 steps' in why
    assert all(trigger.check(1e9, 25.0, 0) is None for _ in range(5))  # window 0: never
    trigger.clear()
    assert trigger.consistent and trigger.requested is None
    trigger.request('asked')
    before = trigger.snapshot()
    trigger.clear()
    trigger.restore(before)
    assert trigger.requested == ('asked', 'reset')


# ------------------------------------------------------------------ the report
def test_the_report_reads_every_parts_counters_and_merges_their_events():
    estimator = _ekf()
    queue, book, log = MeasurementQueue(0.1), ControlBook(0.1, 3), ProvisionalLog(0.1)
    recovery = Recovery(estimator, 1e-2 * np.eye(3), 10.0, 0.1)
    events = Counter({'reinitialisations.reset': 2, 'cold_starts': 1})
    report = RunnerReport(estimator, queue, book, log, recovery, events)
    queue.offer(0, Z, 0, None, SETTINGS)
    queue.offer(0, Z, 0, None, SETTINGS)
    queue.unreadable('malformed')
    book.offer(-DT, U, start_ns=0)
    book.step_control(0, False, VALIDITY)
    log.hold(_held(0))
    report.step_took(2e-6)
    values = report.values()
    assert values['measurements_received'] == 3 and values['measurements_pending'] == 1
    assert values['measurements_rejected'] == 2 and values['measurements_rejected.duplicate'] == 1
    assert values['controls_rejected.before_init'] == 1 and values['controls_missing'] == 1
    assert values['provisional_held'] == 1 and values['provisional_steps'] == 1
    assert values['reinitialisations'] == 2 and values['cold_starts'] == 1 and values['step_time_us_last'] == 2.0
    assert report.problems() == ['3 inputs rejected', '1 controls missing', '2 re-initialisations']


def test_the_step_times_reported_are_the_newest_thousand():
    estimator = _ekf()
    report = RunnerReport(estimator, MeasurementQueue(0.1), ControlBook(0.1, 3), ProvisionalLog(0.1),
                          Recovery(estimator, 1e-2 * np.eye(3), 10.0, 0.1), Counter())
    for k in range(2500):
        report.step_took(k * 1e-6)
    values = report.values()
    assert values['step_time_us_last'] == pytest.approx(2499.0)
    assert values['step_time_us_median'] == pytest.approx(1999.5)
