"""The nonlinear relative motion (:class:`~snn_estimator.models.NonlinearCircular`) compiled: its
drift f(x, u), its Jacobian A(x) and the step's model input the step kernel reads, batched over
runs in one call (docs/decisions.md, 62).

:func:`step_dynamics` is what :class:`~snn_estimator.filters.program.StepDynamics` computes in
numpy for any other nonlinear model (``StateSpaceModel.linearized_increment`` and
``transition``), with the same semantics:

* ``[A_d | B_d]`` of each run: with ``exact``, A(x_hat) frozen over the step and integrated
  exactly, A_d = (Phi - I) / dt, B_d = Gamma / dt, (Phi, Gamma) the zero-order hold of
  (A(x_hat), B) (the slow weights of Eq. 16-17 from the Jacobian at the estimate, Eq. 14);
  otherwise (euler) A_d = A(x_hat), B_d = B;
* unless ``linearized`` (the network integrates A(x_hat) x_hat, Eq. 17), the drift a filter
  integrates itself: exact, one classical RK4 step of f with u held, as (x_next - x_hat) / dt;
  euler, f(x_hat, u).

Phi - I comes from the Taylor series of e^M - I, M = [[A, B], [0, 0]] dt, summed until a bound
on the rest is below the unit roundoff of the sum (with ||M||_1 halved to at most 1 first and
e^M - I squared back as E (E + 2 I)); only M's top n rows are ever non-zero, so every product is
n x n by n x (n + nu). The numpy path subtracts I from scipy's exponential and the drift from
x_next, so the two agree to the rounding of those subtractions (~1e-16 |x| / dt), not to the bit.

:func:`transition` is the model truth's step (``blocks.Plant``: RK4 substeps), which
snn_estimator.sim.compiled_loop runs in its loop (docs/decisions.md, 63).

Models live in the foundation, which loads no compiler (test/house/test_layers.py); this is
their compiled twin, checked against them on random states (test/core/test_model_kernels.py).
"""

from __future__ import annotations

import numba
import numpy as np

from snn_estimator.models import NonlinearCircular, StateSpaceModel

# the fast-math flags of the step kernels (kernels.py): no NaN/Inf assumptions
_FAST = {'reassoc', 'contract', 'nsz', 'arcp'}
_jit = numba.njit(fastmath=_FAST, cache=True)

#: The unit roundoff the exponential's series is summed to.
_ROUNDOFF = 2.0 ** -53
#: Terms of the series at most (||M||_1 <= 1: 1/25! is far below the roundoff).
_MAX_TERMS = 25
#: NonlinearCircular's states and states + inputs, as constants: the products' loops then have
#: fixed trip counts, which LLVM unrolls (~100 ns per product here).
_N, _W = 6, 9


# ---------------------------------------------------------------- the model (NonlinearCircular)
@_jit
def _gravity_factor(radius, x):
    """g = (R / r_c)^3 - 1 = (1 + q)^-1.5 - 1, q = (r_c^2 - R^2) / R^2, without cancellation
    (NonlinearCircular._gravity_factor)."""
    q = ((x[0] * x[0] + x[1] * x[1] + x[2] * x[2]) - 2.0 * radius * x[2]) / (radius * radius)
    return np.expm1(-1.5 * np.log1p(q))


@_jit
def _f(mean_motion, radius, x, u, out):
    """f(x, u) of NonlinearCircular.f for one run: v, then -n^2 (p + g d) + the Coriolis and
    centrifugal terms + u (B = [0; I])."""
    n2, two_n = mean_motion ** 2, 2.0 * mean_motion
    g = _gravity_factor(radius, x)
    out[0], out[1], out[2] = x[3], x[4], x[5]
    out[3] = two_n * x[5] - n2 * g * x[0] + u[0]
    out[4] = -n2 * (1.0 + g) * x[1] + u[1]
    out[5] = -two_n * x[3] - n2 * g * (x[2] - radius) + u[2]


@_jit
def _jacobian(mean_motion, radius, x, a):
    """A(x) of NonlinearCircular.jacobian for one run, written into ``a`` (n x n):
    [[0, I], [G(p) + diag(n^2, 0, n^2), Omega]], G = -(mu / r_c^3)(I - 3 d d^T / r_c^2)."""
    n2 = mean_motion * mean_motion
    g = _gravity_factor(radius, x)
    d0, d1, d2 = x[0], x[1], x[2] - radius
    weight = 3.0 * n2 * (1.0 + g) / (d0 * d0 + d1 * d1 + d2 * d2)  # mu / r_c^3 = n^2 (1 + g)
    for i in range(6):
        for j in range(6):
            a[i, j] = 0.0
    for i in range(3):
        a[i, i + 3] = 1.0
    a[3, 0], a[3, 1], a[3, 2] = weight * d0 * d0 - n2 * g, weight * d0 * d1, weight * d0 * d2
    a[4, 0], a[4, 1], a[4, 2] = weight * d1 * d0, weight * d1 * d1 - n2 * (1.0 + g), weight * d1 * d2
    a[5, 0], a[5, 1], a[5, 2] = weight * d2 * d0, weight * d2 * d1, weight * d2 * d2 - n2 * g
    a[3, 5] = 2.0 * mean_motion
    a[5, 3] = -2.0 * mean_motion


# ---------------------------------------------------------------- the zero-order hold
@_jit
def _norm_1(top):
    """||M||_1 (largest column sum) of M = [top; 0]."""
    largest = 0.0
    for j in range(top.shape[1]):
        column = 0.0
        for i in range(top.shape[0]):
            column += abs(top[i, j])
        largest = max(largest, column)
    return largest


@_jit
def _times(left, right, out):
    """out = left[:, :n] right: the top rows of the product of two matrices [top; 0] (n x w)."""
    for i in range(_N):
        for j in range(_W):
            acc = 0.0
            for k in range(_N):
                acc += left[i, k] * right[k, j]
            out[i, j] = acc


@_jit
def _expm1_top(top, out, term, product):
    """The top rows of e^M - I for M = [top; 0] (n x w, n = 6, w = 9), into ``out``: Taylor series
    with the rest bounded by ||T_k||_1 theta / (k + 1 - theta), theta = ||M||_1 <= 1 after
    halving s times, then E <- E (E + 2 I) s times. ``top`` is scaled in place. NaN if M is
    not finite."""
    theta = _norm_1(top)
    if not np.isfinite(theta):
        out[:, :] = np.nan
        return
    halvings = 0
    while theta > 1.0:
        theta *= 0.5
        halvings += 1
    scale = 0.5 ** halvings
    for i in range(_N):
        for j in range(_W):
            top[i, j] *= scale
            term[i, j] = top[i, j]
            out[i, j] = top[i, j]
    for k in range(2, _MAX_TERMS + 1):
        _times(term, top, product)
        for i in range(_N):
            for j in range(_W):
                term[i, j] = product[i, j] / k
                out[i, j] += term[i, j]
        if _norm_1(term) * theta <= _ROUNDOFF * _norm_1(out) * (k + 1.0 - theta):
            break
    for _ in range(halvings):  # e^{2X} - I = E (E + 2 I), E = e^X - I
        _times(out, out, product)
        for i in range(_N):
            for j in range(_W):
                out[i, j] = product[i, j] + 2.0 * out[i, j]


# ---------------------------------------------------------------- one call per step
@_jit
def _rk4_drift(mean_motion, radius, x, u, dt, stages, trial, drift):
    """(x_next - x) / dt of one classical RK4 step of f with u held: (k1 + 2 k2 + 2 k3 + k4) / 6."""
    n = x.shape[0]
    _f(mean_motion, radius, x, u, stages[0])
    for stage in range(1, 4):
        step = dt if stage == 3 else 0.5 * dt
        for i in range(n):
            trial[i] = x[i] + step * stages[stage - 1, i]
        _f(mean_motion, radius, trial, u, stages[stage])
    for i in range(n):
        drift[i] = (stages[0, i] + 2.0 * stages[1, i] + 2.0 * stages[2, i] + stages[3, i]) / 6.0


@_jit
def step_dynamics(params, b_matrix, x_hat, u, dt, exact, linearized, packed, drift):
    """Write each run's [A_d | B_d] into ``packed`` (runs, n, n + nu) and, unless
    ``linearized``, its drift into ``drift`` (runs, n) (see the module docstring).
    ``params`` = (mean motion n in rad/s, orbit radius R in m); ``b_matrix`` B (n, nu);
    ``x_hat`` (runs, n) m and m/s; ``u`` (runs, nu) m/s^2; ``dt`` s."""
    mean_motion, radius = params[0], params[1]
    runs, n, w = packed.shape  # (runs, 6, 9): checked by the caller (StepDynamics)
    a = np.empty((n, n))
    top, term, product = np.empty((n, w)), np.empty((n, w)), np.empty((n, w))
    stages, trial = np.empty((4, n)), np.empty(n)
    for r in range(runs):
        _jacobian(mean_motion, radius, x_hat[r], a)
        if exact:
            for i in range(n):
                for j in range(n):
                    top[i, j] = dt * a[i, j]
                for j in range(n, w):
                    top[i, j] = dt * b_matrix[i, j - n]
            _expm1_top(top, packed[r], term, product)
            for i in range(n):
                for j in range(w):
                    packed[r, i, j] /= dt
        else:
            for i in range(n):
                for j in range(n):
                    packed[r, i, j] = a[i, j]
                for j in range(n, w):
                    packed[r, i, j] = b_matrix[i, j - n]
        if linearized:
            continue
        if exact:
            _rk4_drift(mean_motion, radius, x_hat[r], u[r], dt, stages, trial, drift[r])
        else:
            _f(mean_motion, radius, x_hat[r], u[r], drift[r])


@_jit
def transition(params, x, u, dt, substeps, stages, trial):
    """x <- x after ``dt`` with u held, by ``substeps`` classical RK4 steps (models.rk4, the
    formula the model truth's Plant steps with), in place; ``x``, ``u`` one run's; ``stages``
    (4, n) and ``trial`` (n) scratch."""
    mean_motion, radius = params[0], params[1]
    n = x.shape[0]
    h = dt / substeps
    for _ in range(substeps):
        _rk4_drift(mean_motion, radius, x, u, h, stages, trial, trial)  # trial is free once the stages are in
        for i in range(n):
            x[i] = x[i] + h * trial[i]


@_jit
def drift_f(params, x, u, out):
    """f(x, u) of every row of ``x`` (rows, n) with ``u`` (rows, nu), into ``out``."""
    for r in range(x.shape[0]):
        _f(params[0], params[1], x[r], u[r], out[r])


@_jit
def jacobian(params, x, out):
    """A(x) of every row of ``x`` (rows, n), into ``out`` (rows, n, n)."""
    for r in range(x.shape[0]):
        _jacobian(params[0], params[1], x[r], out[r])


def compiled_params(model: StateSpaceModel) -> np.ndarray | None:
    """The ``params`` of :func:`step_dynamics` for ``model``, or None if it has no compiled twin
    (a model other than NonlinearCircular itself: a subclass may change f)."""
    if type(model) is not NonlinearCircular:
        return None
    return np.array([model.mean_motion, model.orbit_radius])
