"""The approach from 5 km behind the target to contact (issue 39, parts 2-3), offline: hold
points at 5 km, 2 km, 250 m and 20 m on V-bar, each left on a go from the estimate and its
covariance, then a final approach in a 10 deg cone to contact (snn_estimator.plant.approach).
The loop steps the blocks simulate() steps (truth Plant, PositionSensor, an Estimator, the LQR),
with the guidance giving the LQR its setpoint, u = u_ff - K (x_hat - x_ref), and records the
safety figures of each run (docs/decisions.md, 55-57). With ``sensors='by_range'`` the filter
fuses relative GPS, a LIDAR and a docking camera, each present only inside its range, so the
navigation hands over by range as on HTV and ATV (docs/decisions.md, 72). With
``sensors='angles_far'`` a far camera measuring the line of sight alone replaces relative GPS,
and the guidance flies an out-of-plane hop at the 5 km hold that makes the range observable
before its go (docs/decisions.md, 73-75).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from snn_estimator import defaults as D
from snn_estimator.config import EstimatorConfig, sensor_boundary_layer
from snn_estimator.filters.estimators import make_estimator
from snn_estimator.measurements import make_model
from snn_estimator.measurements.position import RelativeGPS
from snn_estimator.measurements.stacked import Stacked
from snn_estimator.models import DEFAULT_ORBIT_RADIUS, DYNAMICS_MODELS, StateSpaceModel, relative_motion
from snn_estimator.plant.approach import (
    APPROACH_ELLIPSOID,
    KEEP_OUT_RADIUS,
    ApproachGuidance,
    Corridor,
    HoldPoint,
    Leg,
    ObservabilityManoeuvre,
    approach_control,
    at_port,
    port_contact,
)
from snn_estimator.plant.basilisk_truth import BasiliskPlant, BasiliskSettings, OrbitSettings
from snn_estimator.plant.control import lqr_gain
from snn_estimator.plant.sensors import FusedSensor, PositionSensor, design_noise, docking_sensors
from snn_estimator.plant.truth import Plant

#: The holds (docs/decisions.md, 55): 5 km (HTV's AI point), 2 km (the approach ellipsoid's
#: V-bar boundary), 250 m (ATV S3, HTV-4, Dragon: outside the 200 m keep-out sphere), 20 m
#: (ATV S4). Go bounds: hold error, position 3-sigma, speed, dwell, timeout.
HOLDS = (HoldPoint('5 km', 5000.0, 25.0, 10.0, 0.05, 300.0, 3000.0),
         HoldPoint('2 km', 2000.0, 10.0, 5.0, 0.05, 300.0, 3000.0),
         HoldPoint('250 m', 250.0, 1.0, 0.5, 0.01, 300.0, 3000.0),
         HoldPoint('20 m', 20.0, 0.2, 0.1, 0.005, 120.0, 3000.0))
#: Transfers between them: the setpoint's top speed, m/s, time constant, s, and floor speed, m/s.
LEGS = (Leg(1.0, 300.0, 0.02), Leg(0.5, 300.0, 0.02), Leg(0.1, 300.0, 0.01))
#: The final approach's speed along V-bar and the CAM's delta-v, m/s (docs/decisions.md, 55-57).
FINAL_SPEED, CAM_DELTA_V = 0.04, 0.4
#: LQR weights of the tracking loop (response ~ 200 s, Rc^(1/4) ~ 56 s time constant).
LQR_STATE_WEIGHT, LQR_INPUT_WEIGHT = 1.0, 1e7
#: Contact: closing speed (m/s) and lateral offset (m) the docking mechanism accepts (IDSS-class
#: 0.03-0.05 m/s closing, 0.1 m lateral: notes of issues 38-39, item 6).
CONTACT_SPEED, CONTACT_LATERAL = (0.03, 0.05), 0.1
#: The ``plant`` of :func:`approach_scenario` that is Basilisk's two-body integration with J2.
BASILISK_PLANT = 'basilisk'
#: Free drift for the passive-safety figure: two orbits (issue 39), sampled every 10 s.
DRIFT_ORBITS, DRIFT_STEP = 2.0, 10.0
#: What the filters measure with: Table 6's position sensor at every range, the sensors by
#: range (relative GPS, LIDAR, docking camera: :func:`by_range_sensors`), or the same with an
#: angles-only far camera instead of relative GPS (:func:`angles_far_sensors`).
SENSOR_SUITES = ('position', 'by_range', 'angles_far')
#: The far camera (docs/decisions.md, 73): line-of-sight noise, rad (1 sigma per angle), full
#: field-of-view cone, rad, and minimum range, m (closer, the target is resolved: no centroid).
FAR_CAMERA_NOISE, FAR_CAMERA_FIELD_OF_VIEW, FAR_CAMERA_MIN_RANGE = 2e-4, np.radians(18.0), 1000.0
#: The angles suite's start: the along-track (range) error's 1 sigma as a fraction of the
#: range, the hand-over from ground or radar tracking that a far camera cannot improve.
ANGLES_RANGE_UNCERTAINTY = 0.02
#: The observability hop at the 5 km hold (docs/decisions.md, 74): 200 m out of plane, 300 s
#: after arrival (the LQR has settled the start's error), for half an orbit.
ANGLES_HOP = ObservabilityManoeuvre(D.ANGLES_HOP_HOLD, D.ANGLES_HOP_SIZE, D.ANGLES_HOP_DELAY)
#: ``manoeuvre`` of :func:`approach_scenario` that takes the suite's own (ANGLES_HOP for angles_far).
SUITE_MANOEUVRE = 'suite'
#: Relative GPS, m: from 500 m out (HTV switched from relative GPS to its laser radar at 500 m;
#: docs/decisions.md, 72), R = Table 6's 1e-2 m^2 per axis (no flown figure: today's sensor).
RELATIVE_GPS_MIN_RANGE = 500.0
#: The LIDAR's R_hat is its R at 250 m, where it alone measures at a hold (defaults.DOCKING_LIDAR's
#: 100 m is the 360 s rendezvous'); the camera's at defaults.DOCKING_CAMERA's 10 m.
APPROACH_LIDAR_DESIGN_RANGE = 250.0
#: The close sensors' mounting on the chaser, [x, y, z, w]: identity, boresight along +V-bar at the
#: target ahead (the approach comes from behind).
APPROACH_SENSOR_MOUNTING = (0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class ApproachScenario:
    """The filters' ``model``, the ``truth`` model, the start, the step and the guidance's
    parts; ``max_duration`` s ends a run that has not ended otherwise."""

    model: StateSpaceModel
    truth: StateSpaceModel
    x0: np.ndarray
    dt: float
    max_duration: float
    process_noise: np.ndarray
    measurement_noise: np.ndarray
    estimator: EstimatorConfig
    holds: tuple = HOLDS
    legs: tuple = LEGS
    corridor: Corridor = field(default_factory=Corridor)
    final_speed: float = FINAL_SPEED
    cam_delta_v: float = CAM_DELTA_V
    lqr_weights: tuple = (LQR_STATE_WEIGHT, LQR_INPUT_WEIGHT)
    #: A fault: from ``disturbance[0]`` s on, the truth feels ``disturbance[1]`` m/s^2 (3,) that
    #: neither the filters nor the guidance know of (a stuck thruster); None: no fault.
    disturbance: tuple | None = None
    #: Basilisk truth (two-body with J2 by default) instead of the ``truth`` model, which then
    #: serves only the sensor's geometry and the passive-safety drift; None: the model truth.
    basilisk: BasiliskSettings | None = None
    #: A stacked measurement (:func:`by_range_sensors`) the loop measures with and the filters
    #: linearise; None: Table 6's position sensor (``measurement_noise``) at every range.
    sensor: Stacked | None = None
    #: The guidance's observability hop (plant.approach.ObservabilityManoeuvre); None: none.
    manoeuvre: ObservabilityManoeuvre | None = None

    def guidance(self) -> ApproachGuidance:
        return approach_guidance(self.model.mean_motion, self.holds, self.legs, self.corridor,
                                 self.final_speed, self.cam_delta_v, self.manoeuvre)


def approach_guidance(mean_motion: float, holds=HOLDS, legs=LEGS, corridor: Corridor | None = None,
                      final_speed: float = FINAL_SPEED, cam_delta_v: float = CAM_DELTA_V,
                      manoeuvre: ObservabilityManoeuvre | None = None) -> ApproachGuidance:
    """The approach's guidance for a target orbit of ``mean_motion`` rad/s: by default this
    module's holds, legs, corridor and speeds (what the controller node's guidance approach flies)."""
    return ApproachGuidance(holds, legs, corridor or Corridor(), mean_motion, final_speed=final_speed,
                            cam_delta_v=cam_delta_v, manoeuvre=manoeuvre)


def approach_scenario(dynamics_model: str = 'cw', plant: str = 'nonlinear_circular',
                      orbit_radius: float = DEFAULT_ORBIT_RADIUS, dt: float = 1.0,
                      max_duration: float = 30000.0, holds=HOLDS, legs=LEGS, disturbance=None,
                      sensors: str = 'position', manoeuvre=SUITE_MANOEUVRE,
                      range_uncertainty: float = ANGLES_RANGE_UNCERTAINTY, **estimator_changes) -> ApproachScenario:
    """5 km behind the target on V-bar to contact, measured by Table 6's position sensor (R =
    1e-2 m^2 per 1 s sample at every range), or with ``sensors='by_range'`` by the sensors of
    each range (:func:`by_range_sensors`; the spiking filters then code the deviation from the
    prediction, defaults.SENSOR_NETWORK, as on the other angle sensors), on a model truth
    (``plant``: cw or nonlinear_circular, two-body without J2), or on Basilisk's two-body
    integration with J2 (``plant`` basilisk: a 400 km orbit at 51.6 deg, thrust unlimited as on
    the model truth; the nonlinear_circular model is then the passive-safety drift's); the filters predict with
    ``dynamics_model``, the LQR is designed on its linearisation at the port (CW). The filters
    start dispersed about the truth as in the far-range scenario (defaults.FAR_RANGE_ESTIMATOR),
    at the first of ``holds`` (one of ``legs`` between two holds); ``disturbance``: see
    :class:`ApproachScenario`. With ``sensors='angles_far'`` (:func:`angles_far_sensors`) the
    start's along-track sigma is ``range_uncertainty`` times the range, and ``manoeuvre`` is
    the guidance's observability hop: SUITE_MANOEUVRE (ANGLES_HOP on that suite, none on the
    others), None, or a plant.approach.ObservabilityManoeuvre."""
    for name, value, choices in (('dynamics_model', dynamics_model, DYNAMICS_MODELS),
                                 ('plant', plant, DYNAMICS_MODELS + (BASILISK_PLANT,)),
                                 ('sensors', sensors, SENSOR_SUITES)):
        if value not in choices:
            raise ValueError(f"{name} must be one of {', '.join(choices)}; got {value!r}")
    basilisk = None
    if plant == BASILISK_PLANT:
        plant = 'nonlinear_circular'
        basilisk = BasiliskSettings(orbit=OrbitSettings(semi_major_axis=orbit_radius), thrust_limit=None)
    x0 = np.array([-holds[0].distance, 0.0, 0.0, 0.0, 0.0, 0.0])
    sensor, sensing = None, {}
    if sensors != 'position':
        sensor = by_range_sensors() if sensors == 'by_range' else angles_far_sensors()
        r_hat = by_range_noise(sensor)
        sensing = {'measurement_noise': r_hat, 'boundary_layer': sensor_boundary_layer(r_hat), **D.SENSOR_NETWORK}
    p0 = angles_initial_covariance(holds[0].distance, range_uncertainty)  # checks it on every suite
    if sensors == 'angles_far':
        sensing['initial_covariance'] = p0
    manoeuvre = _manoeuvre(manoeuvre, sensors, holds)
    config = EstimatorConfig().replace(**{**D.FAR_RANGE_ESTIMATOR, 'initial_state': tuple(x0),
                                          'dynamics_model': dynamics_model, **sensing, **estimator_changes})
    return ApproachScenario(
        model=relative_motion(dynamics_model, orbit_radius), truth=relative_motion(plant, orbit_radius), x0=x0,
        dt=dt, max_duration=max_duration, process_noise=D.RENDEZVOUS_PROCESS_NOISE * np.eye(6),
        measurement_noise=D.RENDEZVOUS_MEASUREMENT_NOISE * np.eye(3), estimator=config, holds=tuple(holds),
        legs=tuple(legs), disturbance=disturbance, sensor=sensor, basilisk=basilisk, manoeuvre=manoeuvre)


def _manoeuvre(manoeuvre, sensors: str, holds) -> ObservabilityManoeuvre | None:
    """The scenario's observability hop: SUITE_MANOEUVRE gives ANGLES_HOP on the angles suite
    when its hold is among ``holds`` (an approach started inside it has no 5 km hold to hop at),
    none otherwise; None, or an ObservabilityManoeuvre as given. Anything else is refused."""
    if isinstance(manoeuvre, str) and manoeuvre == SUITE_MANOEUVRE:
        flies_it = sensors == 'angles_far' and ANGLES_HOP.hold in {hold.name for hold in holds}
        return ANGLES_HOP if flies_it else None
    if manoeuvre is None or isinstance(manoeuvre, ObservabilityManoeuvre):
        return manoeuvre
    raise ValueError(f'manoeuvre must be {SUITE_MANOEUVRE!r} (the suite\'s own), None or a '
                     f'plant.approach.ObservabilityManoeuvre; got {manoeuvre!r}')


def angles_initial_covariance(distance: float, range_uncertainty: float) -> tuple:
    """P0's diagonal of the angles suite: the far-range scenario's (defaults.FAR_RANGE_ESTIMATOR)
    with the along-track variance raised to (``range_uncertainty`` ``distance``)^2, m^2, on V-bar
    the range (the larger of the two is kept)."""
    if not 0.0 < range_uncertainty < 1.0:
        raise ValueError(f'range_uncertainty is the start\'s range sigma as a fraction of the range, in (0, 1); '
                         f'got {range_uncertainty!r}')
    p0 = list(D.FAR_RANGE_ESTIMATOR['initial_covariance'])
    p0[0] = max(p0[0], (range_uncertainty * distance) ** 2)
    return tuple(p0)


def _truth(scenario: ApproachScenario, seeds: list[int]):
    """The truth plant of a batch of runs: the model's, or Basilisk's (scenario.basilisk)."""
    if scenario.basilisk is None:
        return Plant(scenario.truth, scenario.x0, scenario.process_noise, seeds)
    settings = scenario.basilisk
    return BasiliskPlant(scenario.x0, scenario.process_noise, seeds, dt=scenario.dt, orbit=settings.orbit,
                         chaser_mass=settings.chaser_mass, thrust_limit=settings.thrust_limit,
                         cache_dir=settings.cache_dir)


def by_range_sensors() -> Stacked:
    """Relative GPS from RELATIVE_GPS_MIN_RANGE out, the docking suite's LIDAR (1.8 m - 3 km) and
    docking camera (5 cm - 30 m, 30 deg field of view) on the chaser looking forward along +V-bar
    at the target ahead (identity mounting), stacked in that order: beyond 3 km relative GPS
    alone, then with the LIDAR, the LIDAR alone inside 500 m, with the camera inside 30 m, the
    camera alone inside 1.8 m."""
    gps = RelativeGPS(D.RENDEZVOUS_MEASUREMENT_NOISE * np.eye(3), min_range=RELATIVE_GPS_MIN_RANGE)
    lidar, camera = docking_sensors(field_of_view=True, mounting_rotation=APPROACH_SENSOR_MOUNTING)
    return Stacked([gps, lidar, camera])


def angles_far_sensors(noise: float = FAR_CAMERA_NOISE) -> Stacked:
    """:func:`by_range_sensors` with a far camera in place of relative GPS: line of sight
    (azimuth, elevation; ``noise`` rad 1 sigma each) from FAR_CAMERA_MIN_RANGE out, no maximum
    range, FAR_CAMERA_FIELD_OF_VIEW, on the chaser looking forward along +V-bar. Beyond 3 km the
    camera alone (the 5 km hold: angles only), with the LIDAR from 3 km to 1 km, the LIDAR alone
    to 30 m, then as :func:`by_range_sensors`."""
    camera = make_model('line_of_sight', (noise ** 2, noise ** 2), min_range=FAR_CAMERA_MIN_RANGE,
                        field_of_view=FAR_CAMERA_FIELD_OF_VIEW)
    lidar, docking_camera = docking_sensors(field_of_view=True, mounting_rotation=APPROACH_SENSOR_MOUNTING)
    return Stacked([camera, lidar, docking_camera])


def by_range_noise(sensor: Stacked) -> np.ndarray:
    """The filters' R_hat of :func:`by_range_sensors` or :func:`angles_far_sensors`:
    block-diagonal, the far sensor's R (relative GPS or the far camera), the LIDAR's R at
    APPROACH_LIDAR_DESIGN_RANGE, the camera's at its design range (Decision 46)."""
    far, lidar, camera = sensor.parts
    r_hat = np.zeros((sensor.dim, sensor.dim))
    blocks = (far.noise, design_noise(lidar, APPROACH_LIDAR_DESIGN_RANGE),
              design_noise(camera, D.DOCKING_CAMERA['design_range']))
    for part, block in zip(sensor.slices, blocks):
        r_hat[part, part] = block
    return r_hat


def free_drift_ranges(model: StateSpaceModel, x, duration: float, dt: float = DRIFT_STEP) -> np.ndarray:
    """Ranges (m) from the target along the noise-free free drift of ``model`` from ``x``, every
    ``dt`` s over ``duration`` s (the first sample is ``x``'s)."""
    x = np.asarray(x, dtype=float)
    ranges = [np.linalg.norm(x[:3])]
    for _ in range(int(round(duration / dt))):
        x = model.transition(x, np.zeros(model.n_input), dt, substeps=4)
        ranges.append(np.linalg.norm(x[:3]))
    return np.array(ranges)


def passive_safety(model: StateSpaceModel, x, keep_out: float = KEEP_OUT_RADIUS) -> dict:
    """Free drift from ``x`` for two orbits: its closest range (m), and whether it enters the
    keep-out sphere from outside (True when it starts outside and comes within ``keep_out``; from
    inside, when it leaves the sphere and comes back)."""
    ranges = free_drift_ranges(model, x, DRIFT_ORBITS * 2.0 * np.pi / model.mean_motion)
    outside = ranges > keep_out
    if outside[0]:
        enters = bool((~outside).any())
    else:
        first_out = np.argmax(outside) if outside.any() else len(ranges)
        enters = bool((~outside[first_out:]).any())
    return {'min_range': float(ranges.min()), 'enters_keep_out': enters}


def range_figures(x, x_hat, covariance) -> dict[str, float]:
    """The estimate's range error |r_hat - r| (m) against the truth ``x``, and its range 3-sigma
    (m): 3 sqrt(l^T P l) along the estimated line of sight l = p_hat / |p_hat| (what angles alone
    leave unknown; docs/decisions.md, 74)."""
    p_hat = np.asarray(x_hat, dtype=float)[:3]
    r_hat = float(np.linalg.norm(p_hat))
    line = p_hat / r_hat
    return {'range_error': abs(r_hat - float(np.linalg.norm(np.asarray(x)[:3]))),
            'range_three_sigma': 3.0 * float(np.sqrt(max(line @ np.asarray(covariance)[:3, :3] @ line, 0.0)))}


class _Safety:
    """The safety figures of one run, from its truth, control and guidance, step by step."""

    def __init__(self, scenario: ApproachScenario, guidance: ApproachGuidance):
        self.scenario, self.guidance = scenario, guidance
        #: The hold whose go allows entering the approach ellipsoid (None: the approach starts inside).
        self.ellipsoid_hold = max((i for i, h in enumerate(scenario.holds) if h.distance >= APPROACH_ELLIPSOID[0]),
                                  default=None)
        self.delta_v = 0.0
        self.corridor_violation_time = 0.0
        self.corridor_exit = None
        self.max_corridor_excess = 0.0
        self.keep_out_entry = self.ellipsoid_entry = None
        self.ellipsoid_depth_before_go = 0.0
        self.contact = None
        self.holds: list[dict] = []
        self.cam = None
        self.seen_decisions = 0

    def step(self, t: float, dt: float, x, x_hat, u, covariance) -> None:
        """After the step to ``t``: the truth ``x``, the estimate ``x_hat`` and its ``covariance``,
        the control ``u`` held."""
        g, s = self.guidance, self.scenario
        self.delta_v += float(np.linalg.norm(u)) * dt
        p = x[:3]
        corridor = s.corridor
        if corridor.applies(p) and p[0] < 0.0 and not corridor.contains(p):
            self.corridor_violation_time += dt
            self.corridor_exit = t if self.corridor_exit is None else self.corridor_exit
            self.max_corridor_excess = max(self.max_corridor_excess, corridor.lateral(p) - corridor.radius(p[0]))
        if self.keep_out_entry is None and np.linalg.norm(p) < KEEP_OUT_RADIUS:
            self.keep_out_entry = {'time': t, 'after_go': g.go_time(g.keep_out_hold) is not None}
        depth = 1.0 - np.sqrt(np.sum((p / np.array(APPROACH_ELLIPSOID)) ** 2))
        if depth > 0.0 and self.ellipsoid_hold is not None:
            if g.go_time(self.ellipsoid_hold) is None:
                self.ellipsoid_depth_before_go = max(self.ellipsoid_depth_before_go, depth * APPROACH_ELLIPSOID[0])
            elif self.ellipsoid_entry is None:
                self.ellipsoid_entry = t
        for decision in g.decisions[self.seen_decisions:]:
            self.holds.append({'hold': decision.hold.name, 'decision': decision.decision, 'time': t,
                               'estimate_error': float(np.linalg.norm(x_hat[:3] - p)),
                               'hold_error': float(np.linalg.norm(p - decision.hold.state[:3])),
                               **range_figures(x, x_hat, covariance),
                               **passive_safety(s.truth, x)})
        self.seen_decisions = len(g.decisions)
        if g.phase == 'abort' and self.cam is None:
            self.cam = {'time': t, 'delta_v': (np.asarray(u) * dt).tolist(), **passive_safety(s.truth, x)}
        if g.active and at_port(x):
            g.contact(t)
            self.contact = {'time': t, **port_contact(x)}

    def figures(self) -> dict:
        g, contact = self.guidance, self.contact
        success = (contact is not None and CONTACT_SPEED[0] <= contact['closing_speed'] <= CONTACT_SPEED[1]
                   and contact['lateral'] <= CONTACT_LATERAL and self.corridor_violation_time == 0.0
                   and (self.keep_out_entry or {}).get('after_go', True))
        return {'outcome': g.phase, 'success': bool(success), 'delta_v': self.delta_v,
                'corridor_violation_time': self.corridor_violation_time, 'corridor_exit': self.corridor_exit,
                'max_corridor_excess': self.max_corridor_excess, 'keep_out_entry': self.keep_out_entry,
                'ellipsoid_entry': self.ellipsoid_entry, 'ellipsoid_depth_before_go': self.ellipsoid_depth_before_go,
                'contact': contact, 'holds': self.holds, 'cam': self.cam,
                'events': [(e.time, e.name) for e in g.events]}


class _Trajectory:
    """Every run's time, truth, estimate and covariance at each step of the loop (fly_approach's
    ``record``)."""

    def __init__(self):
        self.rows = {'time': [], 'truth': [], 'estimate': [], 'covariance': []}

    def __bool__(self) -> bool:
        return True

    def keep(self, t: float, x, estimator) -> None:
        for key, value in (('time', t), ('truth', x.copy()), ('estimate', estimator.batch_x_hat.copy()),
                           ('covariance', estimator.batch_P.copy())):
            self.rows[key].append(value)

    def of_run(self, b: int) -> dict:
        return {'time': np.array(self.rows['time']),
                **{key: np.array([v[b] for v in self.rows[key]]) for key in ('truth', 'estimate', 'covariance')}}


def _nees(x, x_hat, covariance) -> np.ndarray:
    """(x - x_hat)^T P^-1 (x - x_hat) per run."""
    error = x - x_hat
    return np.einsum('bi,bi->b', error, np.linalg.solve(covariance, error[..., None])[..., 0])


def fly_approach(scenario: ApproachScenario, kind: str, runs: int = 1, seed: int = 0,
                 max_duration: float | None = None, record: bool = False) -> list[dict]:
    """Fly ``runs`` approaches (seeds seed..seed+runs-1, random streams as simulate()'s) with
    filter ``kind``; each run's safety figures (:class:`_Safety`), spikes, filter steps and mean
    NEES (6 states). A run ends at contact, abort or no-go; the loop when every run has ended or
    after ``max_duration`` s (default the scenario's). ``record``: each run also has 'trajectory',
    {'time' (k,), 'truth', 'estimate' (k, 6), 'covariance' (k, 6, 6)} at every step of the loop
    (the estimate at t before the measurement of t, as the ROS estimator publishes it)."""
    seeds = [seed + b for b in range(runs)]
    estimator = make_estimator(kind, scenario.estimator.replace(seed=seed), scenario.model, runs=runs, seeds=seeds,
                               measurement=scenario.sensor)
    if not estimator.has_covariance:
        raise ValueError(f'the approach decides its holds and its corridor on the covariance, and {kind} has none: '
                         'use a filter kind with a covariance (ekf, emsif, snn_ekf, snn_emsif, ...)')
    plant = _truth(scenario, seeds)
    sensing = _Sensing(scenario, seeds)
    gain = lqr_gain(scenario.model, scenario.lqr_weights[0] * np.eye(6), scenario.lqr_weights[1] * np.eye(3))
    guidance = [scenario.guidance() for _ in seeds]
    safety = [_Safety(scenario, g) for g in guidance]
    dt = scenario.dt
    steps = int(round((max_duration or scenario.max_duration) / dt))
    spikes = np.zeros(runs, dtype=np.int64)
    nees_sum, nees_steps = np.zeros(runs), np.zeros(runs, dtype=np.int64)
    k = 0
    trajectory = _Trajectory() if record else None
    while k < steps and any(g.active for g in guidance):
        x_hat, covariance, t = estimator.batch_x_hat.copy(), estimator.batch_P, k * dt
        if trajectory:
            trajectory.keep(t, plant.x, estimator)
        u = np.zeros((runs, 3))
        flying = np.array([g.active for g in guidance])
        for b, g in enumerate(guidance):
            u[b] = approach_control(g, gain, t, dt, x_hat[b], covariance[b])
        z, valid = sensing.measure(plant.x)
        estimator.step(z, u, dt, valid=valid)
        fault = scenario.disturbance
        plant.step(u if fault is None or t < fault[0] else u + np.asarray(fault[1], dtype=float), dt)
        if estimator.spiking:  # a run's spikes until it ends, whatever the others of its batch still fly
            spikes[flying] += estimator.batch_spikes[flying].sum(axis=1)
        k += 1
        flying_runs = np.flatnonzero(flying)
        nees_sum[flying_runs] += _nees(plant.x[flying_runs], estimator.batch_x_hat[flying_runs],
                                       estimator.batch_P[flying_runs])
        nees_steps[flying_runs] += 1
        for b in flying_runs:
            safety[b].step(k * dt, dt, plant.x[b], estimator.batch_x_hat[b], u[b], estimator.batch_P[b])
    if trajectory:
        trajectory.keep(k * dt, plant.x, estimator)
    flights = [{'seed': s, 'kind': kind, 'dynamics_model': scenario.estimator.dynamics_model,
                'spikes': int(spikes[b]) if estimator.spiking else None, 'steps': k,
                'nees': float(nees_sum[b] / max(nees_steps[b], 1)), 'sensor_samples': sensing.samples(b),
                **safety[b].figures()}
               for b, s in enumerate(seeds)]
    if trajectory:
        for b, flight in enumerate(flights):
            flight['trajectory'] = trajectory.of_run(b)
    return flights


class _Sensing:
    """The truth-side sensor of every run: Table 6's PositionSensor, or the stacked sensors'
    FusedSensor (each sensor NaN outside its range; seeds as simulate()'s)."""

    def __init__(self, scenario: ApproachScenario, seeds):
        if scenario.sensor is None:
            self.sensor = PositionSensor(scenario.truth, scenario.measurement_noise, seeds)
            self.fused = None
        else:
            self.sensor = self.fused = FusedSensor(scenario.sensor, seeds)

    def measure(self, x) -> tuple:
        """``(z, valid)``: the sample of every run (NaN for an absent sensor) and the runs some
        sensor measured (None: all, the position sensor)."""
        if self.fused is None:
            return self.sensor.measure(x), None
        sample = self.fused.measure(x)
        return sample.z, sample.valid

    def samples(self, run: int) -> dict | None:
        """Samples each stacked sensor gave ``run``, by sensor name (None: the position sensor)."""
        if self.fused is None:
            return None
        return {part.name: int(count[run]) for part, count in zip(self.fused.model.parts, self.fused.counts)}


#: How a run ends: contact, abort (CAM), no-go at a hold, or still flying at max_duration.
OUTCOMES = ('contact', 'abort', 'no_go', 'hold', 'transfer', 'final')


def _stats(values) -> dict | None:
    values = np.array([v for v in values if v is not None], dtype=float)
    if values.size == 0:
        return None
    return {'mean': float(values.mean()), 'min': float(values.min()), 'max': float(values.max()), 'n': int(values.size)}


def summarize(flights: list[dict], holds=HOLDS) -> dict:
    """The figures of a batch of runs (:func:`fly_approach`): counts by outcome, safety counts,
    delta-v, contact conditions, and at each hold's decision (its go, or the no-go that ended the
    run) the estimate's and the hold's errors."""
    contacts = [f['contact'] for f in flights if f['contact'] is not None]
    decided = {h.name: [d for f in flights for d in f['holds'] if d['hold'] == h.name] for h in holds}
    return {
        'runs': len(flights),
        'outcomes': {o: sum(f['outcome'] == o for f in flights) for o in OUTCOMES},
        'success': sum(f['success'] for f in flights),
        'corridor_violation_runs': sum(f['corridor_violation_time'] > 0.0 for f in flights),
        'max_corridor_excess': _stats(f['max_corridor_excess'] for f in flights),
        'abort_after_corridor_exit': _stats(f['cam']['time'] - f['corridor_exit'] for f in flights
                                            if f['cam'] is not None and f['corridor_exit'] is not None),
        'cam_drift_enters_keep_out': sum(f['cam']['enters_keep_out'] for f in flights if f['cam'] is not None),
        'cam_drift_min_range': _stats(f['cam']['min_range'] for f in flights if f['cam'] is not None),
        'keep_out_entry_before_go': sum(not (f['keep_out_entry'] or {}).get('after_go', True) for f in flights),
        'ellipsoid_depth_before_go': _stats(f['ellipsoid_depth_before_go'] for f in flights),
        'passive_safety_keep_out_entries': sum(d['enters_keep_out'] for f in flights for d in f['holds']),
        'delta_v': _stats(f['delta_v'] for f in flights),
        'closing_speed': _stats(c['closing_speed'] for c in contacts),
        'lateral_at_contact': _stats(c['lateral'] for c in contacts),
        'contact_time': _stats(c['time'] for c in contacts),
        'spikes': _stats(f['spikes'] for f in flights),
        'nees': _stats(f.get('nees') for f in flights),
        'holds': {name: {'go': sum(d['decision'] == 'go' for d in ds),
                         'estimate_error': _stats(d['estimate_error'] for d in ds),
                         'hold_error': _stats(d['hold_error'] for d in ds),
                         'range_error': _stats(d['range_error'] for d in ds),
                         'range_three_sigma': _stats(d['range_three_sigma'] for d in ds),
                         'drift_min_range': _stats(d['min_range'] for d in ds)}
                  for name, ds in decided.items()},
    }
