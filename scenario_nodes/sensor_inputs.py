"""The estimator's inputs from several sensors (its `sensors` parameter; docs/sensors.md).

Each sensor has its topic, model, R, geometry, boundary layer and Mahalanobis gate
(<name>.* parameters, parameter_tables.SENSOR_INPUT). Their samples are one stacked measurement
(snn_estimator.measurements.stacked), assembled per stamp by
:class:`snn_estimator.runners.assembly.SampleAssembler` and gated per sensor before the runner
takes them.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from functools import partial

import numpy as np

from snn_estimator.measurements.stacked import Stacked
from snn_estimator.runners.assembly import SampleAssembler, gate

from . import qos
from .codec import MessageError, read_measurement
from .conversions import MEASUREMENT_CLASSES
from .core_objects import measurement_model
from .parameter_tables import sensor_input_specs
from .ros_parameters import declare
from .runtime import clock_ns


@dataclass(frozen=True)
class SensorInput:
    name: str
    topic: str
    frame_id: str
    model: object
    gate: float


def declare_sensors(node, names) -> tuple[list[SensorInput], Stacked, tuple]:
    """Declare the <name>.* parameters of each sensor; its inputs, the stacked measurement and the
    boundary layer of every component (one value per sensor spread over its components)."""
    if len(set(names)) != len(names):
        raise ValueError(f'sensors: every name once, got {list(names)}')
    inputs, deltas = [], []
    for name in names:
        values = {key.split('.', 1)[1]: value for key, value in declare(node, sensor_input_specs(name)).items()}
        try:
            model = measurement_model(values, values['measurement_noise'])
        except ValueError as error:
            raise ValueError(f'{name}: {error}') from None
        delta = np.atleast_1d(np.asarray(values['boundary_layer'], dtype=float))
        if delta.size not in (1, model.dim) or not (delta > 0).all():
            raise ValueError(f'{name}.boundary_layer: 1 or {model.dim} values > 0, got {delta.tolist()}')
        deltas.extend(np.broadcast_to(delta, (model.dim,)).tolist())
        inputs.append(SensorInput(name, values['topic'] or name, values['sensor_frame_id'] or name, model,
                                  float(values['gate'])))
    return inputs, Stacked([s.model for s in inputs]), tuple(deltas)


class FusedInputs:
    """One subscription per sensor; a stamp goes to the runner once every sensor reported it
    (a sample or "nothing measured"), its parts gated; a repeat is answered again."""

    def __init__(self, node, runner, outputs, sensors: list[SensorInput], report, wait: float, refuse):
        self._node, self._runner, self._out, self._report = node, runner, outputs, report
        self._refuse = refuse  # Inputs._refuse: count, log, report
        self.sensors = sensors
        self._model = runner.estimator.measurement
        self.assembler = SampleAssembler(self._model, wait)
        self.gated = Counter()
        self.late = Counter()  # reports of a stamp already handed on that were not a resend

    def subscribe(self) -> list:
        """Subscribe to every sensor's topic; returns the subscriptions."""
        return [qos.subscription(self._node, self._node.events, MEASUREMENT_CLASSES[s.model.message_form], s.topic,
                                 partial(self.on_sample, i), qos.INPUT_QOS)
                for i, s in enumerate(self.sensors)]

    def on_sample(self, index: int, data: bytes) -> None:
        sensor, runner = self.sensors[index], self._runner
        self._node.peers.saw(sensor.topic)
        try:
            stamp_ns, z = read_measurement(sensor.model, data, sensor.frame_id)
        except MessageError as error:
            return self._refuse(runner.measurement_unreadable, f"{sensor.name}'s sample", error)
        kind, ready = self.assembler.offer(index, stamp_ns, z)
        if kind == 'repeat':  # a lockstep resend: the same answer
            if self._node.active and runner.has_measurement(stamp_ns) and self._out.resend(stamp_ns):
                runner.repeated()
            return
        if kind == 'late':
            self.late[sensor.name] += 1
            self._node.log('warning', f"{sensor.name}'s sample at {stamp_ns * 1e-9:.3f} s came after that "
                           'stamp was fused without it: not used')
            return
        self._deliver(ready)

    def expire(self) -> None:
        """Hand on the stamps a sensor's report never came for (lost), after the wait."""
        self._deliver(self.assembler.expired())

    def _deliver(self, ready) -> None:
        runner, now = self._runner, clock_ns(self._node)
        for stamp_ns, z in ready:
            if z is not None:
                z, gated = gate(runner.estimator, self._model, z, runner.measurement_covariance,
                                [s.gate for s in self.sensors])
                for i in gated:
                    self.gated[self.sensors[i].name] += 1
                    self._node.log('warning', f"{self.sensors[i].name}'s sample at {stamp_ns * 1e-9:.3f} s "
                                   f'is outside its gate ({self.sensors[i].gate}): dropped')
                if np.isnan(z).all():
                    z = None
            reason = runner.no_measurement(stamp_ns, now) if z is None else runner.measurement(stamp_ns, z, now)
            if reason is not None:
                self._report()

    def values(self) -> dict:
        values = {'sensors': ','.join(s.name for s in self.sensors),
                  'assembled_incomplete': self.assembler.incomplete}
        values.update({f'gated.{name}': n for name, n in sorted(self.gated.items())})
        values.update({f'late.{name}': n for name, n in sorted(self.late.items())})
        return values
