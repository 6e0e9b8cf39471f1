"""Every node parameter, declared once: name, default, unit/meaning, range, read-only. Pure data.

These tables are the one source of the parameters: the nodes declare them
(:mod:`scenario_nodes.ros_parameters`, with their ParameterDescriptors), the YAML files in
config/ and docs/parameters.md are generated from them (``python -m snn_tools.run.parameter_files
--write``; a test keeps them in step), and their defaults come from the core's
:mod:`snn_estimator.defaults` and :mod:`snn_estimator.schema`. Matrices are flat row-major lists
(1 value = scalar times identity, n values = diagonal, n*n values = full).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from snn_estimator import defaults as D
from snn_estimator import schema
from snn_estimator.catalog import DEFAULT_FILTER, FILTER_KINDS, MEASUREMENT_TIMINGS, START_MODES
from snn_estimator.config import EstimatorConfig, sensor_boundary_layer
from snn_estimator.measurements import MODELS as MEASUREMENT_MODELS
from snn_estimator.measurements import OBSERVERS
from snn_estimator.models import DYNAMICS_MODELS
from snn_estimator.plant.sensors import FUSED_SEED_OFFSET, design_noise, docking_sensors

from . import registry
from .topics import GUIDANCE, MEASUREMENT, PIPELINE_TOPICS

#: The controller's guidance choices (parameter ``guidance``).
GUIDANCE_MODES = ('none', 'approach')
#: The approach guidance's observability manoeuvres (parameter ``observability_manoeuvre``):
#: none, or the core's out-of-plane hop (snn_estimator.plant.approach.OutOfPlaneHop).
OUT_OF_PLANE_HOP = 'out_of_plane_hop'
OBSERVABILITY_MANOEUVRES = ('none', OUT_OF_PLANE_HOP)
#: Parameter kinds for arrays without a default (rclpy cannot infer them from None).
DOUBLE_ARRAY, INTEGER_ARRAY, STRING_ARRAY = 'double_array', 'integer_array', 'string_array'


@dataclass(frozen=True)
class Spec:
    """One parameter. ``default`` None means an array with no default (``kind`` gives its type)."""

    name: str
    default: Any
    description: str
    read_only: bool = True
    low: float | None = None
    high: float | None = None
    choices: Sequence[str] = ()
    kind: str | None = None


def _floats(values) -> list:
    return [float(v) for v in np.ravel(values)]


MODEL = (
    Spec('time_step', D.RENDEZVOUS_TIME_STEP, 'Sample period of truth, measurement and estimator, s '
         '(Sec. 3.2: 0.1)', low=1e-6, high=3600.0),
    Spec('orbit_radius', D.ORBIT_RADIUS, 'Target orbit radius R_o, m; mean motion n = sqrt(mu/R_o^3) '
         '(Eq. 39). Not stated in the paper: 400 km LEO', low=1.0),
    Spec('gravitational_parameter', D.EARTH_MU, "Earth's mu, m^3/s^2 (Table 6: 398600 km^3/s^2)", low=1.0),
    Spec('frame_id', 'lvlh', "Frame of states and measurements: the target's LVLH frame (x "
         'along-track, y opposite the orbit normal, z radial toward Earth)'),
    Spec('child_frame_id', 'chaser', 'child_frame_id of the state messages'),
    Spec('diagnostics_period', 1.0, 'Simulated s between diagnostics messages (0: every step)', low=0.0),
    Spec('peer_timeout', 2.0, 'Wall-clock s without an input (truth, measurement, estimate, control, '
         'the clock) after which its publisher counts as gone: logged once, diagnostics WARN (ERROR '
         'after 5x), cleared when it comes back', low=1e-3),
    Spec('control_validity', 0.5, 'Simulated s a control stays in force after its stamp when no newer '
         'one came: then the plant applies zero thrust and the estimator predicts with zero thrust '
         '(the same rule, so both agree on what was applied; default: the controller\'s estimate_timeout)',
         low=1e-6),
)

_PLANT = MODEL + (
    Spec('initial_state', _floats(D.RENDEZVOUS_X0), 'x0 = [x, y, z, vx, vy, vz], m and m/s (Table 6)'),
    Spec('process_noise', [D.RENDEZVOUS_PROCESS_NOISE],
         'Q, process-noise spectral density of the truth, (m/s^2)^2/Hz (Table 6: 1e-12 I6)'),
    Spec('seed', 0, 'Seed of the process noise (stream 1 of the seed; README, "Time and seeds")', low=0),
    Spec('mode', 'lockstep', 'lockstep: step k+1 only after the control for step k arrived; '
         'realtime: step on a wall-clock timer', choices=('lockstep', 'realtime')),
    Spec('duration', D.RENDEZVOUS_DURATION, 'Simulated time to run, s (0: run until stopped)', low=0.0),
    Spec('real_time_factor', 1.0, 'realtime mode: simulated seconds per wall-clock second',
         low=1e-3, high=1e6),
    Spec('control_timeout', 1.0, 'lockstep: wall-clock s to wait for the control of a step before '
         'stepping with the control in force (the last one until control_validity, then zero thrust; '
         'counted as a control timeout)', low=1e-3),
    Spec('resend_period', 0.25, 'lockstep: wall-clock s without the control of a step after which '
         'the state is sent again (each node answers a repeated input again: a sample lost on a '
         'best-effort link does not stall the loop)', low=1e-3),
    Spec('start_time', 0.0, 'Simulated time of the first sample, s (below 2^31 s: a ROS time stamp '
         'counts whole seconds in an int32)', low=0.0, high=2.0 ** 31 - 3600.0),
    Spec('publish_clock', True, 'Publish /clock (the plant owns simulated time)'),
    Spec('wait_for_loop', True, "Start the scenario (publish x0, start the clock) only once the loop "
         "is there: 'truth' matched by min_truth_subscribers subscriptions, and 'measurement', "
         "'estimate' and 'control' each with a publisher and a subscriber; says what it waits for"),
    Spec('min_truth_subscribers', 1, "Subscriptions 'truth' needs before the start (the sensor; the "
         'demo: 2 with the recorder)', low=0),
    Spec('measurement_topics', [MEASUREMENT], "The sensors' topics the loop check looks for (a sensor "
         'publishing one, an estimator subscribing to every one): an estimator with `sensors`'),
    Spec('start_delay', 0.3, 'Wall-clock s to wait once the loop is there, so that every pair of '
         'endpoints has matched before the first sample', low=0.0),
    Spec('exit_when_done', False, 'Exit the process after the last step (the demo and a lockstep '
         'launch: the launch then ends)'),
    Spec('paused', False, 'Hold simulated time (no steps, no /clock) until set false again',
         read_only=False),
    Spec('stop_at_port', False, "End the run once the truth reaches the docking port's plane (x >= 0 "
         'along V-bar: contact in the approach; docs/decisions.md, 67), logging the closing speed and '
         'the lateral offset there'),
    Spec('end_on_guidance', False, "End the run after the step in which the controller's approach "
         "guidance ended without contact (an abort or a no-go on `guidance`; docs/decisions.md, 67)"),
)

PLANT = _PLANT + (
    Spec('dynamics_model', 'cw', 'The truth: cw (Clohessy-Wiltshire, exact transition), '
         'nonlinear_circular (the nonlinear relative motion about a circular orbit, RK4) or ss_j2 '
         '(Schweighart-Sedwick linear J2 model at 51.6 deg, exact transition; snn_estimator.models)',
         choices=DYNAMICS_MODELS),
)

BASILISK_PLANT = _PLANT + (
    Spec('eccentricity', 0.0, "Target orbit's eccentricity (orbit_radius is its semi-major axis; the "
         'target starts at the true anomaly below)', low=0.0, high=0.9),
    Spec('inclination', 51.6, "Target orbit's inclination, deg (ISS-like)", low=0.0, high=180.0),
    Spec('raan', 0.0, 'Right ascension of the ascending node, deg', low=-360.0, high=360.0),
    Spec('argument_of_perigee', 0.0, 'Argument of perigee, deg', low=-360.0, high=360.0),
    Spec('true_anomaly', 0.0, "The target's true anomaly at the start, deg", low=-360.0, high=360.0),
    Spec('j2', True, "Earth's J2 in the gravity field (coefficient 1.08262668e-3, set directly: "
         'nothing is downloaded)'),
    Spec('chaser_mass', 500.0, 'Chaser mass, kg', low=1e-3),
    Spec('thrust_limit', 50.0, 'Thrust limit per LVLH axis, N (0: unlimited); a clipped command is '
         'counted (saturated_steps) and logged', low=0.0),
    Spec('cache_dir', '', 'Folder for the caches Basilisk, matplotlib and pooch may write (empty: '
         'their defaults under ~/.cache)'),
)


def _match_hold(count: str, publisher: str, input_: str, why: str, demo: str, note: str = '') -> tuple:
    """The two parameters of a node that subscribes to its input only once its output's publisher
    matched enough subscriptions (runtime.MatchHold; docs/decisions.md, 33 and 41)."""
    return (
        Spec(count, 0, f'Subscriptions the {publisher} publisher must have matched{note} before the node '
             f"subscribes to {input_} ({why}). DDS may match a subscriber's end first, and what the "
             'publisher sends before its end matched is lost to that subscriber (snn_demo: '
             f'{demo}); 0: subscribe at once', low=0),
        Spec('match_wait', 5.0, f'Wall-clock s at most to wait for {count} before subscribing to {input_} '
             'anyway (with a warning naming the count)', low=0.0, high=600.0))


def _time_jump_threshold(input_: str, before: str = 'the last one', then: str = ': start over') -> Spec:
    """time_jump_threshold of a node that takes ``input_`` (the sensor, the controller, the
    estimator: one name, default and range, each node's own wording)."""
    return Spec('time_jump_threshold', 1.0, f'Without a running /clock, {input_} this far before {before} '
                f'means the time base restarted{then}, s', low=0.0)


#: Where a sensor is and how it is turned: h(x) depends on these, so the sensor and the estimator
#: that takes its measurements read the same values (docs/sensors.md, "Frames and angles").
SENSOR_GEOMETRY = (
    Spec('observer', 'chaser', 'Where the sensor is: on the chaser (sees the target at -position) or on '
         'the target (sees the chaser); not for position', choices=OBSERVERS),
    Spec('mounting_offset', [0.0, 0.0, 0.0], 'Sensor position on its spacecraft, LVLH axes, m'),
    Spec('mounting_rotation', [0.0, 0.0, 0.0, 1.0], 'Sensor axes in LVLH axes as a unit quaternion '
         '[x, y, z, w] (tf2 order; identity: sensor x = V-bar, z = R-bar)'),
    Spec('sensor_frame_id', 'sensor', 'frame_id of the measurements of models other than position'),
)

SENSOR = MODEL + (
    Spec('measured_axes', [0, 1, 2], 'Position axes measured (0 x, 1 y, 2 z); the others are '
         'published as NaN'),
    Spec('measurement_noise', [D.RENDEZVOUS_MEASUREMENT_NOISE], 'R, covariance of the position noise '
         'per sample, m^2 (Table 6: 1e-2 I3); for another model R in its units (docs/sensors.md)'),
    Spec('seed', 0, 'Seed of the measurement noise (stream 2 of the seed)', low=0),
    _time_jump_threshold('a truth'),
    # the measurement model and its geometry (snn_estimator.measurements; docs/sensors.md)
    Spec('model', 'position', 'Measurement model; position and relative_gps publish PointStamped in frame_id, '
         'the others their message in sensor_frame_id (docs/sensors.md)', choices=tuple(MEASUREMENT_MODELS)),
) + SENSOR_GEOMETRY + (
    Spec('field_of_view', 2.0 * np.pi, 'Full cone angle about the sensor x axis, rad (2 pi: no limit); '
         'outside it no measurement (counted)', low=1e-9, high=2.0 * np.pi),
    Spec('min_range', 0.0, 'Shortest range measured, m (range 0 is never measured; relative_gps: where '
         'multipath and the target\'s shadow end it, 500 m in the approach, docs/decisions.md, 72)', low=0.0),
    Spec('max_range', 0.0, 'Longest range measured, m (0: no limit)', low=0.0),
    Spec('range_noise_growth', -1.0, 'Growth g of the range noise with the range r: sigma_r^2 = R_rr + '
         '(g r^e)^2, m^(1-e), e = 1 for range_azimuth_elevation and range, 2 for docking_camera '
         "(docs/sensors.md); negative: the model's own (docking_camera: its pinhole law, 2.09e-4 /m; "
         'the others: 0, R at every range)', low=-1.0),
    Spec('dropout_probability', 0.0, 'Probability that a sample is lost (own random stream 6)',
         low=0.0, high=1.0),
    Spec('measurement_period', 0.0, 'Simulated s between samples (0: every truth): a sample at the first '
         'truth at or after each multiple of it since the first; truths between are not measured', low=0.0),
    Spec('publish_not_measured', True, 'Models with limits: publish a sample outside the field of view or '
         'range, and every truth between two samples (measurement_period), as "nothing measured" '
         '(sensor_msgs/Range -inf/+inf as REP 117, a Vector3Stamped of NaN), so that the estimator '
         'predicts over it at once instead of waiting dropout_wait for it'),
    *_match_hold('min_measurement_subscribers', "measurement topic's", "'truth'",
                 'the plant starts on matched truth subscriptions, so after them',
                 'the estimator, the controller and the recorder'),
)

CONTROLLER = MODEL + (
    Spec('lqr_state_weight', [D.LQR_STATE_WEIGHT], 'Qc of the LQR cost, per m^2 and (m/s)^2 (not in '
         'the paper)', read_only=False),
    Spec('lqr_input_weight', [D.LQR_INPUT_WEIGHT], 'Rc of the LQR cost, per (m/s^2)^2 (not in the '
         'paper)', read_only=False),
    Spec('gain', None, 'K (3x6, 18 values row-major) to use instead of designing it from Qc, Rc',
         read_only=False, kind=DOUBLE_ARRAY),
    Spec('cw_model', 'standard', 'CW matrix used for the LQR design', choices=('standard', 'as_published')),
    Spec('dynamics_model', 'cw', 'Model whose linearisation at the port, A(0), the LQR is designed on: cw '
         '(the cw_model form), ss_j2 (Schweighart-Sedwick J2: A within 2e-3 of CW\'s) or nonlinear_circular '
         '(A(0) equal to CW\'s within 4e-15; the offline approach '
         "designs on the filter's model, and a lockstep run equals it only with the same gain to the bit)",
         choices=DYNAMICS_MODELS),
    Spec('setpoint', [0.0] * 6, 'State the LQR steers to, u = -K (x_hat - setpoint), m and m/s (zeros: '
         'docking; e.g. a V-bar hold point [-100, 0, 0, 0, 0, 0]); guidance approach: unused',
         read_only=False),
    Spec('guidance', 'none', 'none: steer to setpoint; approach: the approach guidance of '
         'snn_estimator.plant.approach (holds at 5 km, 2 km, 250 m, 20 m on V-bar, each left on a go '
         "from the estimate and its covariance, a 10 deg corridor to the port, a CAM when the estimate's "
         '3-sigma leaves it) gives the setpoint and its feed-forward, u = u_ff - K (x_hat - x_ref); its '
         'events on `guidance` (docs/decisions.md, 67)', choices=GUIDANCE_MODES),
    Spec('observability_manoeuvre', 'none', 'guidance approach: none, or out_of_plane_hop: at the hold '
         'observability_hold, observability_hop_delay s after arriving, a burn of n size m/s along y starts '
         'the free out-of-plane oscillation, a second half an orbit later stops it back on V-bar; the '
         "hold's go/no-go starts when it is done; its events ('hop <hold>', 'hop done <hold>') on `guidance` "
         '(snn_estimator.plant.approach.OutOfPlaneHop: what makes the range observable to angles alone, '
         'docs/decisions.md, 74 and 81)', choices=OBSERVABILITY_MANOEUVRES),
    Spec('observability_hold', D.ANGLES_HOP_HOLD, 'The hold whose observability manoeuvre is flown (one of '
         "the approach's holds: 5 km, 2 km, 250 m, 20 m)"),
    Spec('observability_hop_size', D.ANGLES_HOP_SIZE, 'The out-of-plane hop\'s peak offset along y, m '
         '(non-zero; its two burns cost 2 n size m/s)'),
    Spec('observability_hop_delay', D.ANGLES_HOP_DELAY, 'Simulated s after arriving at the hold before '
         "the hop's first burn", low=0.0),
    Spec('estimate_timeout', 0.5, 'Simulated s without a usable estimate before safe mode (zero '
         'thrust)', read_only=False, low=1e-9),
    Spec('max_input_age', 1.0, 'Estimates older than this behind the simulated clock, or stamped '
         'more than this plus two time steps ahead of it, are rejected, s', read_only=False, low=1e-9),
    _time_jump_threshold('an estimate'),
    Spec('measurement_topics', [MEASUREMENT], "The sensors' topics watched (any message type; only its "
         'stamp is read): each is a peer in diagnostics (peer.<topic>), and safe mode starts when none '
         'of them has sent anything for estimate_timeout (the estimates are then predictions); an '
         'estimator with `sensors`: their topics'),
    # the spiking LQR (snn_estimator/spiking/lqr.py)
    Spec('controller_type', 'lqr', 'lqr: u = -K (x_hat - setpoint) computed directly; snn_lqr: the '
         'same law read out of a spike-coding network that encodes x_hat - setpoint',
         choices=('lqr', 'snn_lqr')),
    Spec('snn_lqr_neurons', 100, 'N, LIF neurons of the snn_lqr network', low=1, high=100000),
    Spec('snn_lqr_leak', 0.001, 'lambda, leak of the snn_lqr membranes and trains, 1/s', low=0.0),
    *_match_hold('min_control_subscribers', "control topic's", '`estimate`',
                 'the estimator, the sensor and then the plant wait for their own, so the plant starts '
                 'only once controls reach the estimator and the plant',
                 'the estimator, the plant and the recorder'),
)

#: One sensor of an estimator with `sensors`: declared as <name>.<parameter> at configure.
SENSOR_INPUT = (
    Spec('topic', '', "The sensor's topic (empty: its name)"),
    Spec('model', 'range_azimuth_elevation', 'Its measurement model (docs/sensors.md)',
         choices=tuple(MEASUREMENT_MODELS)),
    Spec('measured_axes', [0, 1, 2], 'model position: the axes measured'),
    Spec('measurement_noise', [D.RENDEZVOUS_MEASUREMENT_NOISE], "R of the sensor's sample, in its model's units "
         '(1 value: times I; m: the diagonal; m*m: the matrix)'),
) + tuple(spec for spec in SENSOR_GEOMETRY if spec.name != 'sensor_frame_id') + (
    Spec('sensor_frame_id', '', 'frame_id of its messages (empty: its name)'),
    Spec('boundary_layer', [D.RENDEZVOUS_BOUNDARY_LAYER], 'delta of the (M)SIF gains per component of its '
         'sample (1 value: all); the MSIF gains divide its variance by it (docs/decisions.md, 35)'),
    Spec('gate', 0.0, 'Mahalanobis gate: a sample whose normalised innovation squared exceeds it is dropped '
         '(counted as gated.<name>; 0: no gate; chi-square, e.g. 16.3 for 3 components at p = 0.001)', low=0.0),
)


def sensor_input_specs(name: str) -> tuple:
    """The SENSOR_INPUT parameters of the estimator's sensor ``name``."""
    if not name or not name.replace('_', '').isalnum():
        raise ValueError(f'sensors: {name!r} is not a name (letters, digits, _)')
    return tuple(Spec(f'{name}.{spec.name}', spec.default, spec.description, choices=spec.choices,
                      low=spec.low, kind=spec.kind) for spec in SENSOR_INPUT)


def _from_schema(field) -> Spec:
    """The ROS parameter of a core estimator field (snn_estimator.schema): same name, default,
    meaning, range; read-only unless the core may change it between steps."""
    low = field.low
    if field.strict and field.type == 'real':
        low = 1e-300  # a descriptor range is closed: the smallest positive double stands for > 0
    return Spec(field.name, field.parameter_default, field.text, read_only=not field.runtime,
                low=low if field.type in ('integer', 'real') else None,
                high=field.high if field.type in ('integer', 'real') else None, choices=field.choices,
                kind=INTEGER_ARRAY if field.type == 'indices' else None)


ESTIMATOR = MODEL + (
    Spec('filter_type', DEFAULT_FILTER, 'The estimator (README, "Filters")', choices=tuple(FILTER_KINDS)),
    Spec('cw_model', 'standard', "CW matrix of the filter's model (dynamics_model cw): standard, or Eq. 41 as printed",
         choices=('standard', 'as_published')),
    Spec('measured_axes', [0, 1, 2], 'Position axes in the measurement (must match the sensor)'),
    Spec('model', 'position', "Measurement model of the `measurement` input (the sensor's; position: "
         'PointStamped in frame_id, z = C x exactly as before; the others: their message in '
         'sensor_frame_id, H(x_hat) each step; measurement_noise and boundary_layer in its units)',
         choices=tuple(MEASUREMENT_MODELS)),
) + SENSOR_GEOMETRY + (
    Spec('sensors', None, 'Several sensors fused in one filter (unset: the one `measurement` input above): '
         'their names; each has the <name>.* parameters of the sensor-input table (its topic, model, R, '
         'geometry, boundary layer, gate) and replaces model, measurement_noise and boundary_layer '
         '(docs/sensors.md)', kind=STRING_ARRAY),
) + tuple(_from_schema(field) for field in schema.FIELDS) + (
    Spec('silenced_fraction', 0.0, 'Fraction of neurons silenced, chosen at random with the seed '
         '(added to silenced_neurons)', read_only=False, low=0.0, high=1.0),
    Spec('publish_spikes', True, 'Publish per-neuron spike counts on `spikes` every step'),
    Spec('autostart', True, 'Configure and activate at start-up (a managed node otherwise: ros2 '
         'lifecycle set /estimator configure, activate)'),
    Spec('standby', False, 'Hot standby: configure, run on the same inputs but do not publish, and '
         'activate when every other estimator on `estimate` is gone (its liveliness lease expired). '
         'Of two active estimators, the one whose node name sorts last yields and stands by'),
    Spec('standby_timeout', 0.25, 'Liveliness lease of the `estimate` publisher, wall-clock s: a '
         'killed, stopped or deactivated active estimator is known to be gone within it, and a '
         'standby takes over', low=1e-3),
    Spec('initialization', 'auto', 'How the filter starts: parameters (initial_state at the first '
         'measurement), last_estimate (the newest estimate on `estimate`, replaying the inputs since: '
         'hot swap), history (a least-squares fit of the measurement history: restart after a crash); '
         'auto: the first of last_estimate, history, parameters that the topics\' history allows',
         choices=START_MODES),
    Spec('measurement_timing', 'grid', 'How measurement stamps relate to the steps: grid (on the '
         'estimate time plus steps of time_step, as the loop\'s sensor stamps them; others are '
         'rejected as misaligned), any (a sensor on its own clock: each measurement is the input '
         'until the next one\'s stamp and the estimate is published at each measurement\'s stamp; '
         'docs/decisions.md, 31)', choices=MEASUREMENT_TIMINGS),
    Spec('provisional_steps', True, "Once the plant reports the controls it applied (`applied_control`): "
         "answer z_k at once with the controller's u_k and correct the estimate (published again under its "
         'stamp) if the report differs; false: wait for the report (in realtime one tick later). At most '
         '8 steps are held for their reports (grid measurement_timing only; docs/decisions.md, 22b)'),
    *_match_hold('min_estimate_subscribers', '`estimate`', 'its measurements',
                 'the sensor and then the plant wait for their own, so the plant starts only once estimates '
                 'reach the controller; a standby subscribes at once', 'the controller and the recorder',
                 note=' (not counting its own liveliness monitor), once active,'),
    Spec('history_wait', 1.0, 'Wall-clock s at most to read the history that publishers keep on '
         '`estimate`, `measurement` and `control` when configured (no wait when none keeps any)', low=0.0),
    Spec('initial_fit_window', D.INITIAL_FIT_WINDOW, 'Seconds of measurement history a least-squares '
         'start fits (10 s: ~2 cm, ~3.5 mm/s 1-sigma at the default R)', low=1e-3),
    Spec('max_input_age', 1.0, 'Measurements older than this behind the newest one received '
         '(stragglers), or stamped more than this plus two time steps ahead of the simulated '
         'clock, are rejected, s', read_only=False, low=1e-9),
    _time_jump_threshold('a measurement', 'the estimate time', ' (bag loop): the filter restarts'),
    Spec('nis_threshold', 25.0, 'Normalised innovation squared above which a step counts as '
         'inconsistent (chi-square, 3 dof: p = 1.5e-5)', read_only=False, low=1e-9),
    Spec('nis_window', 10, 'Inconsistent steps in a row that trigger a re-initialisation from the '
         'measurement (0: never)', read_only=False, low=0),
)

RECORDER = (
    Spec('topics', list(PIPELINE_TOPICS), 'Topics to record (relative names resolve in the '
         "node's namespace); types of topics outside the pipeline are discovered from the graph"),
    Spec('output', '', 'Bag directory to create (empty: bag_<date>-<time> in the working directory)'),
    Spec('storage', 'mcap', 'Storage plugin', choices=('mcap', 'sqlite3')),
    Spec('drain_timeout', 5.0, 'On SIGINT/SIGTERM, wall-clock s at most to keep writing queued '
         'messages before closing the bag', low=0.0),
    Spec('match_wait', 5.0, "Wall-clock s at most to wait, before subscribing to 'truth', until every "
         'publisher of the other recorded topics has matched (the plant starts on matched truth '
         'subscriptions: it then starts when the recorder hears the loop); 0: subscribe at once',
         low=0.0, high=600.0),
)

LIVE_VIEW = MODEL + (
    Spec('host', '127.0.0.1', "Address the Foxglove WebSocket server listens on (0.0.0.0: every "
         'interface; the live view has no authentication)'),
    Spec('port', 8765, "Port of the Foxglove WebSocket server (Foxglove's default; 0: any free port)",
         low=0, high=65535),
    Spec('foxglove', True, 'Serve the live view over Foxglove\'s WebSocket protocol (foxglove-sdk)'),
    Spec('legacy_subprotocol', True, 'Accept clients of the subprotocol foxglove.websocket.v1 too (Lichtblick '
         'before 1.22, older Foxglove Studio, @foxglove/ws-protocol) on `port`: a relay in front of the SDK '
         'rewrites their handshake (docs/decisions.md, 44); false: the SDK serves `port`, foxglove.sdk.v1 only'),
    Spec('log_epoch', 0.0, 'Epoch of the log times, s since the Unix epoch: a message of simulated time t is '
         'logged at log_epoch + t (0: the wall-clock time of the first frame less its simulated time, '
         "the run's start)", low=0.0),
    Spec('markers', True, 'Publish the scene as visualization_msgs/MarkerArray on `markers` (RViz)'),
    Spec('publish_rate', 20.0, 'Frames per wall-clock second at most; inputs between two frames are '
         'coalesced (the newest drawn), never queued', low=0.1, high=1000.0),
    Spec('message_backlog', 64, 'Messages queued per Foxglove client; the oldest is dropped when a '
         'client does not keep up (logging never blocks)', low=1, high=100000),
    Spec('covariance_sigma', 3.0, 'Size of the covariance ellipsoid and of the +- bounds of the error '
         'plots, in standard deviations', low=1e-3, high=100.0),
    Spec('keep_out_radius', 2.0, 'Radius of the keep-out sphere around the target, m (0: not drawn)', low=0.0),
    Spec('corridor_axis', [float(v) for v in D.RENDEZVOUS_X0[:3]], 'Direction of the approach '
         "corridor's axis from the target, LVLH (default: the chaser's initial position)"),
    Spec('corridor_half_angle', 15.0, "Half angle of the approach corridor's cone, deg", low=0.1, high=89.0),
    Spec('corridor_length', 100.0, 'Length of the approach corridor, m (0: not drawn)', low=0.0),
    Spec('thrust_scale', 200.0, 'Length of the thrust arrow per unit of control, m per m/s^2', low=0.0),
    Spec('trail_length', 500, 'Positions kept in the true and estimated trails', low=2, high=100000),
    Spec('raster_steps', 200, 'Steps shown across the spike raster: its width in pixels (its height: the '
         "network's neurons; bytes per image = steps x neurons)", low=1, high=100000),
    Spec('raster_rate', 5.0, 'Spike raster images per wall-clock second at most (0: none); the raster is '
         'most of the live view\'s bytes (docs/live_view.md)', low=0.0, high=1000.0),
)

#: Every table by the name a registry entry gives (``NodeEntry.parameters``).
TABLES = {'MODEL': MODEL, 'PLANT': PLANT, 'BASILISK_PLANT': BASILISK_PLANT, 'SENSOR': SENSOR,
          'CONTROLLER': CONTROLLER, 'ESTIMATOR': ESTIMATOR, 'RECORDER': RECORDER, 'LIVE_VIEW': LIVE_VIEW}
#: Node name -> its table, in the order the YAML files and docs/parameters.md list them (the
#: registry's).
NODES = {entry.name: TABLES[entry.parameters] for entry in registry.NODES}

#: Parameters applied between steps through the parameter services; the others are read-only.
ESTIMATOR_RUNTIME = frozenset(spec.name for spec in ESTIMATOR if not spec.read_only)


def show(value) -> str:
    """A value as the docs, the YAML comments and error messages print it."""
    if value is None:
        return '(unset)'
    if isinstance(value, float):
        return f'{value:g}'
    if isinstance(value, list):
        return '[' + ', '.join(show(v) for v in value) + ']'
    return str(value)


def sensor_suites() -> dict[str, dict[str, dict]]:
    """Sensors that replace Table 6's position sensor: name -> node -> parameter values
    (``make demo SENSOR=<name>``, config/sensor_<name>.yaml; the sensor nodes each starts:
    scenario_nodes.registry.SENSOR_NODES). The numbers are the core's
    (snn_estimator.defaults), as the offline ``sensor_rendezvous_scenario`` takes them: R per
    sample, the mounting that looks back at the target, the minimum range, and the estimator's
    R and boundary layer (Table 6's delta per component, one sensor sigma:
    snn_estimator.config.sensor_boundary_layer) and its network (D.SENSOR_NETWORK: the deviation
    coding in 1 mm and 0.01 mm/s units)."""
    def sensor(model: str, frame: str) -> tuple[dict, list]:
        noise = [float(v) for v in np.atleast_1d(D.SENSOR_NOISE[model])]
        return {'model': model, 'measurement_noise': noise,
                'mounting_rotation': [float(v) for v in D.CLOSE_SENSOR_MOUNTING], 'sensor_frame_id': frame}, noise

    lidar, lidar_noise = sensor('range_azimuth_elevation', 'lidar')
    network = {'network_coding': D.SENSOR_NETWORK['network_coding'],
               'state_scale': [float(v) for v in D.SENSOR_NETWORK['state_scale']]}
    camera, camera_noise = sensor('line_of_sight', 'camera')
    close = {'min_range': float(D.CLOSE_SENSOR_MIN_RANGE)}
    suites = {'lidar': {'position_sensor': {**lidar, **close},
                        'estimator': {**lidar, 'boundary_layer': list(sensor_boundary_layer(lidar_noise)),
                                      **network}}}
    # camera + LIDAR (offline: handover_scenario): two sensor nodes on their own topics, fused
    fused = {'sensors': ['camera', 'lidar'], **network}
    for name, values, noise in (('camera', camera, camera_noise), ('lidar', lidar, lidar_noise)):
        fused.update({f'{name}.{key}': value for key, value in values.items() if key != 'sensor_frame_id'})
        fused[f'{name}.boundary_layer'] = list(sensor_boundary_layer(noise))
    period = D.HANDOVER_PERIODS[1] * D.RENDEZVOUS_TIME_STEP
    topics = [t for t in PIPELINE_TOPICS if t != 'measurement'] + ['camera', 'lidar']
    suites['camera+lidar'] = {
        'camera': {**camera, **close, 'seed': 0},
        'lidar': {**lidar, **close, 'max_range': float(D.HANDOVER_LIDAR_MAX_RANGE),
                  'measurement_period': float(period), 'seed': FUSED_SEED_OFFSET},
        'estimator': fused, 'cw_plant': {'measurement_topics': ['camera', 'lidar']},
        'lqr_controller': {'measurement_topics': ['camera', 'lidar']},
        'recorder': {'topics': topics}}
    suites['docking'] = _docking_suite(network)
    suites.update({suite: _approach_suite(suite) for suite in ('by_range', 'angles_far')})
    return suites


def _docking_suite(network: dict) -> dict[str, dict]:
    """The docking suite (offline: snn_estimator.sim.scenarios.docking_scenario): a LIDAR as flown
    far and the docking camera close (D.DOCKING_LIDAR, D.DOCKING_CAMERA), each its own node on
    its own topic; the sensors draw R(range), the estimator takes R_hat at each one's design
    range (docs/decisions.md, 46)."""
    mounting = [float(v) for v in D.CLOSE_SENSOR_MOUNTING]
    estimator = {'sensors': ['lidar', 'camera'], **network}
    nodes = {}
    for i, (name, model, spec) in enumerate(zip(('lidar', 'camera'), docking_sensors(field_of_view=False),
                                                (D.DOCKING_LIDAR, D.DOCKING_CAMERA))):
        floor = [float(v) for v in spec['noise']]
        nodes[name] = {'model': model.name, 'measurement_noise': floor, 'mounting_rotation': mounting,
                       'sensor_frame_id': name, 'min_range': float(spec['min_range']),
                       'max_range': float(spec['max_range']), 'range_noise_growth': float(model.range_noise_growth),
                       'measurement_period': round(spec['period_steps'] * D.RENDEZVOUS_TIME_STEP, 9),
                       'seed': i * FUSED_SEED_OFFSET}
        r_hat = [float(f'{v:.15g}') for v in np.diag(design_noise(model, spec['design_range']))]
        estimator.update({f'{name}.model': model.name, f'{name}.measurement_noise': r_hat,
                          f'{name}.mounting_rotation': mounting,
                          f'{name}.boundary_layer': list(sensor_boundary_layer(r_hat))})
    topics = [t for t in PIPELINE_TOPICS if t != 'measurement'] + ['lidar', 'camera']
    return {**nodes, 'estimator': estimator, 'cw_plant': {'measurement_topics': ['lidar', 'camera']},
            'lqr_controller': {'measurement_topics': ['lidar', 'camera']}, 'recorder': {'topics': topics}}


#: The filters' and the truth's model of the approach over ROS (issue 39, part 4).
APPROACH_MODEL = 'nonlinear_circular'


def _approach_suite(suite: str) -> dict[str, dict]:
    """A sensor suite of the approach (offline: approach_scenario(sensors=``suite``)), for the
    approach only (config/sensor_<suite>.yaml after config/scenario_approach.yaml). by_range
    (decision 72): relative GPS, the LIDAR and the docking camera; angles_far (decision 73): the
    far camera's line of sight instead of relative GPS. Each sensor its own node on its own topic
    with its range limits, field of view and the offline FusedSensor's seed (sensor i: i *
    FUSED_SEED_OFFSET), sampling every truth, the approach's time step; the estimator fuses them
    with the offline R_hat blocks (by_range_noise) and boundary layers, and the other estimator
    values the suite's scenario changes (the spiking filters' deviation coding; angles_far: P0
    from the range uncertainty); the controller flies the scenario's observability manoeuvre,
    if it has one. docs/decisions.md, 80-81."""
    from snn_estimator.sim.approach import approach_scenario
    s = approach_scenario(APPROACH_MODEL, plant=APPROACH_MODEL, sensors=suite)
    plain = approach_scenario(APPROACH_MODEL, plant=APPROACH_MODEL).estimator
    approach = scenarios()['approach']
    names = registry.SENSOR_NODES[suite]
    estimator = {f.name: dataclasses.replace(f, default=getattr(s.estimator, f.name)).parameter_default
                 for f in schema.FIELDS if f.name not in ('measurement_noise', 'boundary_layer')
                 and repr(getattr(s.estimator, f.name)) != repr(getattr(plain, f.name))}
    estimator['sensors'] = list(names)
    nodes = {}
    for i, (name, part, block) in enumerate(zip(names, s.sensor.parts, s.sensor.slices)):
        r_hat = np.asarray(s.estimator.measurement_noise)[block, block]  # by_range_noise's block
        delta = [float(v) for v in np.asarray(s.estimator.boundary_layer)[block]]
        nodes[name], own = _approach_sensor(approach['position_sensor'], name, part, i, (r_hat, delta))
        estimator.update({f'{name}.{key}': value for key, value in own.items()})
    watched = {'measurement_topics': list(names)}
    topics = [t for t in approach['recorder']['topics'] if t != MEASUREMENT] + list(names)
    return {**nodes, 'estimator': estimator, 'cw_plant': watched,
            'lqr_controller': {**watched, **_manoeuvre_values(s.manoeuvre)}, 'recorder': {'topics': topics}}


def _approach_sensor(every: dict, name: str, part, index: int, estimated: tuple) -> tuple[dict, dict]:
    """One sensor of an approach suite, the ``index``-th: its node's values (``every``: the
    scenario's sensor values) and its estimator sensor input's (``estimated``: R_hat, delta)."""
    from snn_estimator.sim.approach import APPROACH_SENSOR_MOUNTING
    mounting = [float(v) for v in APPROACH_SENSOR_MOUNTING]
    values = {**every, 'model': part.name, 'measurement_noise': _diagonal(part.noise),
              'min_range': float(part.min_range), 'max_range': float(part.max_range),
              'seed': index * FUSED_SEED_OFFSET}
    r_hat, delta = estimated
    own = {'model': part.name, 'measurement_noise': _diagonal(r_hat), 'boundary_layer': delta}
    if part.message_form == 'point':  # in the LVLH frame, as the position sensor's
        own['sensor_frame_id'] = _default(MODEL, 'frame_id')
    else:
        values.update(mounting_rotation=mounting, sensor_frame_id=name,
                      range_noise_growth=float(part.range_noise_growth))
        values.update({} if part.field_of_view >= 2.0 * np.pi else {'field_of_view': float(part.field_of_view)})
        own['mounting_rotation'] = mounting
    return values, own


def _manoeuvre_values(manoeuvre) -> dict:
    """The controller's observability_* values of a scenario's manoeuvre (None: none set)."""
    if manoeuvre is None:
        return {}
    return {'observability_manoeuvre': OUT_OF_PLANE_HOP, 'observability_hold': manoeuvre.hold,
            'observability_hop_size': float(manoeuvre.size), 'observability_hop_delay': float(manoeuvre.delay)}


def _diagonal(matrix) -> list[float]:
    """The diagonal of a diagonal covariance (what a measurement_noise parameter of n values is)."""
    matrix = np.asarray(matrix, dtype=float)
    if np.count_nonzero(matrix - np.diag(np.diag(matrix))):
        raise ValueError('a sensor of a suite takes a diagonal R')
    return [float(v) for v in np.diag(matrix)]


def _default(table, name: str):
    return next(spec.default for spec in table if spec.name == name)


def scenarios() -> dict[str, dict[str, dict]]:
    """Scenarios other than Table 6's rendezvous: name -> node -> parameter values (``make demo
    SCENARIO=<name>``, snn_demo --scenario). approach: the offline approach of
    snn_estimator.sim.approach (approach_scenario: 5 km behind on V-bar, 1 s steps, the
    position sensor at 1 Hz, the filters dispersed about x0 as in the far-range scenario) on
    the nonlinear truth and filter model, the controller's approach guidance on the LQR weights
    of the offline loop, the run ended at the port or by the guidance (docs/decisions.md, 67).
    Every value is the core's; the time limits that count in steps are one-step-scaled."""
    from snn_estimator.sim.approach import approach_scenario  # loads the filters (numba): not at node start
    s = approach_scenario(APPROACH_MODEL, plant=APPROACH_MODEL)
    default = EstimatorConfig()
    estimator = {f.name: dataclasses.replace(f, default=getattr(s.estimator, f.name)).parameter_default
                 for f in schema.FIELDS if repr(getattr(s.estimator, f.name)) != repr(getattr(default, f.name))}
    dt = float(s.dt)
    # a control stays in force, and an estimate counts as recent, for two steps of 1 s (the
    # defaults are 5 steps of Table 6's 0.1 s): the lockstep loop is paced by the plant
    every = {'time_step': dt, 'control_validity': 2.0 * dt, 'diagnostics_period': 60.0}
    state_weight, input_weight = s.lqr_weights
    return {'approach': {
        'cw_plant': {**every, 'dynamics_model': APPROACH_MODEL, 'initial_state': _floats(s.x0),
                     'duration': float(s.max_duration), 'stop_at_port': True, 'end_on_guidance': True},
        'position_sensor': {**every},
        # no NIS re-initialisation (the offline loop has none): on this loop it fired at 1085 s and
        # 1551 s, the SNN-EKF's NIS 27-28 over 10 steps in the 5 km -> 2 km transfer (decision 68)
        'estimator': {**every, **estimator, 'max_input_age': 2.0 * dt, 'nis_window': 0},
        'lqr_controller': {**every, 'guidance': 'approach', 'dynamics_model': APPROACH_MODEL,
                           'lqr_state_weight': [float(state_weight)],
                           'lqr_input_weight': [float(input_weight)], 'estimate_timeout': 3.0 * dt,
                           'max_input_age': 2.0 * dt},
        'recorder': {'topics': [*PIPELINE_TOPICS, GUIDANCE]}}}
