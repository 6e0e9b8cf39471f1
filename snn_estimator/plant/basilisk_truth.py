"""Basilisk truth plant: the chaser's motion relative to the target integrated by Basilisk.

A drop-in for :class:`snn_estimator.plant.truth.Plant` (same ``runs``, ``x``, ``time`` and
``step(u, dt)``) whose truth is not the CW model but two-body gravity, optionally with Earth's
J2, integrated by Basilisk (``bsk==2.12.1``, the ``basilisk`` extra). One Basilisk simulation
holds the uncontrolled target and one chaser per run; every spacecraft has its own integrator
(RK4, one step per task period), so run ``b`` of a batch equals a single run with seed
``seeds[b]`` bit for bit.

Frames and units (SI, angles in rad):

* State ``[x, y, z, vx, vy, vz]`` in the target's LVLH frame as the paper draws it (Fehse):
  x = h_hat x r_hat (V-bar, along-track), y = -h_hat (H-bar), z = -r_hat (R-bar, toward
  Earth), where r_hat, h_hat are the target's instantaneous radial and orbit-normal unit
  vectors. That is Basilisk's Hill frame (``orbitalMotion.rv2hill``: [r_hat, along-track,
  h_hat]) relabelled: x = y_hill, y = -z_hill, z = -x_hill. Velocities are taken relative to
  the rotating frame, with the frame's exact angular velocity: ``|h|/r^2`` about h_hat plus,
  under J2, ``r (a . h_hat)/|h|`` about r_hat (the orbit plane turns when gravity has a
  component normal to it; rv2hill leaves this term out, which under J2 would make the
  velocity differ from the time derivative of the position by up to ~8 mm/s at 5 km range).
  With J2 off the state equals rv2hill's to round-off.
* Eccentric orbits use the same instantaneous frame, which then rotates non-uniformly (the
  true anomaly rate); CW no longer describes the motion (Tschauner-Hempel would).
* ``u`` is the commanded specific force (m/s^2) in LVLH, held over the step. Basilisk holds
  an external force constant in the inertial frame over a step, so the force is applied
  along the LVLH axes of the middle of the step (the frame rotated by omega dt/2): the mean
  direction then agrees with an LVLH-held force to O((omega dt)^2) ~ 1e-9 instead of
  leaving a bias of omega dt/2 ~ 6e-5 rad (5 mm over 360 s at 1e-3 m/s^2 per axis).

Thrust saturation is per axis: the chaser is taken to hold an LVLH-aligned attitude with a
thruster pair on each axis (Fehse's usual layout), so each axis saturates on its own at
``thrust_limit / chaser_mass``. (A norm limit would model one gimballed engine, which does
not fit a 3-axis translation controller.) Propellant use is not modelled: the mass is fixed.

Process noise: a continuous white noise of spectral density Q, exactly as ``Plant`` adds it:
after each Basilisk step the LVLH state is perturbed by ``w ~ N(0, Q_d)``, Q_d from Van Loan
with the CW model of the same orbit (the perturbation is tiny, so the linear model is exact
enough for its covariance), drawn from ``default_rng([seed, 1])``; the chaser's inertial
state is rewritten accordingly. With the same seeds the noise equals ``Plant``'s.

Per-step cost, J2 on, dt = 0.1 s (process CPU time, min to median over repeats, on 2 cores
shared with other jobs; bsk 2.12.1): 1 chaser 0.10-0.15 ms, of which Basilisk's integration
is 20-30 us and the rest the SWIG state access and numpy frame conversion; 100 chasers
2.1-3.1 ms, of which Basilisk 1.1-1.7 ms (~10 us per spacecraft with translation-only
spacecraft; the 6-DOF hub costs ~1.5x that). Point-mass gravity saves ~10 %; process noise
adds ~20 us plus ~3 us per chaser (every chaser's state is written back).

Nothing here writes to ~/.cache: the plant imports only Basilisk's core modules (not
``SimulationBaseClass``, which loads matplotlib, nor the support-data fetcher, which uses
pooch). ``cache_dir`` / :func:`redirect_caches` point those caches elsewhere anyway for
processes that import more of Basilisk.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Sequence

import numba
import numpy as np

from snn_estimator.defaults import EARTH_EQUATORIAL_RADIUS, EARTH_J2, ORBIT_INCLINATION
from snn_estimator.models import DEFAULT_ORBIT_RADIUS, EARTH_MU, ClohessyWiltshire
from snn_estimator.validation import as_matrix, check_covariance, check_positive

from .truth import PLANT_STREAM, GaussianStream, matrix_sqrt

#: The Basilisk release this module is written against (its Python API moves between releases).
BASILISK_REQUIREMENT = 'bsk==2.12.1'


def _check_finite(value, name: str) -> float:
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f'{name} must be a finite number, got {value!r}')
    return number


@dataclass(frozen=True)
class OrbitSettings:
    """The target's orbit (osculating elements at t = 0) and Earth's gravity field.

    Defaults: a circular 400 km orbit (the package's CW radius) at the ISS's 51.6 deg
    inclination, J2 on. Angles in rad, lengths in m.
    """

    semi_major_axis: float = DEFAULT_ORBIT_RADIUS
    eccentricity: float = 0.0
    inclination: float = ORBIT_INCLINATION
    raan: float = 0.0
    argument_of_perigee: float = 0.0
    #: The target's true anomaly at t = 0 (0: at perigee).
    true_anomaly: float = 0.0
    mu: float = EARTH_MU
    j2: bool = True
    j2_coefficient: float = EARTH_J2
    equatorial_radius: float = EARTH_EQUATORIAL_RADIUS

    def __post_init__(self):
        def store(name, value):
            object.__setattr__(self, name, value)

        store('mu', check_positive(self.mu, 'mu (m^3/s^2)'))
        store('equatorial_radius', check_positive(self.equatorial_radius, 'equatorial_radius (m)'))
        store('semi_major_axis', check_positive(self.semi_major_axis, 'semi_major_axis (m)'))
        e = _check_finite(self.eccentricity, 'eccentricity')
        if not 0.0 <= e < 1.0:
            raise ValueError(f'eccentricity must be in [0, 1) (a closed orbit), got {e}')
        store('eccentricity', e)
        perigee = self.semi_major_axis * (1.0 - e)
        if perigee <= self.equatorial_radius:
            raise ValueError(
                f'semi_major_axis * (1 - eccentricity) = {perigee:.0f} m puts the perigee inside '
                f'the Earth (equatorial_radius {self.equatorial_radius:.0f} m): raise '
                'semi_major_axis (it is a radius in m, not an altitude) or lower eccentricity')
        inclination = _check_finite(self.inclination, 'inclination (rad)')
        if not 0.0 <= inclination <= math.pi:
            raise ValueError(f'inclination must be in [0, pi] rad, got {inclination} '
                             '(angles are in radians: use math.radians(degrees))')
        store('inclination', inclination)
        for name in ('raan', 'argument_of_perigee', 'true_anomaly'):
            store(name, _check_finite(getattr(self, name), f'{name} (rad)'))
        store('j2_coefficient', _check_finite(self.j2_coefficient, 'j2_coefficient'))
        store('j2', bool(self.j2))

    @property
    def mean_motion(self) -> float:
        """sqrt(mu / a^3), rad/s: the CW model's n for this orbit."""
        return math.sqrt(self.mu / self.semi_major_axis ** 3)


@dataclass(frozen=True)
class BasiliskSettings:
    """What a scenario with Basilisk truth needs besides its initial state and noise."""

    orbit: OrbitSettings = OrbitSettings()
    #: kg, and N per axis (None or 0: unlimited): 50 N at 500 kg is 0.1 m/s^2, above the paper
    #: scenario's peak LQR command (0.09 m/s^2), so only a far approach saturates.
    chaser_mass: float = 500.0
    thrust_limit: float | None = 50.0
    #: Where Basilisk / matplotlib / pooch may write caches (None: leave them alone).
    cache_dir: str | None = None


def redirect_caches(folder) -> dict[str, str]:
    """Send the caches Basilisk's utilities can write into ``folder`` instead of ~/.cache.

    Sets MPLCONFIGDIR (matplotlib, loaded by ``SimulationBaseClass``), XDG_CACHE_HOME (pooch
    and anything else following the XDG layout) and BSK_SUPPORT_DATA_CACHE (Basilisk's
    support-data fetcher) in this process's environment, creating the folders. These are
    read when those libraries are first imported, so call this before importing them.
    Returns the variables set.
    """
    root = Path(folder).expanduser().resolve()
    paths = {'MPLCONFIGDIR': root / 'matplotlib', 'XDG_CACHE_HOME': root / 'xdg',
             'BSK_SUPPORT_DATA_CACHE': root / 'bsk_support_data'}
    for name, path in paths.items():
        path.mkdir(parents=True, exist_ok=True)
        os.environ[name] = str(path)
    return {name: str(path) for name, path in paths.items()}


def _import_basilisk() -> SimpleNamespace:
    """The Basilisk modules the plant uses, imported on first use only."""
    try:
        from Basilisk.architecture import sim_model, sys_model_task
        from Basilisk.simulation import extForceTorque, gravityEffector, spacecraft
        from Basilisk.simulation.sphericalHarmonicsGravityModel import SphericalHarmonicsGravityModel
        from Basilisk.utilities import orbitalMotion
    except ImportError as error:
        raise ImportError(
            f'BasiliskPlant needs Basilisk: pip install {BASILISK_REQUIREMENT} '
            f"(or install this package with the 'basilisk' extra: pip install "
            f"'snn_rendezvous[basilisk]'); the import failed with: {error}") from error
    return SimpleNamespace(
        sim_model=sim_model, sys_model_task=sys_model_task, extForceTorque=extForceTorque,
        gravityEffector=gravityEffector, spacecraft=spacecraft, orbitalMotion=orbitalMotion,
        SphericalHarmonicsGravityModel=SphericalHarmonicsGravityModel)


@numba.njit(cache=True)
def _apply(matrix: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """``matrix @ v`` for every row ``v`` of ``vectors``.

    Summed in the same order for every row: a BLAS product may block differently for
    different batch sizes, and run b must not depend on how many runs share the batch.
    """
    out = np.zeros((vectors.shape[0], matrix.shape[0]))
    for b in range(vectors.shape[0]):
        for i in range(matrix.shape[0]):
            total = 0.0
            for j in range(matrix.shape[1]):
                total += matrix[i, j] * vectors[b, j]
            out[b, i] = total
    return out


_NO_GRAVITY = np.zeros(3)


@numba.njit(cache=True)
def _frame_matrices(target, gravity, j2, half_dt):
    """From the target's inertial state [r, v] (and, under J2, its gravity acceleration):
    the 6x6 taking an inertial relative state to LVLH, its inverse, and the 3x3 taking an
    LVLH vector to inertial along the LVLH axes rotated by omega half_dt (compiled: a ROS
    plant step is otherwise dominated by this bookkeeping on 3-vectors)."""
    r, v = target[:3], target[3:]
    h = np.cross(r, v)
    radius, h_norm = np.sqrt(r @ r), np.sqrt(h @ h)
    r_hat, h_hat = r / radius, h / h_norm
    # rows: the LVLH x (V-bar), y (H-bar) and z (R-bar) axes in inertial components
    axes = np.empty((3, 3))
    axes[0], axes[1], axes[2] = np.cross(h_hat, r_hat), -h_hat, -r_hat
    normal_rate = radius * (gravity @ h_hat) / h_norm if j2 else 0.0
    omega = np.array([0.0, -h_norm / radius ** 2, -normal_rate])  # LVLH components
    omega_cross = np.array([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]],
                            [-omega[1], omega[0], 0.0]])
    # rho = C dr, rho' = C dv - omega x rho; back: dr = C^T rho, dv = C^T (rho' + omega x rho)
    to_frame = np.zeros((6, 6))
    to_frame[:3, :3] = axes
    to_frame[3:, 3:] = axes
    to_frame[3:, :3] = -(omega_cross @ axes)
    from_frame = np.zeros((6, 6))
    from_frame[:3, :3] = axes.T
    from_frame[3:, 3:] = axes.T
    from_frame[3:, :3] = axes.T @ omega_cross
    # Rodrigues: rotation by the vector omega half_dt
    w = omega * half_dt
    angle = np.sqrt(w @ w)
    rotation = np.eye(3)
    if angle > 0.0:
        x, y, z = w / angle
        s, c = np.sin(angle), np.cos(angle)
        t = 2.0 * np.sin(0.5 * angle) ** 2  # 1 - cos(angle) without cancellation
        rotation = np.array([[c + x * x * t, x * y * t - z * s, x * z * t + y * s],
                             [y * x * t + z * s, c + y * y * t, y * z * t - x * s],
                             [z * x * t - y * s, z * y * t + x * s, c + z * z * t]])
    return to_frame, from_frame, axes.T @ rotation


@numba.njit(cache=True)
def _forces_of(command, limit, mid_step_axes, mass, previous):
    """The step's command clipped per axis at ``limit`` (inf: no limit), which runs were
    clipped, the inertial forces along the mid-step LVLH axes and which runs' force changed
    (one compiled call: in a ROS plant, between DDS callbacks, numpy's per-call overhead on
    3-vectors was most of the step)."""
    applied = np.minimum(np.maximum(command, -limit), limit)
    saturated = np.zeros(command.shape[0], dtype=np.int64)
    for b in range(command.shape[0]):
        for i in range(3):
            if applied[b, i] != command[b, i]:
                saturated[b] = 1
    forces = mass * _apply(mid_step_axes, applied)
    changed = np.zeros(command.shape[0], dtype=np.bool_)
    for b in range(command.shape[0]):
        for i in range(3):
            if forces[b, i] != previous[b, i]:
                changed[b] = True
    return applied, saturated, forces, changed


@numba.njit(cache=True)
def _after_step(states, gravity, j2, half_dt, noisy, noise_root, draw):
    """From the inertial states after a step (target first): the chasers' LVLH states (plus
    process noise when ``noisy``), the noisy states back in inertial components, and the
    frame matrices of :func:`_frame_matrices` for the new target state."""
    target = states[0]
    to_frame, from_frame, mid_step_axes = _frame_matrices(target, gravity, j2, half_dt)
    x = _apply(to_frame, states[1:] - target)
    inertial = states[1:]
    if noisy:
        x = x + _apply(noise_root, draw)
        inertial = target + _apply(from_frame, x)
    return x, inertial, to_frame, from_frame, mid_step_axes


class BasiliskPlant:
    """Truth propagation by Basilisk for a batch of chasers about one target.

    ``x0``: initial LVLH state, shape (6,) for every run or (runs, 6). ``process_noise``: Q
    (6x6, 36 numbers row-major, 6 diagonal entries or a scalar), as for ``Plant``. ``seeds``:
    one per run; run b draws from ``default_rng([seeds[b], 1])``. ``dt``: the Basilisk task
    period, s; ``step`` accepts only this step. ``orbit``: :class:`OrbitSettings`.
    ``chaser_mass`` in kg; ``thrust_limit`` in N per axis (None or 0: unlimited).
    ``cache_dir``: if given, :func:`redirect_caches` to it before Basilisk is imported.

    After each step: ``x`` (runs, 6), ``time`` (s), ``applied`` (runs, 3) the clipped specific
    force of the last step, ``saturated_steps`` (runs,) how many steps were clipped;
    ``target_state`` and ``chaser_states`` give the inertial states. ``model`` is the CW model
    of the same orbit (n = sqrt(mu / a^3)), which discretises Q as in ``Plant``.
    """

    def __init__(self, x0, process_noise=0.0, seeds: Sequence[int] = (0,), *, dt: float = 0.1,
                 orbit: OrbitSettings | None = None, chaser_mass: float = 500.0,
                 thrust_limit: float | None = None, cache_dir=None):
        self.orbit = OrbitSettings() if orbit is None else orbit
        if not isinstance(self.orbit, OrbitSettings):
            raise TypeError(f'orbit must be an OrbitSettings, got {type(orbit).__name__}')
        seeds = [int(seed) for seed in seeds]
        if not seeds:
            raise ValueError('seeds must hold one seed per run (at least one)')
        self.runs = len(seeds)
        self.dt, self._rate_ns = self._task_rate(dt)
        self.chaser_mass = check_positive(chaser_mass, 'chaser_mass (kg)')
        limit = 0.0 if thrust_limit is None else check_positive(
            thrust_limit, 'thrust_limit (N per axis; 0 or None: unlimited)', strict=False)
        self.thrust_limit = limit or None
        x0 = self._initial_states(x0)
        self.model = ClohessyWiltshire(orbit_radius=self.orbit.semi_major_axis, mu=self.orbit.mu)
        self.q = check_covariance(as_matrix(process_noise, (6, 6), 'process_noise (Q)'),
                                  'process_noise (Q)', allow_singular=True)
        self._noise = None
        self._noise_root, self._no_draw = np.zeros((6, 6)), np.zeros((self.runs, 6))
        if np.any(self.q):
            self._noise = GaussianStream(seeds, PLANT_STREAM, 6)
            self._noise_root = matrix_sqrt(self.model.process_noise_discrete(self.q, self.dt))
        if cache_dir is not None:
            redirect_caches(cache_dir)
        self._build(_import_basilisk())
        self._write_chasers(x0)
        self.x = x0
        self.time = 0.0
        self.applied = np.zeros((self.runs, 3))
        self.saturated_steps = np.zeros(self.runs, dtype=np.int64)
        self._compile_step()

    def _compile_step(self) -> None:
        """Compile the step's kernels for this plant's argument types (or load them from
        numba's cache), changing nothing: the first step of a ROS plant is then not seconds
        long. The noise draw is a view like GaussianStream's rows."""
        _forces_of(np.zeros((self.runs, 3)), self.acceleration_limit, self._mid_step_axes, self.chaser_mass,
                   self._forces)
        states = self._read()
        draw = np.zeros((self.runs, 2, 6))[:, 0, :] if self._noise is not None else self._no_draw
        _after_step(states, self._gravity(states[0]), self.orbit.j2, 0.5 * self.dt, self._noise is not None,
                    self._noise_root, draw)

    @property
    def acceleration_limit(self) -> float:
        """Largest specific force per axis, m/s^2 (inf when unlimited)."""
        return math.inf if self.thrust_limit is None else self.thrust_limit / self.chaser_mass

    @property
    def target_state(self) -> np.ndarray:
        """The target's inertial (ECI) position and velocity, (6,), m and m/s."""
        return self._target.copy()

    @property
    def chaser_states(self) -> np.ndarray:
        """Every chaser's inertial position and velocity, (runs, 6), m and m/s."""
        return self._read()[1:]

    def step(self, u, dt: float) -> np.ndarray:
        """Advance by ``dt`` (the task period) with the specific force ``u`` (m/s^2, LVLH,
        shape (3,) or (runs, 3)) held; returns x, shape (runs, 6)."""
        self._check_step(dt)
        self.applied, saturated, forces, changed = _forces_of(
            self._command(u), self.acceleration_limit, self._mid_step_axes, self.chaser_mass, self._forces)
        self.saturated_steps += saturated
        for b in np.flatnonzero(changed):
            self._effectors[b].extForce_N = forces[b]
        self._forces = forces
        self._sim.SingleStepProcesses()
        states = self._read()
        noisy = self._noise is not None
        x, inertial, self._to_frame, self._from_frame, self._mid_step_axes = _after_step(
            states, self._gravity(states[0]), self.orbit.j2, 0.5 * self.dt, noisy,
            self._noise_root, self._noise.draw() if noisy else self._no_draw)
        self._target = states[0]
        if noisy:
            self._set_chaser_states(inertial)
        self.x = x
        self.time = self._sim.CurrentNanos * 1e-9
        return x

    # -- set-up -------------------------------------------------------------------------------

    @staticmethod
    def _task_rate(dt) -> tuple[float, int]:
        dt = float(dt)
        if not 0.0 < dt < math.inf:
            raise ValueError(f'dt must be a finite positive number of seconds, got {dt!r}')
        nanos = round(dt * 1e9)
        if abs(dt * 1e9 - nanos) > 1e-3:
            raise ValueError(f'dt must be a whole number of nanoseconds (Basilisk counts time '
                             f'in ns), got {dt!r} s')
        return nanos * 1e-9, nanos

    def _initial_states(self, x0) -> np.ndarray:
        x0 = np.array(x0, dtype=float, ndmin=2)
        if x0.shape == (1, 6):
            x0 = np.repeat(x0, self.runs, axis=0)
        if x0.shape != (self.runs, 6):
            raise ValueError(f'x0 must have 6 entries (every run) or shape (runs, 6) = '
                             f'({self.runs}, 6), got shape {x0.shape}')
        if not np.all(np.isfinite(x0)):
            raise ValueError('x0 must be finite')
        return x0

    def _gravity_body(self, bsk):
        body = bsk.gravityEffector.GravBodyData()
        body.planetName = 'earth'
        body.isCentralBody = True
        body.mu = self.orbit.mu
        body.radEquator = self.orbit.equatorial_radius
        if self.orbit.j2:
            # Coefficients set here, never loaded from a file (Basilisk's factory would fetch
            # one over the network). Basilisk takes fully normalised coefficients,
            # C20_bar = -J2 / sqrt(5); the degree-0 term mu/r^2 is added by the model itself.
            # Without a planet-orientation message the Earth frame is the inertial frame:
            # right for a zonal field, which only depends on latitude.
            field = bsk.SphericalHarmonicsGravityModel()
            c20 = -self.orbit.j2_coefficient / math.sqrt(5.0)
            field.cBar = [[1.0], [0.0, 0.0], [c20, 0.0, 0.0]]
            field.sBar = [[0.0], [0.0, 0.0], [0.0, 0.0, 0.0]]
            field.maxDeg = 2
            body.gravityModel = field
        return body

    def _build(self, bsk) -> None:
        orbit = self.orbit
        elements = bsk.orbitalMotion.ClassicElements()
        elements.a, elements.e = orbit.semi_major_axis, orbit.eccentricity
        elements.i, elements.Omega = orbit.inclination, orbit.raan
        elements.omega, elements.f = orbit.argument_of_perigee, orbit.true_anomaly
        r_target, v_target = bsk.orbitalMotion.elem2rv(orbit.mu, elements)

        self._sim = bsk.sim_model.SimModel()
        # SimulationBaseClass would do this wiring but imports matplotlib; the core API is enough.
        self._process = bsk.sim_model.SysProcess('truth')
        self._task = bsk.sys_model_task.SysModelTask(self._rate_ns, 0)
        self._process.addNewTask(self._task, -1)
        self._sim.addNewProcess(self._process)
        self._earth = self._gravity_body(bsk)
        self._spacecraft, self._effectors, self._states = [], [], []
        for k in range(self.runs + 1):
            craft = bsk.spacecraft.Spacecraft()
            craft.ModelTag = 'target' if k == 0 else f'chaser{k - 1}'
            # Translation only: no attitude is simulated (~1.5x faster, the same trajectory).
            craft.pointMassTranslationalOnly = True
            craft.hub.mHub = self.chaser_mass  # the target's too: only gravity acts on it
            # Chasers start on the target and are moved to x0 once the simulation is
            # initialised: the frame's rotation rate needs the gravity model's field.
            craft.hub.r_CN_NInit = list(r_target)
            craft.hub.v_CN_NInit = list(v_target)
            craft.gravField.gravBodies = bsk.spacecraft.GravBodyVector([self._earth])
            self._task.AddNewObject(craft, -1)
            if k:
                effector = bsk.extForceTorque.ExtForceTorque()
                effector.ModelTag = f'thrust{k - 1}'
                craft.addDynamicEffector(effector)  # read in the integration; needs no task slot
                self._effectors.append(effector)
            self._spacecraft.append(craft)
        self._sim.assignRemainingProcs()
        self._sim.ResetSimulation()
        self._sim.selfInitSimulation()
        self._sim.resetInitSimulation()
        # Basilisk's first task call runs at t = 0 and integrates nothing; afterwards each call
        # integrates one task period, with the forces set before it.
        self._sim.SingleStepProcesses()
        for craft in self._spacecraft:
            self._states.append(craft.dynManager.getStateObject(craft.hub.nameOfHubPosition))
            self._states.append(craft.dynManager.getStateObject(craft.hub.nameOfHubVelocity))
        self._forces = np.zeros((self.runs, 3))
        self._set_frame(self._read()[0])

    # -- per step -----------------------------------------------------------------------------

    def _check_step(self, dt) -> None:
        step = float(dt)
        if not (math.isfinite(step) and round(step * 1e9) == self._rate_ns):
            raise ValueError(
                f'dt = {dt!r} s, but this BasiliskPlant steps its Basilisk task every '
                f'{self.dt!r} s; build it with dt={dt!r} to use that step')

    def _command(self, u) -> np.ndarray:
        u = np.array(u, dtype=float)  # a copy: ``applied`` must not alias the caller's array
        if u.shape not in ((3,), (self.runs, 3)):
            raise ValueError(f'u must have shape (3,) or (runs, 3) = ({self.runs}, 3), '
                             f'got {u.shape}')
        if not np.isfinite(u).all():
            raise ValueError('u must be finite (a NaN or inf command would corrupt the truth)')
        return u if u.ndim == 2 else np.tile(u, (self.runs, 1))

    def _read(self) -> np.ndarray:
        """Inertial [r, v] of the target (row 0) and the chasers, (runs + 1, 6)."""
        values = [value for state in self._states for (value,) in state.getState()]
        return np.array(values).reshape(self.runs + 1, 6)

    def _set_frame(self, target: np.ndarray) -> None:
        """From the target's inertial state: ``_to_frame`` (6x6) taking an inertial relative
        state to LVLH, its inverse ``_from_frame``, and ``_mid_step_axes`` (3x3) taking an LVLH
        vector to inertial along the LVLH axes of the next step's middle."""
        self._to_frame, self._from_frame, self._mid_step_axes = _frame_matrices(
            target, self._gravity(target), self.orbit.j2, 0.5 * self.dt)
        self._target = target

    def _gravity(self, target: np.ndarray) -> np.ndarray:
        """The field's acceleration at the target (J2 only: point-mass gravity is radial and
        cannot turn the orbit plane)."""
        if not self.orbit.j2:
            return _NO_GRAVITY
        return np.array(self._earth.computeGravityInertial(target[:3].tolist(), self._sim.CurrentNanos),
                        dtype=float).reshape(3)

    def _write_chasers(self, x: np.ndarray) -> None:
        """Set every chaser's inertial state to the LVLH state ``x``."""
        self._set_chaser_states(self._target + _apply(self._from_frame, x))

    def _set_chaser_states(self, states: np.ndarray) -> None:
        """Set every chaser's inertial [r, v], (runs, 6)."""
        for b in range(self.runs):
            self._states[2 * b + 2].setState(states[b, :3])
            self._states[2 * b + 3].setState(states[b, 3:])



def warm_up() -> None:
    """Fill numba's cache with the step kernels for the plants the package builds (one run
    and a batch, with and without process noise); ``make`` calls this at install."""
    for runs, noise in ((1, 1e-12), (2, 1e-12), (1, 0.0)):
        BasiliskPlant(np.zeros(6), noise * np.eye(6), seeds=list(range(runs)), dt=0.1)


__all__ = ['BASILISK_REQUIREMENT', 'BasiliskPlant', 'EARTH_EQUATORIAL_RADIUS', 'EARTH_J2',
           'OrbitSettings', 'redirect_caches', 'warm_up']
