"""Read a recorded run back from its rosbag2 directory and compute its summary.

No rclpy is needed, so a bag can be examined anywhere: rosbags reads the bag, and the
pipeline's messages are decoded by the nodes' own codec (scenario_nodes.codec, 2-6x faster
than rosbags' deserializer per message type, docs/performance.md); the diagnostics by
rosbags. The summary is computed from the bag, never from in-memory data of the run.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from scenario_nodes import codec
from scenario_nodes.topics import GUIDANCE, PIPELINE_TOPICS  # decoded; other topics (ros2 bag record -a) only counted
from snn_estimator.models import ClohessyWiltshire
from snn_estimator.plant.sensors import SamplePeriod
from snn_estimator.sim.results import contact_conditions

STATES = ClohessyWiltshire.state_names
NS = codec.NS
#: What a sensor node publishes (docs/sensors.md): on a topic of its own, any of these is a report.
SENSOR_TYPES = frozenset(codec.MEASUREMENT_TYPES.values())


def _stamp(header) -> int:
    return int(header.stamp.sec) * NS + int(header.stamp.nanosec)


@dataclass
class RunData:
    """Everything a report needs, as arrays (times in seconds)."""

    path: Path
    counts: dict = field(default_factory=dict)        # topic -> messages in the bag
    types: dict = field(default_factory=dict)         # topic -> message type
    truth_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    truth: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    estimate_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    estimate: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    estimate_variance: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    measurement_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    measurement: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    control_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    control: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    spike_count: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    # (steps, N) per-neuron spike counts; N is the largest network of the run, and a step with
    # fewer neurons (hot swap to another N, or to a non-spiking filter: empty arrays) is
    # padded with zeros. Only steps that published spikes have a row.
    spikes: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int64))
    receive_times: dict = field(default_factory=dict)  # pipeline topic -> (k,) ns, in bag order
    diagnostics: dict = field(default_factory=dict)    # status name -> list of (stamp s, values)
    namespace: str = ''
    repeats: dict = field(default_factory=dict)      # series -> resent (or corrected) samples left out of it
    # sensor topic (relative, e.g. measurement, camera) -> (stamps ns, measured): one per stamp, in
    # stamp order; measured False for "nothing measured"
    reports: dict = field(default_factory=dict)
    # the approach guidance's events (`guidance`, if recorded): (stamp s, event, {key: value}), in bag order
    guidance: list = field(default_factory=list)

    def last_diagnostics(self, name: str) -> dict:
        entries = self.diagnostics.get(name)
        return entries[-1][1] if entries else {}


def read_bag(path: str | Path, namespace: str | None = None) -> RunData:
    """Load the pipeline topics of a bag (topic names under ``namespace``; None: the namespace
    of the bag's ``truth`` or ``estimate`` topic). Other topics are counted, not decoded."""
    path = Path(path)
    typestore = get_typestore(Stores.ROS2_JAZZY)
    run = RunData(path=path)
    series = defaultdict(list)
    receive = defaultdict(list)
    with Reader(path) as reader:
        for connection in reader.connections:
            run.types[connection.topic] = connection.msgtype
            run.counts[connection.topic] = run.counts.get(connection.topic, 0) + connection.msgcount
        if namespace is None:
            namespace = next((topic.rsplit('/', 1)[0] for topic in run.types
                              if topic.rsplit('/', 1)[-1] in ('truth', 'estimate')), '')
        prefix = namespace.rstrip('/') + '/'
        run.namespace = namespace.rstrip('/')
        pipeline = [c for c in reader.connections
                    if c.topic.startswith(prefix) and c.topic[len(prefix):] in (*PIPELINE_TOPICS, GUIDANCE)]
        # a sensor's topic: its message type, directly in the namespace (not '<topic>/history')
        sensors = {c.id for c in reader.connections if c.msgtype in SENSOR_TYPES
                   and c.topic.startswith(prefix) and '/' not in c.topic[len(prefix):]}
        chosen = pipeline + [c for c in reader.connections if c.id in sensors and c not in pipeline]
        messages = reader.messages(connections=chosen) if chosen else ()  # [] reads all
        for connection, timestamp, raw in messages:
            name = connection.topic[len(prefix):]
            if connection.id in sensors:
                series[('report', name)].append(codec.sensor_report(connection.msgtype, raw))
            if name == GUIDANCE:
                msg = typestore.deserialize_cdr(raw, connection.msgtype)
                run.guidance += [(_stamp(msg.header) / NS, status.message, {kv.key: kv.value for kv in status.values})
                                 for status in msg.status]
            elif name in PIPELINE_TOPICS:
                receive[connection.topic].append(timestamp)
                _decode(run, series, typestore, connection, name, raw)
    run.receive_times = {topic: np.asarray(times, dtype=np.int64) for topic, times in receive.items()}
    for key in [key for key in series if isinstance(key, tuple)]:
        reports, _ = _one_per_stamp(series.pop(key))
        run.reports[key[1]] = (np.array([r[0] for r in reports], dtype=np.int64),
                               np.array([r[1] for r in reports], dtype=bool))
    for name in ('truth', 'estimate', 'measurement', 'control'):
        series[name], run.repeats[name] = _one_per_stamp(series[name], last=name == 'estimate')
    if series['truth']:
        run.truth_t = np.array([s[0] for s in series['truth']]) / NS
        run.truth = np.stack([s[1] for s in series['truth']])
    if series['estimate']:
        run.estimate_t = np.array([s[0] for s in series['estimate']]) / NS
        run.estimate = np.stack([s[1] for s in series['estimate']])
        run.estimate_variance = np.stack([s[2] for s in series['estimate']])
    for name in ('measurement', 'control'):
        if series[name]:
            setattr(run, f'{name}_t', np.array([s[0] for s in series[name]]) / NS)
            setattr(run, name, np.stack([s[1] for s in series[name]]))
    run.spike_count = np.asarray(series['spike_count'], dtype=np.int64)
    neurons = max((len(s) for s in series['spikes']), default=0)
    if neurons:
        run.spikes = np.zeros((len(series['spikes']), neurons), dtype=np.int64)
        for row, counts in zip(run.spikes, series['spikes']):
            row[:len(counts)] = counts
    return run


def _decode(run: RunData, series: dict, typestore, connection, name: str, raw: bytes) -> None:
    """One pipeline message into its series (diagnostics into ``run.diagnostics``)."""
    if name in ('truth', 'estimate'):
        record = codec.decode_odometry(raw)
        series[name].append((record.stamp_ns, record.state, np.diag(record.covariance)))
    elif name == 'measurement' and connection.msgtype == 'sensor_msgs/msg/Range':
        record = codec.decode_range(raw)  # +-inf: nothing measured (REP 117)
        series[name].append((record.stamp_ns, np.array([record.range, np.nan, np.nan])))
    elif name in ('measurement', 'control'):  # PointStamped and Vector3Stamped: one layout
        record = codec.decode_point(raw) if name == 'measurement' else codec.decode_accel(raw)
        series[name].append((record.stamp_ns, record.vector))
    elif name == 'spike_count':
        series[name].append(codec.decode_uint32(raw))
    elif name == 'spikes':
        series[name].append(codec.decode_spikes(raw))
    elif name == 'diagnostics':
        msg = typestore.deserialize_cdr(raw, connection.msgtype)
        stamp = _stamp(msg.header) / NS
        for status in msg.status:
            run.diagnostics.setdefault(status.name, []).append((stamp, {kv.key: kv.value for kv in status.values}))


def _one_per_stamp(samples: list, last: bool = False) -> tuple[list, int]:
    """One sample per stamp, in stamp order, and how many were left out. A lockstep resend
    repeats a sample when its answer is late (docs/decisions.md 21: the same bytes); an estimate
    taken again with the control the plant applied is published again under its stamp (22b), so
    for estimates ``last`` keeps the final one (the estimator's answer; the first is what the
    controller acted on). Every copy stays on record in the bag."""
    kept = {}
    for sample in samples:
        if last or sample[0] not in kept:
            kept[sample[0]] = sample
    ordered = sorted(kept.values(), key=lambda sample: sample[0])  # a recorder backfills missed samples later
    return ordered, len(samples) - len(ordered)


def matched_errors(run: RunData) -> tuple[np.ndarray, np.ndarray]:
    """Times and errors truth - estimate where both have a sample (same stamp)."""
    truth_index = {int(round(t * NS)): i for i, t in enumerate(run.truth_t)}
    times, errors = [], []
    for j, t in enumerate(run.estimate_t):
        i = truth_index.get(int(round(t * NS)))
        if i is not None:
            times.append(t)
            errors.append(run.truth[i] - run.estimate[j])
    return np.asarray(times), np.asarray(errors).reshape(-1, 6)


#: Each node's counter of what it published: one that goes down in the bag means a restart.
PUBLISHED_COUNTERS = {'cw_plant': 'truth_published', 'basilisk_plant': 'truth_published',
                      'position_sensor': 'measurements_published', 'lqr_controller': 'controls_published',
                      'estimator': 'estimates_published'}


def restarts(run: RunData) -> dict:
    """Node status name -> how many times it restarted during the bag (its published counter
    went down; a restarted node counts again from zero)."""
    found = {}
    for name, key in PUBLISHED_COUNTERS.items():
        values = [_number(v, key, -1.0) for _, v in run.diagnostics.get(name, ())]
        values = [v for v in values if v >= 0]
        found[name] = int(sum(b < a for a, b in zip(values, values[1:])))
    return {name: n for name, n in found.items() if name in run.diagnostics}


def _truth_grid(run: RunData) -> np.ndarray:
    return np.unique(np.round(run.truth_t * NS).astype(np.int64))


def _runs(missing: np.ndarray, schedule: np.ndarray) -> list:
    """``missing`` stamps (ns, sorted, all in ``schedule``) as [first, last] runs in seconds,
    a run being stamps that follow each other on the schedule."""
    runs, start = [], None
    for i, stamp in enumerate(missing):
        start = stamp if start is None else start
        following = missing[i + 1] if i + 1 < missing.size else None
        if following is None or np.searchsorted(schedule, following) != np.searchsorted(schedule, stamp) + 1:
            runs.append([start / NS, stamp / NS])
            start = None
    return runs


def stamp_gaps(run: RunData) -> dict:
    """Per recorded series answered on the truth's grid (control, estimate), the stamps of the
    grid it lacks, as [first, last] runs in seconds (the last truth stamp needs no control).
    The sensors: :func:`sensor_reports`."""
    grid = _truth_grid(run)
    gaps = {}
    for name, times, tail in (('control', run.control_t, 1), ('estimate', run.estimate_t, 0)):
        if not times.size or not grid.size:
            continue  # not recorded (or no truth to judge against)
        expected = grid[:grid.size - tail]
        gaps[name] = _runs(np.setdiff1d(expected, np.round(times * NS).astype(np.int64)), expected)
    return gaps


def sensor_schedule(grid: np.ndarray, period: float, every_truth: bool) -> np.ndarray:
    """The truth stamps (ns) a sensor reports on: every one when it answers each truth (a sample
    or "nothing measured"), else its samples, the first truth at or after each multiple of
    ``period`` s (the sensor's own rule, :class:`SamplePeriod`; 0: every truth)."""
    if every_truth or not period:
        return grid
    due = SamplePeriod(period).due
    return grid[np.fromiter((due(int(stamp)) for stamp in grid), dtype=bool, count=grid.size)]


def sensor_reports(run: RunData) -> dict:
    """Each sensor's stream against its own schedule, by topic: a gap is a stamp the sensor was
    due to report (every truth, or every ``sample_period``; :func:`sensor_schedule`) that the bag
    lacks. The sensors are the nodes whose diagnostics count ``measurements_published``; their
    diagnostics give the topic, the period, whether every truth is answered, and the samples
    the sensor itself did not publish (dropouts; limits when it does not say "nothing
    measured"), which explain that many missing stamps: ``lost`` are the ones left. A bag
    without sensor diagnostics is read as the default sensor on `measurement` (every truth).

    Per topic: node, period_s (between samples), expected, recorded (stamps on the schedule),
    measured and not_measured (of the recorded), off_schedule, missing, gaps ([first, last] s),
    not_published, lost."""
    grid = _truth_grid(run)
    if not grid.size:
        return {}
    step = float(np.median(np.diff(grid))) / NS if grid.size > 1 else 0.0
    prefix = run.namespace + '/'
    nodes = {}
    for name, entries in run.diagnostics.items():
        values = entries[-1][1]
        if 'measurements_published' in values:
            topic = values.get('topic') or ('measurement' if name == 'position_sensor' else name)
            nodes[topic[len(prefix):] if topic.startswith(prefix) else topic.lstrip('/')] = (name, values)
    if not nodes and 'measurement' in run.reports:
        nodes['measurement'] = (None, {})
    out = {}
    for topic, (name, values) in sorted(nodes.items()):
        period = _number(values, 'sample_period')
        every_truth = str(values.get('reports_every_truth', 'True')) == 'True'
        schedule = sensor_schedule(grid, period, every_truth)
        stamps, measured = run.reports.get(topic, (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool)))
        on_schedule = np.isin(stamps, schedule)
        missing = np.setdiff1d(schedule, stamps)
        not_published = int(_number(values, 'samples_unpublished'))
        out[topic] = {
            'node': name, 'period_s': period or step, 'every_truth': every_truth,
            'expected': int(schedule.size), 'recorded': int(on_schedule.sum()),
            'measured': int(measured[on_schedule].sum()), 'not_measured': int((~measured[on_schedule]).sum()),
            'off_schedule': int((~on_schedule).sum()), 'missing': int(missing.size),
            'gaps': _runs(missing, schedule), 'not_published': not_published,
            'lost': max(0, int(missing.size) - not_published)}
    return out


def _number(values: dict, key: str, default=0.0) -> float:
    try:
        return float(values.get(key, default))
    except (TypeError, ValueError):
        return default


def summarize(run: RunData, window: float = 60.0) -> dict:
    """The demo's summary.json, computed from the bag alone."""
    plant = run.last_diagnostics('cw_plant') or run.last_diagnostics('basilisk_plant')
    estimator = run.last_diagnostics('estimator')
    sensor = run.last_diagnostics('position_sensor')
    controller = run.last_diagnostics('lqr_controller')
    times, errors = matched_errors(run)
    if times.size:
        recent = times >= times[-1] - window + 1e-9
        rmse = np.sqrt(np.mean(errors[recent] ** 2, axis=0))
    else:
        rmse = np.full(6, np.nan)
    neurons = int(_number(estimator, 'neurons'))
    spikes_total = int(run.spike_count.sum())
    # per recorded step (one spike count per published estimate, whichever estimator sent it):
    # mean spikes per neuron and step, whatever restarted or published twice
    spike_steps = run.spike_count.size
    prefix = run.namespace + '/'
    estimates = _number(estimator, 'estimates_published')
    published = {
        'truth': int(_number(plant, 'truth_published')),
        'measurement': int(_number(sensor, 'measurements_published')),
        'control': int(_number(controller, 'controls_published')),
        'estimate': int(estimates),
        # one per step: not sent again with a resend or a correction
        'spike_count': int(estimates - _number(estimator, 'estimates_resent')
                           - _number(estimator, 'estimates_corrected')),
        # none with publish_spikes false; estimators older than the key published one per estimate
        'spikes': int(_number(estimator, 'spikes_published', estimates)),
    }
    sensors = [name for name in str(estimator.get('sensors', '')).split(',') if name]
    if sensors:  # several sensors, each on its topic (its name) with its own diagnostics
        del published['measurement']
        published.update({name: int(_number(run.last_diagnostics(name), 'measurements_published'))
                          for name in sensors})
    recorded = {name: int(run.counts.get(prefix + name, 0)) for name in published}
    completeness = _completeness(run, estimator, published, recorded, sensor_reports(run))
    return {
        'estimator': estimator.get('filter', 'unknown'),
        'sim_time_s': _number(plant, 'sim_time'),
        'wall_time_s': _number(plant, 'wall_time'),
        'real_time_factor': _number(plant, 'real_time_factor'),
        'steps': int(_number(plant, 'steps')),
        'rmse_last_60s': {state: float(value) for state, value in zip(STATES, rmse)},
        'final_range_m': float(np.linalg.norm(run.truth[-1, :3])) if run.truth.size else float('nan'),
        # within the last metre: closing speed, offset from the docking axis (docs/decisions.md, 49)
        'contact': _contact(run),
        'spikes_total': spikes_total,
        'spike_fraction': spikes_total / (neurons * spike_steps) if neurons and spike_steps else 0.0,
        'control_timeouts': int(_number(plant, 'control_timeouts')),
        'plant': 'basilisk_plant' if run.last_diagnostics('basilisk_plant') else 'cw_plant',
        'saturated_steps': int(_number(plant, 'saturated_steps')),
        'measurements_rejected': int(_number(estimator, 'measurements_rejected')),
        'controls_missing': int(_number(estimator, 'controls_missing')),
        'estimator_spikes_total': int(_number(estimator, 'spikes_total')),
        'neurons': neurons,
        'messages': {name: {'published': published[name], 'recorded': recorded[name]} for name in published},
        **completeness,
    }


def _contact(run: RunData) -> dict | None:
    """The contact conditions of the recorded truth, with the simulated time of that sample."""
    contact = contact_conditions(run.truth) if run.truth.size else None
    if contact is None:
        return None
    return {'t_s': float(run.truth_t[contact.pop('step')]), **contact}


def _completeness(run: RunData, estimator: dict, published: dict, recorded: dict, sensors: dict) -> dict:
    """Whether the bag holds the whole run: every stamp of the truth's grid in control and
    estimate, every stamp each sensor was due to report but those it says it did not publish,
    and, when the nodes' totals can be compared (no restart, nobody publishing twice), every
    message they published (a restarted node counts from its restart)."""
    restarted = restarts(run)
    gaps = {topic: values['gaps'] for topic, values in sensors.items()} | stamp_gaps(run)
    duplicates = max(0, run.repeats.get('estimate', 0) - int(_number(estimator, 'estimates_resent'))
                     - int(_number(estimator, 'estimates_corrected')))
    comparable = not any(restarted.values()) and not duplicates
    complete = (all(not gaps[name] for name in gaps if name not in sensors)
                and all(not values['lost'] for values in sensors.values())
                and (not comparable or all(recorded[n] == published[n] for n in published)))
    return {'recording_complete': complete, 'restarts': restarted, 'duplicate_estimates': duplicates,
            'gaps': gaps, 'sensors': sensors}
