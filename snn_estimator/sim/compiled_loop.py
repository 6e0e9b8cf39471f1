"""The closed loop of :func:`simulate` stepped in compiled code (numba), batched over runs.

:func:`simulate`'s Python loop calls numpy for the LQR, the sensor, the NIS, the plant, the NEES
and the bookkeeping of every step, and around a batched filter step of ~1-5 us per run that
costs more than the filter (issue 25: 4.8x the EKF's own step). Here one compiled call steps a
chunk of up to :data:`CHUNK` steps of every run: the LQR ``u = -K (x_hat - setpoint)`` (Eq. 42),
the position sensor ``z = C x + v``, the NIS of z against the prior estimate, the filter's own
step kernel (the same compiled :func:`snn_estimator.filters.kernels.step_kernel`, on the same
packed arrays as :meth:`Estimator.step`), the CW truth ``x = Phi x + Gamma u + L w`` and the
samples (truth, estimate, covariance diagonal, NEES, spikes). The noise comes from the same
generators in the same order (:class:`GaussianStream` rows, the membrane noise), drawn a chunk at
a time, so the numbers are those of the Python loop, which stays the reference
(``simulate(..., engine='reference')``); a test holds them equal to 1e-9 for every filter kind.

What it covers: a linear measurement (the position sensor of Table 6); the filters' model CW or
the nonlinear relative motion (its A(x_hat), zero-order hold and drift recomputed in the loop
before each step by snn_estimator.filters.model_kernels, as Estimator.step does); the CW or the
nonlinear relative-motion truth inside the compiled loop (the latter by its RK4 substeps, as
blocks.Plant), or the Basilisk truth stepped by Basilisk between two compiled calls; the LQR, a
known open-loop schedule or no control; the float64 network (any spike rule, coding, gain
schedule, membrane noise); ``events`` (the loop returns to Python before an event's step). A
measurement model, the chip network, the spiking LQR or a nonlinear model without a compiled twin
(Van der Pol) run the reference loop (:func:`unsupported` says why).

The packed arguments of :func:`_loop_template` (tuples, as the step kernel's):
``step_args`` the step kernel's ten arguments (its z, u and noise are written here each step);
``truth`` (inside, Phi, Gamma, L_Q, noise rows (runs, count, n), x, applied u); ``sensing``
(the sensor's C, L_R, noise rows (runs, count, m), the filter's C, R_hat), each C as its nonzero
entries (:func:`sparse`); ``control`` (mode, K, setpoint, schedule); ``outputs`` (truth, estimate,
diag P, NEES, NIS, control, spikes per step, raster); ``where`` (first step, count, index of the
first sample, index of the first step, first sample with NEES and NIS); ``models`` (the filter's
``StepDynamics.loop_model()``, and the truth's (nonlinear, model_kernels params, RK4 substeps)).
"""

from __future__ import annotations

import hashlib
import types
from pathlib import Path

import numba
import numpy as np

from snn_estimator import gains
from snn_estimator.filters import kernels, model_kernels
from snn_estimator.filters.program import StepProgram

#: Steps per compiled call (and noise rows drawn at a time): the blocks of GaussianStream.
CHUNK = 512

_FAST = {'reassoc', 'contract', 'nsz', 'arcp'}
_jit = numba.njit(fastmath=_FAST)

CONTROL_NONE, CONTROL_LQR, CONTROL_SCHEDULE = 0, 1, 2
#: The loop's own statuses beside the step kernel's (kernels.STATUS_*): a running run's control
#: is not finite (returned before step k: nothing of it was done), or a run diverged in step k
#: (its estimate, covariance or truth is not finite, its P not positive definite, or its spikes
#: reached max_spikes_per_step; returned after step k, samples written). simulate's _Divergence
#: then marks and restarts it.
STATUS_CONTROL_DIVERGED, STATUS_RUN_DIVERGED = 5, 6
#: The filter's step kernel, given to the loop template as a global by :func:`loop_kernel`.
_step = None


def unsupported(scenario, estimator, controller: str) -> str | None:
    """Why the compiled loop cannot run this set-up (None: it can)."""
    if scenario.sensor is not None:
        return 'a measurement model (the filter re-linearises in Python)'
    truth = scenario.truth_model or scenario.model
    if not (scenario.model.is_linear or estimator.program.dynamics.compiled):
        return 'a nonlinear model without a compiled twin (snn_estimator.filters.model_kernels)'
    if scenario.basilisk is None and not (truth.is_linear or model_kernels.compiled_params(truth) is not None):
        return 'a nonlinear truth model without a compiled twin (snn_estimator.filters.model_kernels)'
    if estimator.chip is not None:
        return 'the chip network'
    if controller != 'lqr':
        return f'controller {controller}'
    return None


# ---------------------------------------------------------------- quadratic forms (NEES, NIS)
@_jit
def _quadratic_lu(matrix, vector, lu, work):
    """vector^T matrix^-1 vector by LU with partial pivoting (LAPACK's getrf/getrs order); inf
    when ``matrix`` is singular or not finite (an overconfident filter, not a crash)."""
    d = vector.shape[0]
    for i in range(d):
        work[i] = vector[i]
        for j in range(d):
            lu[i, j] = matrix[i, j]
    for col in range(d):
        pivot, largest = col, abs(lu[col, col])
        for row in range(col + 1, d):
            if abs(lu[row, col]) > largest:
                pivot, largest = row, abs(lu[row, col])
        if not largest > 0.0 or not np.isfinite(largest):
            return np.inf
        if pivot != col:
            for j in range(d):
                lu[col, j], lu[pivot, j] = lu[pivot, j], lu[col, j]
            work[col], work[pivot] = work[pivot], work[col]
        for row in range(col + 1, d):
            factor = lu[row, col] / lu[col, col]
            for j in range(col + 1, d):
                lu[row, j] -= factor * lu[col, j]
            work[row] -= factor * work[col]
    for i in range(d - 1, -1, -1):  # back substitution: work = U^-1 L^-1 P vector
        acc = work[i]
        for j in range(i + 1, d):
            acc -= lu[i, j] * work[j]
        work[i] = acc / lu[i, i]
    total = 0.0
    for i in range(d):
        total += vector[i] * work[i]
    return total


@_jit
def _quadratic(matrix, vector, factor, work):
    """vector^T matrix^-1 vector (NEES, NIS): by Cholesky, matrix = L L^T and the sum of squares
    of L^-1 vector, half the work of LU; a matrix that is not positive definite (a P that is no
    covariance any more) goes to :func:`_quadratic_lu`, as numpy's solve would."""
    d = vector.shape[0]
    total = 0.0
    for i in range(d):
        acc = matrix[i, i]
        for k in range(i):
            acc -= factor[i, k] * factor[i, k]
        if not acc > 0.0 or not np.isfinite(acc):
            return _quadratic_lu(matrix, vector, factor, work)
        root = np.sqrt(acc)
        factor[i, i] = root
        for j in range(i + 1, d):
            acc = matrix[j, i]
            for k in range(i):
                acc -= factor[j, k] * factor[i, k]
            factor[j, i] = acc / root
        acc = vector[i]
        for k in range(i):
            acc -= factor[i, k] * work[k]
        work[i] = acc / root
        total += work[i] * work[i]
    return total


# ---------------------------------------------------------------- the pieces of one step
@_jit
def _control(b, k, x_hat, u, control, running):
    """u_k of run b: -K (x_hat - setpoint) (Eq. 42), the schedule's, or none; zero for a run
    that diverged (not ``running``)."""
    mode, lqr, setpoint, schedule = control
    for i in range(u.shape[1]):
        acc = 0.0
        if not running[b]:
            pass
        elif mode == CONTROL_LQR:
            for q in range(x_hat.shape[1]):
                acc -= lqr[i, q] * (x_hat[b, q] - setpoint[q])
        elif mode == CONTROL_SCHEDULE:
            acc = schedule[k, i]
        u[b, i] = acc


@_jit
def _measure(b, j, x, z, sensing):
    """z_k = C x_k + L_R w of run b (blocks.PositionSensor), w the chunk's row j."""
    (rows, cols, values), root, noise = sensing[0], sensing[1], sensing[2]
    for i in range(z.shape[1]):
        acc = 0.0
        for q in range(z.shape[1]):
            acc += root[i, q] * noise[b, j, q]
        z[b, i] = acc
    for e in range(rows.shape[0]):
        z[b, rows[e]] += values[e] * x[b, cols[e]]


@_jit
def _nis(b, z, x_hat, p, sensing, nu, s_matrix, factor, work):
    """nu^T (C P C^T + R_hat)^-1 nu, nu = z - C x_hat: the prior's (simulate's NIS)."""
    (rows, cols, values), r_hat = sensing[3], sensing[4]
    m = nu.shape[0]
    for i in range(m):
        nu[i] = z[b, i]
        for q in range(m):
            s_matrix[i, q] = r_hat[i, q]
    for e in range(rows.shape[0]):
        nu[rows[e]] -= values[e] * x_hat[b, cols[e]]
        for f in range(rows.shape[0]):
            s_matrix[rows[e], rows[f]] += values[e] * values[f] * p[b, cols[e], cols[f]]
    return _quadratic(s_matrix, nu, factor, work)


@_jit
def _propagate(b, j, truth, u, scratch):
    """x_{k+1} = Phi x_k + Gamma u_k + L_Q w of run b (blocks.Plant, exact ZOH), w row j."""
    _, phi, gamma, root, noise, x, applied = truth
    n = x.shape[1]
    for i in range(n):
        acc = 0.0
        for q in range(n):
            acc += phi[i, q] * x[b, q] + root[i, q] * noise[b, j, q]
        for q in range(u.shape[1]):
            acc += gamma[i, q] * u[b, q]
        scratch[i] = acc
    for i in range(n):
        x[b, i] = scratch[i]
    for i in range(u.shape[1]):
        applied[b, i] = u[b, i]


@_jit
def _propagate_nonlinear(b, j, dt, truth, truth_model, u, stages, trial):
    """x_{k+1} = the model's RK4 substeps from x_k with u_k held + L_Q w of run b (blocks.Plant
    on a nonlinear model: model_kernels.transition), w row j."""
    _, _, _, root, noise, x, applied = truth
    _, params, substeps = truth_model
    model_kernels.transition(params, x[b], u[b], dt, substeps, stages, trial)
    n = x.shape[1]
    for i in range(n):
        acc = 0.0
        for q in range(n):
            acc += root[i, q] * noise[b, j, q]
        x[b, i] += acc
    for i in range(u.shape[1]):
        applied[b, i] = u[b, i]


@_jit
def _record(sample, step, with_metrics, x, applied, state, network, outputs, factor, work, error):
    """The samples after a step: truth, estimate, diag P and (``with_metrics``) NEES e^T P^-1 e,
    e = x - x_hat, at index ``sample``; the control applied over the step, spikes per run and run
    0's raster at index ``step``. An empty array (a filter without P or spikes) is skipped."""
    truth_out, estimate_out, cov_out, nees_out, _, control_out, spikes_out, raster_out = outputs
    x_hat, p, spikes = state[0], state[1], network[6]
    n = x_hat.shape[1]
    for b in range(x_hat.shape[0]):
        for i in range(n):
            truth_out[b, sample, i] = x[b, i]
            estimate_out[b, sample, i] = x_hat[b, i]
            error[i] = x[b, i] - x_hat[b, i]
        for i in range(applied.shape[1]):
            control_out[b, step, i] = applied[b, i]
        if cov_out.shape[2] > 0:
            for i in range(n):
                cov_out[b, sample, i] = p[b, i, i]
            nees_out[b, sample] = _quadratic(p[b], error, factor, work) if with_metrics else np.nan
        if spikes_out.shape[1] > 0:
            total = 0
            for i in range(spikes.shape[1]):
                total += spikes[b, i]
            spikes_out[b, step] = total
            if b == 0 and raster_out.shape[0] > 0:
                for i in range(spikes.shape[1]):
                    raster_out[step, i] = spikes[0, i]


@numba.njit(cache=True)
def _controls_finite(u, running):
    """Every running run's control finite (compiled without fast-math, as kernels._row_finite)."""
    for b in range(u.shape[0]):
        if running[b]:
            for i in range(u.shape[1]):
                if not np.isfinite(u[b, i]):
                    return False
    return True


@numba.njit(cache=True)
def _any_diverged(state, network, x, max_spikes, covariance, spiking):
    """Whether a run's estimate, covariance (``covariance``) or truth is not finite, its step
    tripped the covariance guard (``fault``) or its spikes this step reached ``max_spikes``
    (simulate's _Divergence.check; no fast-math)."""
    x_hat, p, fault, spikes = state[0], state[1], state[3], network[6]
    for b in range(x_hat.shape[0]):
        if fault[b]:
            return True
        for i in range(x_hat.shape[1]):
            if not (np.isfinite(x_hat[b, i]) and np.isfinite(x[b, i])):
                return True
            if covariance:
                for j in range(x_hat.shape[1]):
                    if not np.isfinite(p[b, i, j]):
                        return True
        if spiking:
            total = 0
            for i in range(spikes.shape[1]):
                total += spikes[b, i]
            if total >= max_spikes:
                return True
    return False


def _loop_template(step_args, membrane, truth, sensing, control, outputs, where, models):
    """Steps ``first .. first + count - 1`` (``where``) of the loop for every run; per step k,
    simulate's order: u_k from x_hat_k (zero for a diverged run: ``step_args``' measured, the
    runs still running); z_k = C x_k + L_R w; the NIS of z_k against x_hat_k and P_k; the filter's
    step (with membrane[j] as its noise when given); then, with the truth inside, x_{k+1} and
    the samples of k + 1. Returns (status, steps done, runs capped), stopping early at a step
    whose status is not OK: bad input (nothing done), a running run's control not finite (before
    the step, nothing done), a run diverged (after the step), or the state non-finite without a
    run to blame (after the step): where simulate's Python loop raises or marks the run.
    ``models``: (the filter's StepDynamics.loop_model(), (truth nonlinear, its params, RK4
    substeps)): a nonlinear filter model's dynamics are recomputed at x_hat_k, u_k before each
    step (as Estimator.step does), a nonlinear truth stepped by model_kernels.transition."""
    consts, state, network, running, dt, dynamics, drift, z, u, noise = step_args
    filter_model, truth_model = models
    first, count, sample_at, step_at, metrics_from = where
    x_hat, p, x = state[0], state[1], truth[5]
    runs, n = x_hat.shape
    m = z.shape[1]
    nu, s_matrix, factor_m, work_m = np.empty(m), np.empty((m, m)), np.empty((m, m)), np.empty(m)
    factor_n, work_n, error = np.empty((n, n)), np.empty(n), np.empty(n)
    stages = np.empty((4, n))
    with_covariance, spiking = outputs[2].shape[2] > 0, network[0].shape[2] > 0
    capped_total = 0
    for j in range(count):
        k = first + j
        with_metrics = k + 1 >= metrics_from
        for b in range(runs):
            _control(b, k, x_hat, u, control, running)
        if not _controls_finite(u, running):
            return STATUS_CONTROL_DIVERGED, j, capped_total
        for b in range(runs):
            _measure(b, j, x, z, sensing)
            if with_covariance:
                outputs[4][b, step_at + j] = (_nis(b, z, x_hat, p, sensing, nu, s_matrix, factor_m, work_m)
                                              if with_metrics else np.nan)
        step_noise = membrane[j] if membrane.shape[0] > 0 else noise
        if filter_model[0]:  # [A_d | B_d] (and the drift) written into dynamics (and drift)
            model_kernels.step_dynamics(filter_model[1], filter_model[2], x_hat, u, dt, filter_model[3],
                                        filter_model[4], filter_model[5], filter_model[6])
        status, capped = _step(consts, state, network, running, dt, dynamics, drift, z, u, step_noise)
        capped_total += capped
        if status == kernels.STATUS_BAD_INPUT or not truth[0]:  # Basilisk: Python steps the truth
            return status, j + (status != kernels.STATUS_BAD_INPUT), capped_total
        for b in range(runs):
            if truth_model[0]:
                _propagate_nonlinear(b, j, dt, truth, truth_model, u, stages, work_n)
            else:
                _propagate(b, j, truth, u, work_n)
        _record(sample_at + j, step_at + j, with_metrics, x, truth[6], state, network, outputs, factor_n,
                work_n, error)
        if _any_diverged(state, network, x, consts[gains.MAX_SPIKES], with_covariance, spiking):
            return STATUS_RUN_DIVERGED, j + 1, capped_total
        if status != kernels.STATUS_OK:
            return status, j + 1, capped_total
    return kernels.STATUS_OK, count, capped_total


@numba.njit(cache=True)
def record_sample(sample, step, with_metrics, x, applied, state, network, outputs):
    """:func:`_record` for a truth stepped outside the compiled loop (Basilisk)."""
    n = x.shape[1]
    _record(sample, step, with_metrics, x, applied, state, network, outputs, np.empty((n, n)), np.empty(n),
            np.empty(n))


_DIGEST = hashlib.sha256(Path(__file__).read_bytes() + Path(model_kernels.__file__).read_bytes()
                         + StepProgram.DIGEST.encode()).hexdigest()[:12]
_LOOPS: dict = {}


def loop_kernel(step):
    """The compiled loop around the filter's step kernel ``step`` (numba caches it on disk under
    a name that carries a hash of this file and of the kernels' sources)."""
    key = step.py_func.__qualname__ if hasattr(step, 'py_func') else step.__qualname__
    loop = _LOOPS.get(key)
    if loop is None:
        function = types.FunctionType(_loop_template.__code__, {**globals(), '_step': step}, 'loop')
        function.__qualname__ = f'loop_{key}_{_DIGEST}'
        function.__doc__ = _loop_template.__doc__
        loop = _LOOPS[key] = numba.njit(cache=True, fastmath=_FAST)(function)
    return loop


def sparse(matrix) -> tuple:
    """A matrix as its nonzero entries: (rows, columns, values), the compiled loop's C (Table 6's
    C = [I 0] has 3 of 18)."""
    matrix = np.asarray(matrix, dtype=float)
    rows, cols = np.nonzero(matrix)
    return (np.ascontiguousarray(rows, dtype=np.int64), np.ascontiguousarray(cols, dtype=np.int64),
            np.ascontiguousarray(matrix[rows, cols]))


class FullRecord:
    """Where the compiled loop writes every sample: simulate's ``_Record`` arrays (the
    trajectories), step k's at index k (samples at k + 1)."""

    metrics_from = 0
    chunk = CHUNK

    def __init__(self, record, runs: int, n: int, neurons: int):
        self.outputs = (record.truth, record.estimate,
                        record.cov if record.cov is not None else np.zeros((runs, 0, 0)),
                        record.nees if record.nees is not None else np.zeros((runs, 0)),
                        record.nis if record.nis is not None else np.zeros((runs, 0)),
                        record.controls,
                        record.spikes if record.spikes is not None else np.zeros((runs, 0), dtype=np.int64),
                        record.raster if record.raster is not None else np.zeros((0, max(neurons, 1)), np.int16))

    def offsets(self, first: int) -> tuple[int, int]:
        """(index of sample first + 1, index of step first)."""
        return first + 1, first

    def done(self, first: int, count: int, diverged_at: np.ndarray) -> None:
        """Steps first .. first + count - 1 are written (nothing to do: they stay; simulate
        discards a diverged run's samples at the end)."""


class CompiledLoop:
    """One :func:`simulate` set-up stepped by the compiled loop: its estimator, truth (a
    blocks.Plant, stepped inside, or a Basilisk plant, stepped between compiled steps),
    position sensor and ``_Control``, at steps of ``dt``."""

    def __init__(self, estimator, plant, sensor, control, dt: float, filter_c, r_hat):
        program = estimator.program  # the filter's kernel and the arrays it steps
        if dt != program.dt:
            estimator.prepare(dt)
        self.estimator, self.plant, self.sensor, self.dt = estimator, plant, sensor, float(dt)
        runs, n, n_u = estimator.runs, estimator.model.n_state, estimator.model.n_input
        dynamics, drift = program.dynamics(estimator.batch_x_hat, np.zeros((runs, n_u)), dt)
        m = sensor.model.measurement_matrix.shape[0]
        self._z, self._u = np.zeros((runs, m)), np.zeros((runs, n_u))
        network = estimator.network
        self._dynamics, self._drift = dynamics, drift
        self._loop = loop_kernel(program.kernel)
        self.truth_inside = hasattr(plant, 'step_noise_covariance')  # blocks.Plant; Basilisk steps itself
        self._x = np.ascontiguousarray(plant.x, dtype=float).copy()
        self._applied = np.zeros((runs, n_u))
        truth_params = None
        if self.truth_inside:
            if plant.model.is_linear:
                phi, gamma = (np.ascontiguousarray(a) for a in plant.model.discrete_matrices(dt))
            else:  # RK4 of the model's compiled twin (unsupported() checked there is one)
                phi, gamma = np.zeros((n, n)), np.zeros((n, n_u))
                truth_params = model_kernels.compiled_params(plant.model)
            self._plant_root = np.ascontiguousarray(_plant_root(plant, dt))
        else:
            phi, gamma, self._plant_root = np.zeros((n, n)), np.zeros((n, n_u)), np.zeros((n, n))
        self._phi, self._gamma = phi, gamma
        self._models = (program.dynamics.loop_model(),
                        (truth_params is not None, np.zeros(2) if truth_params is None else truth_params,
                         int(getattr(plant, 'substeps', 1))))
        mode = (CONTROL_LQR if control.gain is not None else
                CONTROL_SCHEDULE if control.schedule is not None else CONTROL_NONE)
        self._control = (mode, np.ascontiguousarray(np.zeros((n_u, n)) if control.gain is None else control.gain,
                                                    dtype=float),
                         np.ascontiguousarray(control.setpoint, dtype=float),
                         np.ascontiguousarray(np.zeros((1, n_u)) if control.schedule is None else control.schedule,
                                              dtype=float))
        self._sensing = (sparse(sensor.model.measurement_matrix), np.ascontiguousarray(sensor._root), None,
                         sparse(filter_c), np.ascontiguousarray(r_hat, dtype=float))
        self._neurons = network.r.shape[1]
        spiking = estimator.spiking
        self._sigma = estimator.settings.membrane_noise * np.sqrt(dt) if spiking else 0.0

    def run(self, sink, steps: int, divergence, events=None, on_step=None) -> None:
        """Steps 0 .. steps - 1, written to ``sink`` (a :class:`FullRecord` or a chunk sink);
        ``divergence`` is simulate's ``_Divergence`` (the runs still running, and what marks
        and restarts a run that diverged); ``events`` and ``on_step`` as simulate's. Raises what
        simulate's Python loop raises at the same step."""
        boundaries = sorted({steps, *(k for k in (events or {}) if 0 < k < steps)})
        k = 0
        while k < steps:
            if events and k in events:
                events[k](self.estimator)
            end = min(k + sink.chunk, next(b for b in boundaries if b > k))
            self._chunk(sink, k, end - k, divergence)
            if on_step is not None:
                for step in range(k, end):
                    on_step(step)
            k = end

    def _chunk(self, sink, first: int, count: int, divergence) -> None:
        """Steps first .. first + count - 1, in as many compiled calls as divergences need, then
        ``sink.done``."""
        runs, n = self._x.shape
        plant_noise = (self.plant._noise.take(count) if self.truth_inside else np.zeros((runs, count, n)))
        sensor_noise = self.sensor._noise.take(count)
        membrane = (np.stack([g.normal(0.0, self._sigma, (count, self._neurons))
                              for g in self.estimator.network.noise_rngs], axis=1)
                    if self._sigma > 0.0 else np.zeros((0, runs, self._neurons)))
        sample_at, step_at = sink.offsets(first)
        done = 0
        while done < count:
            left = count if self.truth_inside else done + 1  # Basilisk: one step per call
            status, taken = self._call(sink, first + done, left - done, sample_at + done, step_at + done,
                                       plant_noise[:, done:left], sensor_noise[:, done:left],
                                       membrane[done:left] if membrane.shape[0] else membrane, divergence)
            done += taken
            k = first + done - 1  # the last step taken
            if self.truth_inside:
                self._sync_plant(taken)
            if status == STATUS_CONTROL_DIVERGED:  # mark before step first + done, then take it
                divergence.control(first + done, self._u, self.estimator)
            elif not self.truth_inside:
                self._step_truth(sink, sample_at + done - 1, step_at + done - 1, k, status, divergence)
            elif status == STATUS_RUN_DIVERGED:
                divergence.check(k, self.estimator, self.plant)
            elif status == kernels.STATUS_NON_FINITE:
                raise FloatingPointError(f'the {self.estimator.kind} state became non-finite')
        sink.done(first, count, divergence.at)

    def _call(self, sink, first: int, count: int, sample_at: int, step_at: int, plant_noise, sensor_noise,
              membrane, divergence) -> tuple[int, int]:
        """One compiled call for steps first .. first + count - 1; returns (status, steps taken)
        after the estimator's counters and a bad input's ValueError."""
        estimator = self.estimator
        program = estimator.program  # read each call: an event may have retuned the constants
        running = program.all_runs if divergence.running is None else np.ascontiguousarray(divergence.running)
        step_args = (program.constants, program.state, program.network, running, self.dt, self._dynamics,
                     self._drift, self._z, self._u, estimator.network.zero_noise)
        truth = (self.truth_inside, self._phi, self._gamma, self._plant_root, np.ascontiguousarray(plant_noise),
                 self._x, self._applied)
        sensing = self._sensing[:2] + (np.ascontiguousarray(sensor_noise),) + self._sensing[3:]
        status, taken, capped = self._loop(step_args, np.ascontiguousarray(membrane), truth, sensing, self._control,
                                           sink.outputs, (first, count, sample_at, step_at, sink.metrics_from),
                                           self._models)
        estimator.steps += taken
        estimator.capped_steps += capped
        if status == kernels.STATUS_BAD_INPUT:
            raise ValueError('z and u must be finite')
        return status, taken

    def _step_truth(self, sink, sample: int, step: int, k: int, status: int, divergence) -> None:
        """Step k's truth by the plant itself (Basilisk), its samples, and the divergence check."""
        self.plant.step(self._u, self.dt)
        self._x[:] = self.plant.x
        record_sample(sample, step, k + 1 >= sink.metrics_from, self._x,
                      np.ascontiguousarray(self.plant.applied, dtype=float), self.estimator.program.state,
                      self.estimator.program.network, sink.outputs)
        if divergence.check(k, self.estimator, self.plant) == 0 and status == kernels.STATUS_NON_FINITE:
            raise FloatingPointError(f'the {self.estimator.kind} state became non-finite')

    def _sync_plant(self, taken: int) -> None:
        """The compiled truth back into the plant object after ``taken`` steps of it."""
        self.plant.x, self.plant.applied = self._x.copy(), self._applied.copy()
        self.plant.time += taken * self.dt


def _plant_root(plant, dt: float) -> np.ndarray:
    """L with L L^T = the process noise one step adds (the plant's own cached root)."""
    from snn_estimator.plant.truth import matrix_sqrt
    root = plant._sqrt_cache.get(dt)
    if root is None:
        root = plant._sqrt_cache[dt] = matrix_sqrt(plant.step_noise_covariance(dt))
    return root
