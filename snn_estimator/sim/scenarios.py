"""The scenarios: the paper's rendezvous (Sec. 3.2, Table 6) and Van der Pol (Sec. 3.1, Table 1),
and this package's: the far-range approach, the rendezvous on a LIDAR, a camera and LIDAR
handed over, angles-only navigation (docs/decisions.md).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from snn_estimator import defaults as D
from snn_estimator.config import EstimatorConfig, sensor_boundary_layer
from snn_estimator.models import (
    DEFAULT_ORBIT_RADIUS,
    DYNAMICS_MODELS,
    ClohessyWiltshire,
    StateSpaceModel,
    VanDerPol,
    relative_motion,
)


@dataclass(frozen=True)
class Scenario:
    """A complete experiment set-up."""

    name: str
    model: StateSpaceModel
    x0: np.ndarray
    dt: float
    duration: float
    process_noise: np.ndarray
    measurement_noise: np.ndarray
    estimator: EstimatorConfig
    #: LQR weights; None means open loop (u = 0).
    lqr_state_weight: np.ndarray | None = None
    lqr_input_weight: np.ndarray | None = None
    #: Length of the final window the tables average over, s.
    metric_window: float = 60.0
    #: Model of the truth when it differs from the filters' model (None: the same).
    truth_model: StateSpaceModel | None = None
    #: The state the LQR regulates to, u = -K (x_hat - setpoint) (None: the origin, docking).
    setpoint: np.ndarray | None = None
    #: Truth by Basilisk (basilisk_truth.BasiliskSettings) instead of the model (None: the model).
    basilisk: object | None = None
    #: How the truth reads Eq. 1's w: spectral_density (variance Q dt per step) | held_sample
    #: (w ~ N(0, Q) held over the step, variance ~ Q dt^2): blocks.TRUTH_NOISE_READINGS.
    truth_noise: str = 'spectral_density'
    #: The sensor (a snn_estimator.measurements model) the loop measures with and the filters
    #: linearise; None: the model's linear C with ``measurement_noise`` (Table 6's position).
    sensor: object | None = None
    #: Open loop (no LQR weights): the known control of each step, (steps, m_u) (None: u = 0).
    control_schedule: np.ndarray | None = None
    #: With a stacked ``sensor``: steps between two samples of each of its sensors (None: every step).
    sensor_periods: tuple | None = None

    @property
    def steps(self) -> int:
        return int(round(self.duration / self.dt))


PRESETS = ('default', 'as_published')


def _apply_preset(config: EstimatorConfig, preset: str, changes: dict) -> EstimatorConfig:
    """'as_published' runs the network literally as the paper's tables give it: no state
    scaling and forward-Euler steps; 'default' keeps this package's numerical choices."""
    if preset == 'as_published':
        config = config.replace(state_scale=None, discretization='euler')
    elif preset != 'default':
        raise ValueError(f"preset must be one of {', '.join(PRESETS)}; got {preset!r}")
    return config.replace(**changes)


def rendezvous_scenario(preset: str = 'default', cw_model: str = 'standard',
                        orbit_radius: float = DEFAULT_ORBIT_RADIUS, plant: str = 'cw', basilisk=None,
                        **estimator_changes) -> Scenario:
    """Sec. 3.2 / Table 6: CW rendezvous, 360 s at dt = 0.1 s, LQR in the loop.

    ``preset='as_published'`` keeps Table 6 literally in the network (decoder variance 1/15,
    no state scaling) and integrates by forward Euler; 'default' uses this package's choices.
    ``cw_model='as_published'`` gives the filters and the LQR design the matrix printed as
    Eq. 41 while the truth stays standard CW, to measure what the misprint costs.
    ``plant='basilisk'`` flies the truth with Basilisk (two-body gravity, J2, thrust limits:
    ``basilisk``, a BasiliskSettings; default: J2 on, circular orbit of ``orbit_radius``)
    while the filters keep the CW model.
    """
    config = _apply_preset(EstimatorConfig(), preset, estimator_changes)
    truth = ClohessyWiltshire(orbit_radius=orbit_radius)
    model = truth if cw_model == 'standard' else ClohessyWiltshire(orbit_radius=orbit_radius, form=cw_model)
    return Scenario(
        name='rendezvous', model=model, x0=np.array(D.RENDEZVOUS_X0), dt=D.RENDEZVOUS_TIME_STEP,
        duration=D.RENDEZVOUS_DURATION, process_noise=D.RENDEZVOUS_PROCESS_NOISE * np.eye(6),
        measurement_noise=D.RENDEZVOUS_MEASUREMENT_NOISE * np.eye(3), estimator=config,
        lqr_state_weight=D.LQR_STATE_WEIGHT * np.eye(6), lqr_input_weight=D.LQR_INPUT_WEIGHT * np.eye(3),
        metric_window=D.RENDEZVOUS_METRIC_WINDOW, truth_model=None if model is truth else truth,
        basilisk=_truth_settings(plant, basilisk, orbit_radius))


def _truth_settings(plant: str, basilisk, orbit_radius: float, model_truths=('cw',)):
    """None for a model truth (one of ``model_truths``); Basilisk settings (default: J2,
    circular orbit of orbit_radius)."""
    if plant in model_truths:
        return None
    if plant != 'basilisk':
        raise ValueError(f"plant must be one of {', '.join(model_truths)}, basilisk; got {plant!r}")
    from snn_estimator.plant.basilisk_truth import BasiliskSettings, OrbitSettings
    return basilisk or BasiliskSettings(orbit=OrbitSettings(semi_major_axis=orbit_radius))


def far_range_scenario(plant: str = 'basilisk', basilisk=None, orbit_radius: float = DEFAULT_ORBIT_RADIUS,
                       **estimator_changes) -> Scenario:
    """A V-bar approach from 5 km behind the target to a hold point 100 m behind it (where the
    paper's 100 m scenario begins), over about one orbit (not in the paper).

    Here the model the filters use is wrong in earnest: rectilinear CW against a curved orbit
    (a point 5 km back on the straight V-bar drifts ~70 m per orbit in truth), J2, and the
    thrust limit. 1 s steps (far-range navigation rates); the LQR weights of defaults.FAR_RANGE_*
    reach the hold point in about an orbit within the thrust limit. Measurements as in Table 6.
    The estimator's ``dynamics_model`` (schema) is the filters' model: cw, or nonlinear_circular
    (the nonlinear relative motion; the LQR is designed on its linearisation, CW). ``plant``:
    basilisk, or a model truth (cw, nonlinear_circular: two-body motion without J2).
    """
    config = EstimatorConfig().replace(**{**D.FAR_RANGE_ESTIMATOR, **estimator_changes})
    settings = _truth_settings(plant, basilisk, orbit_radius, model_truths=DYNAMICS_MODELS)
    dynamics_model = config.dynamics_model
    model = relative_motion(dynamics_model, orbit_radius)
    truth = None if settings is not None or plant == dynamics_model else relative_motion(plant, orbit_radius)
    return Scenario(
        name='far_range', model=model, x0=np.array(D.FAR_RANGE_X0), dt=D.FAR_RANGE_TIME_STEP,
        duration=D.FAR_RANGE_DURATION, process_noise=D.RENDEZVOUS_PROCESS_NOISE * np.eye(6),
        measurement_noise=D.RENDEZVOUS_MEASUREMENT_NOISE * np.eye(3), estimator=config,
        lqr_state_weight=D.FAR_RANGE_LQR_STATE_WEIGHT * np.eye(6),
        lqr_input_weight=D.FAR_RANGE_LQR_INPUT_WEIGHT * np.eye(3),
        metric_window=D.FAR_RANGE_METRIC_WINDOW, setpoint=np.array(D.FAR_RANGE_SETPOINT), truth_model=truth,
        basilisk=settings)


def sensor_rendezvous_scenario(sensor: str = 'range_azimuth_elevation', preset: str = 'default', noise=None,
                              sensor_options: dict | None = None,
                              boundary_layer_units: str = D.SENSOR_BOUNDARY_LAYER_UNITS,
                              **estimator_changes) -> Scenario:
    """Sec. 3.2 measured by ``sensor`` (a model of snn_estimator.measurements) instead of Table
    6's position (issue 22): noise R per sample ``noise`` (default defaults.SENSOR_NOISE), the
    sensor on the chaser looking back at the target (defaults.CLOSE_SENSOR_MOUNTING; no field of
    view, and the range limit defaults.CLOSE_SENSOR_MIN_RANGE, unless ``sensor_options`` sets
    them). The filters take the sensor's R as their R (times measurement_noise_scale) and Table
    6's delta per component in ``boundary_layer_units`` (config.sensor_boundary_layer: 'sigma',
    one sensor sigma, the default; 'variance', 10 R_jj; Decision 35), unless ``measurement_noise``
    or ``boundary_layer`` is given. The spiking filters
    code the deviation from the prediction in units of 1 mm and 0.01 mm/s (defaults.SENSOR_NETWORK;
    Decision 36) unless ``network_coding`` or ``state_scale`` is given or the preset is
    'as_published'."""
    from snn_estimator.measurements import make_model
    base = rendezvous_scenario(preset, **_sensor_network(preset, estimator_changes))
    options = {'mounting_rotation': D.CLOSE_SENSOR_MOUNTING, 'min_range': D.CLOSE_SENSOR_MIN_RANGE,
               **(sensor_options or {})}
    model = make_model(sensor, D.SENSOR_NOISE[sensor] if noise is None else noise, **options)
    config = base.estimator
    if 'measurement_noise' not in estimator_changes:
        config = config.replace(measurement_noise=model.noise)
    if 'boundary_layer' not in estimator_changes:  # Table 6's delta per component (Decision 35)
        config = config.replace(boundary_layer=sensor_boundary_layer(model.noise, boundary_layer_units))
    return replace(base, name=f'rendezvous_{sensor}', sensor=model, estimator=config,
                   measurement_noise=model.noise)


def _sensor_network(preset: str, estimator_changes: dict) -> dict:
    """``estimator_changes`` with the sensors' network (defaults.SENSOR_NETWORK) where it does not
    say otherwise; the 'as_published' preset keeps the paper's network."""
    if preset == 'as_published':
        return estimator_changes
    return {**D.SENSOR_NETWORK, **estimator_changes}


def handover_scenario(preset: str = 'default', lidar_max_range: float = D.HANDOVER_LIDAR_MAX_RANGE,
                      periods=D.HANDOVER_PERIODS, boundary_layer_units: str = D.SENSOR_BOUNDARY_LAYER_UNITS,
                      **estimator_changes) -> Scenario:
    """Sec. 3.2 flown on two sensors fused in one filter (issue 22; not in the paper): a camera
    (line_of_sight, every ``periods[0]`` steps) for the whole approach and a LIDAR
    (range_azimuth_elevation, every ``periods[1]`` steps) within ``lidar_max_range``; both on the
    chaser looking back at the target, no closer than defaults.CLOSE_SENSOR_MIN_RANGE. Far, the
    filter has the bearings only (the LQR's known burns make the range observable); once the
    LIDAR sees the target it hands over. R_hat = scale * blockdiag(R_camera, R_lidar), delta
    and the network as in :func:`sensor_rendezvous_scenario`."""
    from snn_estimator.measurements import make_model
    from snn_estimator.measurements.stacked import Stacked
    base = rendezvous_scenario(preset, **_sensor_network(preset, estimator_changes))
    geometry = {'mounting_rotation': D.CLOSE_SENSOR_MOUNTING, 'min_range': D.CLOSE_SENSOR_MIN_RANGE}
    camera = make_model('line_of_sight', D.SENSOR_NOISE['line_of_sight'], **geometry)
    lidar = make_model('range_azimuth_elevation', D.SENSOR_NOISE['range_azimuth_elevation'],
                       max_range=lidar_max_range, **geometry)
    model = Stacked([camera, lidar])
    config = base.estimator
    if 'measurement_noise' not in estimator_changes:
        config = config.replace(measurement_noise=model.noise)
    if 'boundary_layer' not in estimator_changes:
        config = config.replace(boundary_layer=sensor_boundary_layer(model.noise, boundary_layer_units))
    return replace(base, name='rendezvous_camera_lidar', sensor=model, estimator=config,
                   measurement_noise=model.noise, sensor_periods=tuple(periods))


def docking_scenario(preset: str = 'default', boundary_layer_units: str = D.SENSOR_BOUNDARY_LAYER_UNITS,
                     field_of_view: bool = False, **estimator_changes) -> Scenario:
    """Sec. 3.2 flown to contact on the docking suite (issue 38; not in the paper): a LIDAR as
    flown far and a docking camera close, fused in one filter (:func:`docking_sensors`; the
    sensors' ranges hand over), each at its own rate. R_hat = scale * blockdiag(R_lidar(100 m),
    R_camera(10 m)) (Decision 46); delta and the network as in :func:`sensor_rendezvous_scenario`.
    The camera's 30 deg field of view applies only with ``field_of_view``: the state has no
    attitude to point it, and Sec. 3.2's LQR path crosses the target's position (Decision 46)."""
    from snn_estimator.measurements.stacked import Stacked
    from snn_estimator.plant.sensors import design_noise, docking_sensors
    base = rendezvous_scenario(preset, **_sensor_network(preset, estimator_changes))
    lidar, camera = docking_sensors(field_of_view)
    model = Stacked([lidar, camera])
    r_hat = np.zeros((6, 6))
    r_hat[:3, :3] = design_noise(lidar, D.DOCKING_LIDAR['design_range'])
    r_hat[3:, 3:] = design_noise(camera, D.DOCKING_CAMERA['design_range'])
    config = base.estimator
    if 'measurement_noise' not in estimator_changes:
        config = config.replace(measurement_noise=r_hat)
    if 'boundary_layer' not in estimator_changes:
        config = config.replace(boundary_layer=sensor_boundary_layer(r_hat, boundary_layer_units))
    return replace(base, name='rendezvous_docking', sensor=model, estimator=config, measurement_noise=r_hat,
                   sensor_periods=(D.DOCKING_LIDAR['period_steps'], D.DOCKING_CAMERA['period_steps']))


def angles_only_scenario(maneuver: bool = False, noise=None, **estimator_changes) -> Scenario:
    """An angles-only far approach (issue 22; not in the paper): a camera (line_of_sight) on the
    chaser, 1 km behind the target and 50 m below its orbit, drifting toward it under free CW
    motion, open loop, 1 s samples for 3000 s (defaults.ANGLES_ONLY_*). The filters start 30 m
    off along the line of sight. Under free drift the bearings of x and of k x are the same for
    every k (linear dynamics, no input), so the range cannot be observed; ``maneuver`` adds a known
    radial burn (defaults.ANGLES_ONLY_MANEUVER), which breaks that scale symmetry."""
    from snn_estimator.measurements import make_model
    truth = ClohessyWiltshire()
    x0 = np.array(D.ANGLES_ONLY_X0, dtype=float)
    x0[3] = 1.5 * truth.mean_motion * x0[2]  # the drift of a lower orbit: no secular radial motion
    camera = make_model('line_of_sight', D.SENSOR_NOISE['line_of_sight'] if noise is None else noise)
    config = EstimatorConfig().replace(**{
        'initial_state': tuple(x0 + np.array(D.ANGLES_ONLY_INITIAL_ERROR)),
        'initial_covariance': D.ANGLES_ONLY_INITIAL_COVARIANCE, 'measurement_noise': camera.noise,
        'state_scale': (1.0, 1e-2, 1e-2, 1e-3, 1e-3, 1e-3), **estimator_changes})
    steps = int(round(D.ANGLES_ONLY_DURATION / D.ANGLES_ONLY_TIME_STEP))
    schedule = np.zeros((steps, 3))
    if maneuver:
        start, end, acceleration = D.ANGLES_ONLY_MANEUVER
        times = D.ANGLES_ONLY_TIME_STEP * np.arange(steps)
        schedule[(times >= start) & (times < end)] = acceleration
    return Scenario(
        name='angles_only' + ('_maneuver' if maneuver else ''), model=truth, x0=x0, dt=D.ANGLES_ONLY_TIME_STEP,
        duration=D.ANGLES_ONLY_DURATION, process_noise=D.RENDEZVOUS_PROCESS_NOISE * np.eye(6),
        measurement_noise=camera.noise, estimator=config, metric_window=D.ANGLES_ONLY_METRIC_WINDOW,
        sensor=camera, control_schedule=schedule)


def van_der_pol_scenario(preset: str = 'default', **estimator_changes) -> Scenario:
    """Sec. 3.1 / Table 1: Van der Pol, 20 s at dt = 0.01 s, open loop, x1 measured."""
    config = EstimatorConfig(
        neuron_count=100, leak_rate=0.5, boundary_layer=0.05, decoder_variance=0.25,
        process_noise=0.01 * np.eye(2), measurement_noise=0.1, process_noise_scale=1.0,
        measurement_noise_scale=1.0, initial_covariance=(0.01, 0.01), initial_state=(0.0, 0.0),
        state_scale=(0.01, 0.01))
    config = _apply_preset(config, preset, estimator_changes)
    return Scenario(
        name='van_der_pol', model=VanDerPol(mu=D.VAN_DER_POL_MU), x0=np.array(D.VAN_DER_POL_X0),
        dt=D.VAN_DER_POL_TIME_STEP, duration=D.VAN_DER_POL_DURATION, process_noise=0.01 * np.eye(2),
        measurement_noise=np.array([[0.1]]),
        estimator=config, metric_window=10.0)
