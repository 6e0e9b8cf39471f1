"""The compiled twin of the nonlinear relative motion (snn_estimator.filters.model_kernels)
against the numpy model it mirrors: f, the Jacobian, the zero-order hold and the RK4 drift on
random states from 1 m to 50 km, CW's exact discretisation at the origin, and a filter stepped
through the compiled and the numpy path (docs/decisions.md, 62)."""

import numpy as np
import pytest

from snn_estimator import make_estimator
from snn_estimator.filters import model_kernels
from snn_estimator.models import ClohessyWiltshire, NonlinearCircular
from snn_estimator.sim.scenarios import far_range_scenario

MODEL = NonlinearCircular()
PARAMS = model_kernels.compiled_params(MODEL)
B = np.ascontiguousarray(MODEL.input_matrix)


def random_states(runs=200, seed=0):
    """Positions from ~1 m to ~50 km in every direction, speeds up to 10 m/s, inputs up to 1 mm/s^2."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(runs, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    position = direction * 10.0 ** rng.uniform(0.0, 4.7, (runs, 1))
    x = np.concatenate([position, rng.uniform(-10.0, 10.0, (runs, 3))], axis=1)
    return np.ascontiguousarray(x), rng.uniform(-1e-3, 1e-3, (runs, 3))


def compiled_step(x, u, dt, method, linearized=False):
    packed, drift = np.empty((len(x), 6, 9)), np.empty((len(x), 6))
    model_kernels.step_dynamics(PARAMS, B, x, u, dt, method == 'exact', linearized, packed, drift)
    return packed, drift


def assert_close_per_row(actual, expected, rtol):
    """|actual - expected| <= rtol max|expected| of each run (a row's own scale: entries of a row
    that cancel to ~0 are held to the row's precision, not their own)."""
    scale = np.abs(expected).reshape(len(expected), -1).max(axis=1)
    error = np.abs(actual - expected).reshape(len(expected), -1).max(axis=1)
    assert np.all(error <= rtol * scale), (error / scale).max()


def test_the_compiled_f_and_jacobian_equal_the_models_to_rounding():
    x, u = random_states()
    f = np.empty_like(x)
    model_kernels.drift_f(PARAMS, x, u, f)
    assert_close_per_row(f, MODEL.f(x, u), 1e-13)
    jacobian = np.empty((len(x), 6, 6))
    model_kernels.jacobian(PARAMS, x, jacobian)
    expected = MODEL.jacobian(x, u)
    np.testing.assert_array_equal(jacobian == 0.0, expected == 0.0)
    np.testing.assert_allclose(jacobian, expected, rtol=1e-12, atol=0.0)  # the gravity gradient, entry by entry


@pytest.mark.parametrize('method', ['exact', 'euler'])
@pytest.mark.parametrize('dt', [0.1, 1.0, 10.0, 100.0])
def test_the_compiled_step_dynamics_equal_the_numpy_path(dt, method):
    """[A_d | B_d] equal linearized_increment (scipy's exponential less I, over dt) to ~1e-15 of
    their scale, and the drift equals one RK4 step of f (Euler: f) written here from the
    model's f; against (transition - x) / dt, the numpy path, up to that subtraction's rounding."""
    x, u = random_states(seed=1)
    packed, drift = compiled_step(x, u, dt, method)
    a_d, b_d = MODEL.linearized_increment(x, dt, method)
    expected = np.concatenate([a_d, np.broadcast_to(b_d, (len(x), 6, 3))], axis=2)
    assert_close_per_row(packed, expected, 1e-14)
    if method == 'euler':
        k = MODEL.f(x, u)
    else:
        k1 = MODEL.f(x, u)
        k2 = MODEL.f(x + 0.5 * dt * k1, u)
        k3 = MODEL.f(x + 0.5 * dt * k2, u)
        k4 = MODEL.f(x + dt * k3, u)
        k = (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0
    assert_close_per_row(drift, k, 1e-12)
    subtraction = 4.0 * np.finfo(float).eps * np.abs(x).max(axis=1, keepdims=True) / dt
    assert np.all(np.abs(drift - (MODEL.transition(x, u, dt, method) - x) / dt) <= subtraction + 1e-13 * np.abs(k))


@pytest.mark.parametrize('dt', [0.1, 1.0, 30.0])
def test_at_the_origin_the_exact_step_is_cws_zero_order_hold(dt):
    """A(0) is CW's, so I + dt A_d and dt B_d are CW's Phi and Gamma (expm of CW's A)."""
    packed, _ = compiled_step(np.zeros((1, 6)), np.zeros((1, 3)), dt, 'exact', linearized=True)
    phi, gamma = ClohessyWiltshire().discrete_matrices(dt)
    np.testing.assert_allclose(np.eye(6) + dt * packed[0, :, :6], phi, rtol=0.0, atol=1e-15 * max(dt, 1.0))
    np.testing.assert_allclose(dt * packed[0, :, 6:], gamma, rtol=0.0, atol=1e-15 * dt * max(dt, 1.0))


def test_a_non_finite_state_gives_non_finite_dynamics_and_does_not_hang():
    x = np.array([[np.inf, 0.0, 0.0, 0.0, 0.0, 0.0], [np.nan, 0.0, 0.0, 0.0, 0.0, 0.0]])
    packed, drift = compiled_step(x, np.zeros((2, 3)), 1.0, 'exact')
    assert not np.isfinite(packed).all(axis=(1, 2)).any() and not np.isfinite(drift).all(axis=1).any()


class NumpyNonlinearCircular(NonlinearCircular):
    """The same model, not NonlinearCircular itself: it has no compiled twin (a subclass may change f)."""


@pytest.mark.parametrize('kind', ['ekf', 'snn_ekf'])
def test_a_filter_steps_alike_through_the_compiled_and_the_numpy_dynamics(kind):
    """Two runs 2 km and 5 km out, 150 steps of 1 s: the estimates agree to 1e-9 m, spikes equal."""
    scenario = far_range_scenario(plant='nonlinear_circular', dynamics_model='nonlinear_circular')
    config = scenario.estimator.replace(neuron_count=60)
    fast = make_estimator(kind, config, scenario.model, runs=2, seeds=[0, 1])
    slow = make_estimator(kind, config, NumpyNonlinearCircular(), runs=2, seeds=[0, 1])
    assert fast.program.dynamics.compiled and not slow.program.dynamics.compiled
    rng = np.random.default_rng(4)
    x = np.array([[-2000.0, 10.0, 20.0, 0.1, 0.0, -0.05], [-5000.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    for _ in range(150):
        x = scenario.model.transition(x, np.zeros(3), 1.0)
        z = x[:, :3] + 0.1 * rng.normal(size=(2, 3))
        fast.step(z, np.zeros((2, 3)), 1.0)
        slow.step(z, np.zeros((2, 3)), 1.0)
        np.testing.assert_allclose(fast.x_hat, slow.x_hat, rtol=0.0, atol=1e-9)
        if fast.spiking:
            np.testing.assert_array_equal(fast.spikes, slow.spikes)
    np.testing.assert_allclose(fast.P, slow.P, rtol=1e-9)


def test_step_dynamics_refuses_a_state_of_the_wrong_shape():
    config = far_range_scenario(plant='nonlinear_circular', dynamics_model='nonlinear_circular').estimator
    estimator = make_estimator('ekf', config, NonlinearCircular(), runs=2)
    with pytest.raises(ValueError, match=r'x_hat and u must be \(2, 6\) and \(2, 3\)'):
        estimator.program.dynamics(np.zeros((3, 6)), np.zeros((3, 3)), 1.0)


@pytest.mark.parametrize('dt', [0.1, 1.0, 10.0])
def test_the_compiled_transition_is_the_models_rk4_substeps(dt):
    """The model truth's step (Plant: models.rk4 with 4 substeps), run by run in place."""
    x, u = random_states(seed=2)
    stepped, stages, trial = x.copy(), np.empty((4, 6)), np.empty(6)
    for r in range(len(x)):
        model_kernels.transition(PARAMS, stepped[r], u[r], dt, 4, stages, trial)
    assert_close_per_row(stepped, MODEL.transition(x, u, dt, 'exact', substeps=4), 1e-14)
