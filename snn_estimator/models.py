"""Dynamical models: Clohessy-Wiltshire relative motion (paper Sec. 3.2), the nonlinear relative
motion it linearises, the Schweighart-Sedwick linear J2 relative motion, and Van der Pol (Sec. 3.1).

Every model implements :class:`StateSpaceModel`: ``x_dot = f(x, u)`` with Jacobians ``A(x)``
and ``B``, and a *linear* measurement ``z = C x`` (both of the paper's problems measure a subset
of the state). All functions accept a leading batch axis: ``x`` of shape ``(..., n)``.
Time in seconds, SI units.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Sequence

import numpy as np
import scipy.linalg

from .defaults import (
    EARTH_EQUATORIAL_RADIUS,
    EARTH_J2,
    EARTH_MU,  # noqa: F401 (re-exported)
    ORBIT_INCLINATION,
)
from .defaults import ORBIT_RADIUS as DEFAULT_ORBIT_RADIUS
from .validation import check_choice, check_positive

#: Per-dt matrices kept (steps on a grid reuse a few; steps of any length must not grow them).
DT_CACHE_SIZE = 64

DISCRETIZATIONS = ('exact', 'euler')
#: The relative-motion models a filter can predict with (:func:`relative_motion`).
DYNAMICS_MODELS = ('cw', 'nonlinear_circular', 'ss_j2')


class StateSpaceModel(ABC):
    """A continuous-time model ``x_dot = f(x, u) + w``, ``z = C x + v``."""

    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    measurement_names: tuple[str, ...]
    #: True when f is linear: ``f(x, u) = A x + B u`` with constant A, B.
    is_linear: bool = False

    @property
    def n_state(self) -> int:
        return len(self.state_names)

    @property
    def n_input(self) -> int:
        return len(self.input_names)

    @property
    def n_meas(self) -> int:
        return len(self.measurement_names)

    @abstractmethod
    def f(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """State derivative, shape ``(..., n)``."""

    @abstractmethod
    def jacobian(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``A = df/dx`` at ``x``, shape ``(..., n, n)``."""

    #: Set by subclasses: ``B = df/du`` (constant here) and ``C`` of ``z = C x``.
    _b: np.ndarray
    _c: np.ndarray

    @property
    def input_matrix(self) -> np.ndarray:
        """``B = df/du`` (constant for the models here), shape ``(n, m_u)``."""
        return self._b

    @property
    def measurement_matrix(self) -> np.ndarray:
        """``C`` in ``z = C x``, shape ``(m, n)``."""
        return self._c

    def h(self, x: np.ndarray) -> np.ndarray:
        """Noise-free measurement ``C x``."""
        return np.asarray(x) @ self.measurement_matrix.T

    def transition(self, x: np.ndarray, u: np.ndarray, dt: float,
                   method: str = 'exact', substeps: int = 1) -> np.ndarray:
        """Propagate ``x_dot = f(x, u)`` over ``dt`` with ``u`` held (zero-order hold).

        'exact' uses the matrix exponential for linear models and RK4 (``substeps`` per step)
        otherwise; 'euler' is one forward-Euler step, the literal discretisation of Eq. 3.
        """
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        if method == 'euler':
            return x + dt * self.f(x, u)
        if self.is_linear:
            phi, gamma = self.discrete_matrices(dt)
            return x @ phi.T + u @ gamma.T
        return rk4(self.f, x, u, dt, substeps)

    def linearized_increment(self, x: np.ndarray, dt: float,
                             method: str = 'exact') -> tuple[np.ndarray, np.ndarray]:
        """Matrices ``(A_d, B_d)`` such that one step is ``x + dt (A_d x + B_d u)``.

        This is the linearised drift the spiking network implements through its slow weights
        (Eq. 16-17 use ``A_d = A(x_hat)``, ``B_d = B``: 'euler'). With 'exact' the Jacobian is
        frozen over the step and integrated exactly: ``A_d = (Phi - I)/dt``, ``B_d = Gamma/dt``,
        which tend to A and B as dt -> 0.
        """
        n = self.n_state
        if x is None:
            x = np.zeros(n)
        if method == 'euler':
            return self.jacobian(x, np.zeros(self.n_input)), self.input_matrix
        if self.is_linear:
            phi, gamma = self.discrete_matrices(dt)
            return (phi - np.eye(n)) / dt, gamma / dt
        a = self.jacobian(x, np.zeros(self.n_input))
        phi, gamma = zoh_matrices(a, self.input_matrix, dt)
        return (phi - np.eye(n)) / dt, gamma / dt

    def discrete_matrices(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Exact zero-order-hold ``(Phi, Gamma)`` of a linear model (cached per dt)."""
        if not self.is_linear:
            raise TypeError(f'{type(self).__name__} is nonlinear: it has no constant Phi')
        cache = self.__dict__.setdefault('_zoh_cache', {})
        if dt not in cache:
            if len(cache) >= DT_CACHE_SIZE:  # steps of any length (a sensor on its own clock)
                cache.clear()
            a = self.jacobian(np.zeros(self.n_state), np.zeros(self.n_input))
            cache[dt] = zoh_matrices(a, self.input_matrix, dt)
        return cache[dt]

    def process_noise_discrete(self, q_continuous: np.ndarray, dt: float) -> np.ndarray:
        """Covariance of the noise a continuous white noise of density Q adds over dt.

        Van Loan's method for linear models; ``Q dt`` (Euler-Maruyama) otherwise.
        """
        if not self.is_linear:
            return q_continuous * dt
        n = self.n_state
        a = self.jacobian(np.zeros(n), np.zeros(self.n_input))
        block = np.zeros((2 * n, 2 * n))
        block[:n, :n] = -a
        block[:n, n:] = q_continuous
        block[n:, n:] = a.T
        van_loan = scipy.linalg.expm(block * dt)
        phi_t = van_loan[n:, n:]
        q_d = phi_t.T @ van_loan[:n, n:]
        return 0.5 * (q_d + q_d.T)


def rk4(f, x: np.ndarray, u: np.ndarray, dt: float, substeps: int = 4) -> np.ndarray:
    """Classical Runge-Kutta integration of ``x_dot = f(x, u)`` with u held over dt."""
    h = dt / substeps
    for _ in range(substeps):
        k1 = f(x, u)
        k2 = f(x + 0.5 * h * k1, u)
        k3 = f(x + 0.5 * h * k2, u)
        k4 = f(x + h * k3, u)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x


def zoh_matrices(a: np.ndarray, b: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order-hold discretisation via ``expm([[A, B], [0, 0]] dt)``; A may be batched."""
    a = np.asarray(a, dtype=float)
    n, m = a.shape[-1], b.shape[-1]
    block = np.zeros(a.shape[:-2] + (n + m, n + m))
    block[..., :n, :n] = a
    block[..., :n, n:] = b
    exp_block = expm(block * dt)
    return exp_block[..., :n, :n], exp_block[..., :n, n:]


def expm(matrix: np.ndarray) -> np.ndarray:
    """Matrix exponential of a (batch of) matrices.

    Small arguments (max row sum <= 0.05, e.g. a Jacobian times a short step) use a degree-8
    Taylor polynomial, whose truncation error 0.05^9/9! < 1e-17 is below double precision and
    which costs a few small products instead of scipy's general algorithm. The choice is made
    per matrix, so a run of a batch gets what it would get alone.
    """
    matrix = np.asarray(matrix, dtype=float)
    large = np.abs(matrix).sum(axis=-1).max(axis=-1) > 0.05  # per matrix: a run's result is its own
    if np.all(large):
        return scipy.linalg.expm(matrix)
    identity = np.eye(matrix.shape[-1])
    result = identity + matrix / 8.0
    for k in range(7, 0, -1):  # Horner: I + M (I + M/2 (I + ... (I + M/8)))
        result = identity + (matrix @ result) / k
    if np.any(large):
        result[large] = scipy.linalg.expm(matrix[large])
    return result


class RelativeMotion(StateSpaceModel):
    """The chaser's motion relative to a target on a circular orbit of radius ``orbit_radius``.

    State ``[x, y, z, vx, vy, vz]`` (m, m/s) in the target's LVLH frame as the paper draws it
    (Fehse's convention): x along-track (V-bar), y opposite to the orbit normal (H-bar), z radial
    toward Earth (R-bar). Input: specific force ``[f_x, f_y, f_z]`` in m/s^2 (B = [0; I]).
    Measured: the position axes ``measured_axes`` (C selects them).
    """

    state_names = ('x', 'y', 'z', 'vx', 'vy', 'vz')
    input_names = ('fx', 'fy', 'fz')
    #: Its name in :data:`DYNAMICS_MODELS` (the estimator's ``dynamics_model`` must name it).
    dynamics_model: str

    def __init__(self, orbit_radius: float = DEFAULT_ORBIT_RADIUS, mu: float = EARTH_MU,
                 measured_axes: Sequence[int] = (0, 1, 2)):
        self.orbit_radius = check_positive(orbit_radius, 'orbit_radius (m)')
        self.mu = check_positive(mu, 'mu (m^3/s^2)')
        axes = tuple(int(a) for a in measured_axes)
        if not axes or len(set(axes)) != len(axes) or not all(0 <= a <= 2 for a in axes):
            raise ValueError(
                f'measured_axes must be distinct position axes among 0 (x), 1 (y), 2 (z); got {axes}')
        self.measured_axes = axes
        self.measurement_names = tuple(self.state_names[a] for a in axes)
        self.mean_motion = float(np.sqrt(self.mu / self.orbit_radius ** 3))  # Eq. 39, rad/s
        self._b = np.vstack([np.zeros((3, 3)), np.eye(3)])
        self._c = np.zeros((len(axes), 6))
        self._c[np.arange(len(axes)), axes] = 1.0


class LinearRelativeMotion(RelativeMotion):
    """Relative motion with constant ``A`` (``self._a``, set by the subclass): ``f = A x + B u``.
    The filters, the network and the compiled loop take any such model through ``is_linear``
    and its exact zero-order hold (:meth:`StateSpaceModel.discrete_matrices`)."""

    is_linear = True
    _a: np.ndarray

    def f(self, x, u):
        return np.asarray(x) @ self._a.T + np.asarray(u) @ self._b.T

    def jacobian(self, x, u):
        x = np.asarray(x)
        return np.broadcast_to(self._a, x.shape[:-1] + (6, 6)).copy() if x.ndim > 1 else self._a.copy()


class ClohessyWiltshire(LinearRelativeMotion):
    """Linearised relative motion about a circular orbit (Eq. 36-41, corrected); axes, state
    and input as :class:`RelativeMotion`.

    ``form='standard'`` (default) is the textbook CW system::

        x'' =  2 n z'           + f_x
        y'' = -n^2 y            + f_y
        z'' = -2 n x' + 3 n^2 z + f_z

    ``form='as_published'`` is the matrix printed as Eq. 41, which puts ``-n^2`` on ``vy``
    instead of ``y`` and ``2 n^2`` on ``vz`` instead of ``3 n^2`` on ``z`` (misprints: they make
    the out-of-plane motion damped instead of oscillating, and remove the radial gravity
    gradient). It is kept so the difference can be measured.
    """

    dynamics_model = 'cw'

    def __init__(self, orbit_radius: float = DEFAULT_ORBIT_RADIUS, mu: float = EARTH_MU,
                 form: str = 'standard', measured_axes: Sequence[int] = (0, 1, 2)):
        super().__init__(orbit_radius, mu, measured_axes)
        self.form = check_choice(form, ('standard', 'as_published'), 'cw_model')
        self._a = self.system_matrix(self.mean_motion, self.form)

    @staticmethod
    def system_matrix(n: float, form: str = 'standard') -> np.ndarray:
        """The CW ``A`` matrix for mean motion ``n`` (rad/s)."""
        a = np.zeros((6, 6))
        a[0:3, 3:6] = np.eye(3)
        a[3, 5] = 2.0 * n
        a[5, 3] = -2.0 * n
        if form == 'standard':
            a[4, 1] = -n * n
            a[5, 2] = 3.0 * n * n
        else:  # Eq. 41 as printed
            a[4, 4] = -n * n
            a[5, 5] = 2.0 * n * n
        return a


class NonlinearCircular(RelativeMotion):
    """The nonlinear equations of relative motion (two-body gravity on both spacecraft) about a
    target on a circular orbit; axes, state and input as :class:`RelativeMotion`.

    The target sits at ``(0, 0, -R)`` from Earth's centre, the frame turns at ``(0, -n, 0)``;
    with ``d = p - (0, 0, R)`` the chaser's position from Earth's centre and ``r_c = |d|``::

        x'' =  2 n z' + n^2 x - mu x / r_c^3                 + f_x
        y'' =                 - mu y / r_c^3                 + f_y
        z'' = -2 n x' + n^2 z + mu (R - z) / r_c^3 - mu / R^2 + f_z

    (Fehse 2003, ch. 3; Alfriend et al. 2010, ch. 4). Linearising ``r_c^-3`` about ``R`` gives
    :class:`ClohessyWiltshire` back. Exact for two-body motion at any separation: no curvature
    error (a point 5 km back on the straight V-bar is 1.84 m above the orbit, which CW ignores).
    The gravity difference is evaluated as ``-n^2 (p + g d)`` with ``g = (R / r_c)^3 - 1`` from
    ``expm1``/``log1p``, so it keeps full relative precision as the separation goes to 0 (the
    literal form subtracts two ~8.7 m/s^2 terms).
    """

    dynamics_model = 'nonlinear_circular'

    def _gravity_factor(self, p: np.ndarray) -> np.ndarray:
        """``g = (R / r_c)^3 - 1`` without cancellation: ``(1 + q)^-1.5 - 1``, ``q = (r_c^2 - R^2)/R^2``."""
        radius = self.orbit_radius
        q = ((p * p).sum(axis=-1) - 2.0 * radius * p[..., 2]) / (radius * radius)
        return np.expm1(-1.5 * np.log1p(q))

    def f(self, x, u):
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        n2, two_n = self.mean_motion ** 2, 2.0 * self.mean_motion
        p, v = x[..., :3], x[..., 3:]
        g = self._gravity_factor(p)
        acceleration = np.stack([two_n * v[..., 2] - n2 * g * p[..., 0],
                                 -n2 * (1.0 + g) * p[..., 1],
                                 -two_n * v[..., 0] - n2 * g * (p[..., 2] - self.orbit_radius)], axis=-1)
        return np.concatenate([v, acceleration + u @ self._b[3:].T], axis=-1)

    def jacobian(self, x, u):
        """``[[0, I], [G(p) + diag(n^2, 0, n^2), Omega]]``, ``G = -(mu / r_c^3)(I - 3 d d^T / r_c^2)``
        (the gravity gradient at the chaser), ``Omega`` the Coriolis block of CW."""
        x = np.asarray(x, dtype=float)
        n = self.mean_motion
        n2 = n * n
        p = x[..., :3]
        g = self._gravity_factor(p)
        d = p.copy()
        d[..., 2] -= self.orbit_radius
        outer = d[..., :, None] * d[..., None, :] / (d * d).sum(axis=-1)[..., None, None]
        a = np.zeros(x.shape[:-1] + (6, 6))
        a[..., 0:3, 3:6] = np.eye(3)
        block = 3.0 * (n2 * (1.0 + g))[..., None, None] * outer  # mu / r_c^3 = n^2 (1 + g)
        block[..., 0, 0] -= n2 * g       # -mu / r_c^3 + n^2 without cancellation
        block[..., 1, 1] -= n2 * (1.0 + g)
        block[..., 2, 2] -= n2 * g
        a[..., 3:6, 0:3] = block
        a[..., 3, 5] = 2.0 * n
        a[..., 5, 3] = -2.0 * n
        return a


class SchweighartSedwick(LinearRelativeMotion):
    """Linearised relative motion under Earth's J2 about a circular reference orbit of radius
    ``orbit_radius`` and inclination ``inclination`` (rad): Schweighart & Sedwick, "High-Fidelity
    Linearized J2 Model for Satellite Formation Flight", JGCD 25(6), 2002. Axes, state and input
    as :class:`RelativeMotion`.

    SS write it in the Hill frame (X radial out, Y along-track, Z along the orbit normal) as::

        X'' = 2 (n c) Y' + (5 c^2 - 2) n^2 X
        Y'' = -2 (n c) X'
        Z'' = -q^2 Z + 2 l q cos(q t + phi)

    with ``s = 3 J2 Re^2 / (8 r^2) (1 + 3 cos 2i)``, ``c = sqrt(1 + s)``: the J2 gravity gradient
    averaged over one orbit, and the frame turning at ``n c``. Here X = -z, Y = x, Z = -y, so::

        x'' =  2 n c z'                      + f_x
        y'' = -q^2 y                         + f_y
        z'' = -2 n c x' + (5 c^2 - 2) n^2 z  + f_z

    The cross-track frequency is SS's ``q = n c - (cos g sin g cot dO - sin^2 g cos i2)
    (dO1' - dO2') - dO1' cos i1`` (g the angle between the two orbit planes, dO their node
    difference, ``dOj' = -3 n J2 Re^2 / (2 r^2) cos ij`` the nodal rates). The filters' chaser flies
    in the target's plane (the approach's V-bar; a hop out of it is 200 m, 3e-5 rad of plane
    angle), where both nodal rates are equal: the forcing ``l`` is zero and ``q`` is
    ``n c + 3 n J2 Re^2 / (2 r^2) cos^2 i``, SS's ``k`` (the rate of the argument of latitude).
    SS's X and Y equations also carry a forcing that does not depend on the state (the J2 pull at
    the reference point); it is the same for chaser and target and cancels in their difference,
    the state here. With J2 = 0 the model is :class:`ClohessyWiltshire`; at the inclination where
    ``1 + 3 cos 2i = 0`` (54.7 deg) s = 0 and the in-plane block is CW's (q is still k there).
    SS average the J2 gradient over the orbit: its part that varies with the argument of
    latitude (docs/decisions.md, 82) is not in the model.
    """

    dynamics_model = 'ss_j2'

    def __init__(self, orbit_radius: float = DEFAULT_ORBIT_RADIUS, mu: float = EARTH_MU,
                 measured_axes: Sequence[int] = (0, 1, 2), inclination: float = ORBIT_INCLINATION,
                 j2: float = EARTH_J2, equatorial_radius: float = EARTH_EQUATORIAL_RADIUS):
        super().__init__(orbit_radius, mu, measured_axes)
        self.inclination = float(inclination)
        if not 0.0 <= self.inclination <= np.pi:
            raise ValueError(f'inclination must be in [0, pi] rad, got {inclination!r} '
                             '(radians: use math.radians(degrees))')
        self.j2 = check_positive(j2, 'j2 (Earth J2 coefficient; 0 gives CW)', strict=False)
        self.equatorial_radius = check_positive(equatorial_radius, 'equatorial_radius (m)')
        n, i = self.mean_motion, self.inclination
        ratio = self.j2 * (self.equatorial_radius / self.orbit_radius) ** 2
        #: SS's s and c (dimensionless) and the cross-track frequency q (rad/s), in-plane chaser.
        self.s = 3.0 * ratio / 8.0 * (1.0 + 3.0 * np.cos(2.0 * i))
        self.c = float(np.sqrt(1.0 + self.s))
        self.cross_track_frequency = n * self.c + 1.5 * n * ratio * np.cos(i) ** 2
        self._a = self.system_matrix(n, self.c, self.cross_track_frequency)

    @staticmethod
    def system_matrix(n: float, c: float, q: float) -> np.ndarray:
        """The SS ``A`` for mean motion ``n`` (rad/s), SS's ``c`` and cross-track frequency ``q``
        (rad/s), in this package's axes."""
        a = np.zeros((6, 6))
        a[0:3, 3:6] = np.eye(3)
        a[3, 5] = 2.0 * n * c
        a[5, 3] = -2.0 * n * c
        a[4, 1] = -q * q
        a[5, 2] = (5.0 * c * c - 2.0) * n * n
        return a


def relative_motion(dynamics_model: str = 'cw', orbit_radius: float = DEFAULT_ORBIT_RADIUS, mu: float = EARTH_MU,
                    measured_axes: Sequence[int] = (0, 1, 2),
                    inclination: float = ORBIT_INCLINATION) -> RelativeMotion:
    """The relative-motion model named ``dynamics_model`` (:data:`DYNAMICS_MODELS`): cw, the
    standard :class:`ClohessyWiltshire`; nonlinear_circular, :class:`NonlinearCircular`; ss_j2,
    :class:`SchweighartSedwick` (the only one that reads ``inclination``, rad)."""
    kind = check_choice(dynamics_model, DYNAMICS_MODELS, 'dynamics_model')
    if kind == 'ss_j2':
        return SchweighartSedwick(orbit_radius=orbit_radius, mu=mu, measured_axes=measured_axes,
                                  inclination=inclination)
    model = NonlinearCircular if kind == 'nonlinear_circular' else ClohessyWiltshire
    return model(orbit_radius=orbit_radius, mu=mu, measured_axes=measured_axes)


class VanDerPol(StateSpaceModel):
    """Van der Pol oscillator (Eq. 25-28), measured in x1.

    ``x1' = x2``, ``x2' = mu (1 - x1^2) x2 - x1 + u``. The paper's system has no input; a
    force on x2 is added so the model fits the common interface (the experiments keep u = 0).
    """

    state_names = ('x1', 'x2')
    input_names = ('u',)
    measurement_names = ('x1',)

    def __init__(self, mu: float = 0.005):
        self.mu = float(mu)
        if not np.isfinite(self.mu):
            raise ValueError(f'mu must be finite, got {mu!r}')
        self._b = np.array([[0.0], [1.0]])
        self._c = np.array([[1.0, 0.0]])  # Eq. 28

    def f(self, x, u):
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        x1, x2 = x[..., 0], x[..., 1]
        return np.stack([x2, self.mu * (1.0 - x1 * x1) * x2 - x1 + u[..., 0]], axis=-1)

    def jacobian(self, x, u):
        """Eq. 27."""
        x = np.asarray(x, dtype=float)
        x1, x2 = x[..., 0], x[..., 1]
        a = np.zeros(x.shape[:-1] + (2, 2))
        a[..., 0, 1] = 1.0
        a[..., 1, 0] = -(2.0 * self.mu * x1 * x2 + 1.0)
        a[..., 1, 1] = self.mu * (1.0 - x1 * x1)
        return a
