"""Models against independent computations: matrix exponentials, CW closed forms, finite differences,
two-body integration in an inertial frame."""

import numpy as np
import pytest
import scipy.linalg
from scipy.integrate import solve_ivp

from snn_estimator.models import EARTH_MU, ClohessyWiltshire, NonlinearCircular, VanDerPol


def cw_free_motion(state0, n, t):
    """Closed-form CW solution without thrust in Fehse's LVLH axes (x V-bar, z R-bar)."""
    x0, y0, z0, vx0, vy0, vz0 = state0
    s, c = np.sin(n * t), np.cos(n * t)
    x = (4 * vx0 / n - 6 * z0) * s - 2 * vz0 / n * c + (6 * n * z0 - 3 * vx0) * t + (x0 + 2 * vz0 / n)
    y = y0 * c + vy0 / n * s
    z = (2 * vx0 / n - 3 * z0) * c + vz0 / n * s + (4 * z0 - 2 * vx0 / n)
    vx = (4 * vx0 - 6 * n * z0) * c + 2 * vz0 * s + (6 * n * z0 - 3 * vx0)
    vy = -y0 * n * s + vy0 * c
    vz = -(2 * vx0 - 3 * n * z0) * s + vz0 * c
    return np.array([x, y, z, vx, vy, vz])


def test_mean_motion_follows_eq39_for_a_400km_orbit():
    model = ClohessyWiltshire()
    assert model.mean_motion == pytest.approx(np.sqrt(EARTH_MU / 6_778_137.0 ** 3), rel=1e-12)
    assert model.mean_motion == pytest.approx(1.1313e-3, rel=1e-3)  # ~92.6 min period


def test_standard_cw_matches_the_closed_form_solution():
    model = ClohessyWiltshire()
    state0 = np.array([70.0, 30.0, -5.0, -1.7, -0.9, 0.25])
    state = state0.copy()
    for _ in range(3000):  # 300 s in 0.1 s steps, no thrust
        state = model.transition(state, np.zeros(3), 0.1)
    np.testing.assert_allclose(state, cw_free_motion(state0, model.mean_motion, 300.0),
                               rtol=1e-9, atol=1e-9)


def test_transition_equals_expm_with_zero_order_hold():
    model = ClohessyWiltshire(orbit_radius=7.0e6)
    a = model.system_matrix(model.mean_motion)
    dt = 0.1
    phi = scipy.linalg.expm(a * dt)
    # Gamma = integral_0^dt expm(A s) ds B, by a fine trapezoid rule
    s = np.linspace(0.0, dt, 2001)
    gamma = np.trapezoid(np.stack([scipy.linalg.expm(a * si) for si in s]), s, axis=0) @ model.input_matrix
    x = np.array([1.0, -2.0, 3.0, 0.1, -0.2, 0.3])
    u = np.array([0.01, -0.02, 0.03])
    np.testing.assert_allclose(model.transition(x, u, dt), phi @ x + gamma @ u, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(model.transition(x, u, dt, 'euler'), x + dt * (a @ x + model.input_matrix @ u))


def test_printed_cw_matrix_differs_only_where_the_misprints_are():
    n = ClohessyWiltshire().mean_motion
    standard = ClohessyWiltshire.system_matrix(n, 'standard')
    printed = ClohessyWiltshire.system_matrix(n, 'as_published')
    differing = {tuple(index) for index in np.argwhere(standard != printed)}
    # row 5 (y''): -n^2 on y vs on vy; row 6 (z''): 3n^2 on z vs 2n^2 on vz
    assert differing == {(4, 1), (4, 4), (5, 2), (5, 5)}
    assert standard[4, 1] == -n * n and printed[4, 4] == -n * n
    assert standard[5, 2] == 3 * n * n and printed[5, 5] == 2 * n * n
    # the printed y-dynamics do not oscillate: a pure y offset stays put instead of returning
    assert np.all(printed[3:, 1] == 0.0)


def test_partial_measurement_selects_the_position_axes():
    model = ClohessyWiltshire(measured_axes=(0, 2))
    assert model.measurement_names == ('x', 'z')
    np.testing.assert_array_equal(model.h(np.arange(6.0)), [0.0, 2.0])


@pytest.mark.parametrize('kwargs, message', [
    ({'orbit_radius': 0.0}, 'orbit_radius'),
    ({'orbit_radius': -7e6}, 'orbit_radius'),
    ({'form': 'printed'}, 'cw_model'),
    ({'measured_axes': (0, 3)}, 'measured_axes'),
    ({'measured_axes': ()}, 'measured_axes'),
    ({'measured_axes': (1, 1)}, 'measured_axes'),
])
def test_bad_cw_parameters_raise_value_errors_that_name_the_field(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ClohessyWiltshire(**kwargs)


def test_van_loan_process_noise_matches_q_dt_for_short_steps_and_is_exact_for_a_double_integrator():
    model = ClohessyWiltshire(orbit_radius=1e12)  # n ~ 2e-11 rad/s: a free double integrator
    q = np.diag([0.0, 0.0, 0.0, 1.0, 2.0, 3.0])
    dt = 2.0
    q_d = model.process_noise_discrete(q, dt)
    # for a double integrator (n -> 0) the exact answer is [[q dt^3/3, q dt^2/2], [q dt^2/2, q dt]]
    expected = np.zeros((6, 6))
    for axis, density in zip(range(3), (1.0, 2.0, 3.0)):
        expected[axis, axis] = density * dt ** 3 / 3
        expected[axis, axis + 3] = expected[axis + 3, axis] = density * dt ** 2 / 2
        expected[axis + 3, axis + 3] = density * dt
    np.testing.assert_allclose(q_d, expected, rtol=1e-9, atol=1e-9)
    leo = ClohessyWiltshire()
    np.testing.assert_allclose(leo.process_noise_discrete(q, 1e-4)[3:, 3:], q[3:, 3:] * 1e-4, rtol=1e-3, atol=1e-9)


def test_van_der_pol_jacobian_equals_finite_differences():
    model = VanDerPol(mu=0.7)
    rng = np.random.default_rng(5)
    for x in rng.normal(0.0, 2.0, (5, 2)):
        jac = model.jacobian(x, np.zeros(1))
        eps = 1e-6
        numeric = np.column_stack([
            (model.f(x + eps * e, np.zeros(1)) - model.f(x - eps * e, np.zeros(1))) / (2 * eps)
            for e in np.eye(2)])
        np.testing.assert_allclose(jac, numeric, rtol=1e-7, atol=1e-8)


def test_van_der_pol_batches_match_single_evaluations():
    model = VanDerPol(mu=0.005)
    xs = np.array([[2.0, 2.0], [-1.0, 0.5], [0.3, -0.7]])
    us = np.zeros((3, 1))
    batch = model.transition(xs, us, 0.01)
    singles = np.stack([model.transition(x, u, 0.01) for x, u in zip(xs, us)])
    np.testing.assert_allclose(batch, singles, rtol=0, atol=0)
    np.testing.assert_allclose(model.jacobian(xs, us), np.stack([model.jacobian(x, u) for x, u in zip(xs, us)]))


def test_linearized_increment_tends_to_the_jacobian_for_small_steps():
    model = VanDerPol(mu=0.5)
    x = np.array([1.2, -0.4])
    a_exact, b_exact = model.linearized_increment(x, 1e-6, 'exact')
    np.testing.assert_allclose(a_exact, model.jacobian(x, np.zeros(1)), atol=1e-5)
    np.testing.assert_allclose(b_exact, model.input_matrix, atol=1e-5)
    # the exact step against scipy's exponential of [[J, B], [0, 0]] dt (Van Loan's block form)
    block = np.zeros((3, 3))
    block[:2, :2], block[:2, 2:] = model.jacobian(x, np.zeros(1)), model.input_matrix
    exp = scipy.linalg.expm(0.01 * block)
    a_d, b_d = model.linearized_increment(x, 0.01, 'exact')
    np.testing.assert_allclose(np.eye(2) + 0.01 * a_d, exp[:2, :2], rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(0.01 * b_d, exp[:2, 2:], rtol=1e-13, atol=1e-15)
    # and it is not the Euler step (the O(dt^2) terms are there)
    assert np.abs(a_d - model.jacobian(x, np.zeros(1))).max() > 1e-4


def test_small_argument_expm_matches_scipy():
    from snn_estimator.models import expm
    rng = np.random.default_rng(1)
    for scale in (1e-4, 1e-2, 0.0125, 0.3):
        matrices = rng.normal(0.0, scale, (5, 3, 3))
        np.testing.assert_allclose(expm(matrices), scipy.linalg.expm(matrices), rtol=1e-14, atol=1e-15)


# ------------------------------------------------------------ nonlinear relative motion (NERM)
def _central_differences(model, x, steps):
    u = np.zeros(3)
    return np.column_stack([(model.f(x + h * e, u) - model.f(x - h * e, u)) / (2 * h)
                            for e, h in zip(np.eye(6), steps)])


def test_nonlinear_jacobian_equals_central_differences_near_and_far():
    model = NonlinearCircular()
    states = np.array([[-5000.0, 100.0, 50.0, 0.5, 0.1, -0.3], [1e3, -2e3, 3e3, 1.0, 2.0, 3.0],
                       [-50e3, 0.0, 0.0, 0.0, 0.0, 0.0], [0.3, -0.2, 0.1, 0.0, 0.0, 0.0]])
    jacobians = model.jacobian(states, np.zeros((4, 3)))
    for x, jac in zip(states, jacobians):
        numeric = _central_differences(model, x, [1.0] * 3 + [1e-3] * 3)
        # the gravity block is ~n^2 = 1.3e-6 1/s^2; the truncation error of 1 m steps is ~1e-13
        np.testing.assert_allclose(jac, numeric, rtol=0, atol=1e-12)
        np.testing.assert_allclose(jac, model.jacobian(x, np.zeros(3)), rtol=0, atol=0)
    # and it is not CW's: the gravity gradient turns with the line to Earth's centre at 50 km
    cw = ClohessyWiltshire().jacobian(np.zeros(6), np.zeros(3))
    assert np.abs(jacobians[2] - cw).max() > 1e-2 * model.mean_motion ** 2


@pytest.mark.parametrize('separation', [1.0, 100.0, 1e4])
def test_nonlinear_acceleration_tends_to_cw_as_the_separation_goes_to_zero(separation):
    """The difference from CW is second order: relative to CW's acceleration it is ~ r / R."""
    model, cw = NonlinearCircular(), ClohessyWiltshire()
    rng = np.random.default_rng(39)
    radius = model.orbit_radius
    for direction in rng.normal(size=(5, 3)):
        position = separation * direction / np.linalg.norm(direction)
        x = np.concatenate([position, 1e-3 * separation * rng.normal(size=3)])
        a_nerm, a_cw = model.f(x, np.zeros(3))[3:], cw.f(x, np.zeros(3))[3:]
        relative = np.linalg.norm(a_nerm - a_cw) / np.linalg.norm(a_cw)
        assert relative < 5.0 * separation / radius
    np.testing.assert_allclose(model.jacobian(np.zeros(6), np.zeros(3)), cw.jacobian(np.zeros(6), np.zeros(3)),
                               rtol=1e-14, atol=1e-20)


def _lvlh_axes(target):
    """Rows: the LVLH x (V-bar), y (-h_hat), z (-r_hat) axes in inertial components, and the
    frame's angular velocity in LVLH components (written out here, not taken from the package)."""
    r, v = target[:3], target[3:]
    h = np.cross(r, v)
    r_hat, h_hat = r / np.linalg.norm(r), h / np.linalg.norm(h)
    return np.array([np.cross(h_hat, r_hat), -h_hat, -r_hat]), np.array([0.0, -np.linalg.norm(h) / (r @ r), 0.0])


def _two_body_relative_motion(x0, duration):
    """Target and chaser integrated in an inertial frame under point-mass gravity, the chaser's
    final state returned in the target's LVLH frame."""
    radius, mu = ClohessyWiltshire().orbit_radius, EARTH_MU
    target = np.array([radius, 0.0, 0.0, 0.0, np.sqrt(mu / radius), 0.0])
    axes, omega = _lvlh_axes(target)
    chaser = target + np.concatenate([axes.T @ x0[:3], axes.T @ (x0[3:] + np.cross(omega, x0[:3]))])

    def gravity(_, s):
        r1, r2 = s[0:3], s[6:9]
        return np.concatenate([s[3:6], -mu * r1 / np.linalg.norm(r1) ** 3, s[9:12], -mu * r2 / np.linalg.norm(r2) ** 3])

    end = solve_ivp(gravity, (0.0, duration), np.concatenate([target, chaser]), method='DOP853',
                    rtol=1e-13, atol=1e-9).y[:, -1]
    axes, omega = _lvlh_axes(end[:6])
    p = axes @ (end[6:9] - end[0:3])
    return np.concatenate([p, axes @ (end[9:12] - end[3:6]) - np.cross(omega, p)])


# CW's position error after one orbit from a point at rest on V-bar (issue 39: 2.8 m, 69.5 m, 6.95 km)
@pytest.mark.parametrize('behind, cw_error', [(1e3, 2.78), (5e3, 69.5), (50e3, 6953.0)])
def test_nonlinear_model_follows_two_body_motion_over_one_orbit_where_cw_does_not(behind, cw_error):
    model, cw = NonlinearCircular(), ClohessyWiltshire()
    period = 2.0 * np.pi / model.mean_motion
    x0 = np.array([-behind, 0.0, 0.0, 0.0, 0.0, 0.0])
    truth = _two_body_relative_motion(x0, period)
    steps = int(np.ceil(period))  # the filters' propagation: RK4, ~1 s steps
    x = x0
    for _ in range(steps):
        x = model.transition(x, np.zeros(3), period / steps)
    assert np.linalg.norm(x[:3] - truth[:3]) < 1e-4  # m; measured ~1e-7 at all three ranges
    assert np.linalg.norm(x[3:] - truth[3:]) < 1e-8  # m/s
    phi, _ = cw.discrete_matrices(period)
    assert np.linalg.norm(phi[:3] @ x0 - truth[:3]) == pytest.approx(cw_error, rel=2e-3)


def test_nonlinear_model_follows_two_body_motion_from_a_moving_out_of_plane_start():
    model = NonlinearCircular()
    period = 2.0 * np.pi / model.mean_motion
    x0 = np.array([-5000.0, 100.0, 50.0, 0.5, 0.1, -0.3])
    truth = _two_body_relative_motion(x0, period)
    x = x0
    for _ in range(556):  # ~10 s steps of two RK4 substeps
        x = model.transition(x, np.zeros(3), period / 556, substeps=2)
    assert np.linalg.norm(x[:3] - truth[:3]) < 1e-3
