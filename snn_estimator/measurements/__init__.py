"""Measurement models: one module per sensor, the interface they share, and their registry.

What lives here: ``base.py`` (the interface :class:`MeasurementModel`: h(x) and its Jacobian
H(x) batched over runs, the residual with angles wrapped at +-pi, dimension, noise R, validity:
field of view, range limits, range > 0; the frame and angle conventions; the relative geometry
the sensor models share), one module per model, and :data:`MODELS` (name -> class) below.
Adding a sensor is one module plus one line in MODELS plus its tests (docs/adding_a_sensor.md).

What it may import: numpy and :mod:`snn_estimator.validation`, nothing else (no scipy, no
other core module, no ROS): the sensor node, the filters and the codec all use it.

Stone Soup's nonlinear measurement models (one class per sensor: function, jacobian, covar,
translation and rotation offsets, angle types that wrap) are the pattern; none of their code.
"""

from __future__ import annotations

from .base import (  # noqa: F401 (the interface, re-exported)
    DROPOUT,
    MESSAGE_FORMS,
    NON_FINITE,
    OBSERVERS,
    OUT_OF_VIEW,
    REASONS,
    SINGULAR,
    TOO_CLOSE,
    TOO_FAR,
    VALID,
    MeasurementModel,
    RelativeGeometry,
    rotation_from_quaternion,
    wrap_angle,
)
from .docking_camera import DockingCamera
from .position import Position, RelativeGPS
from .range_rate import RangeRate
from .ranging import Range
from .spherical import LineOfSight, RangeAzimuthElevation

#: name -> model class: the one list of measurement models (sensor node `model` parameter, docs).
MODELS: dict[str, type[MeasurementModel]] = {
    'position': Position,
    'range_azimuth_elevation': RangeAzimuthElevation,
    'line_of_sight': LineOfSight,
    'range': Range,
    'range_rate': RangeRate,
    'docking_camera': DockingCamera,
    'relative_gps': RelativeGPS,
}


def make_model(name: str, noise, **parameters) -> MeasurementModel:
    """The model ``name`` with noise R and those of ``parameters`` it takes (others ignored:
    a sensor node passes all its parameters)."""
    if name not in MODELS:
        raise ValueError(f"model must be one of {', '.join(MODELS)}; got {name!r}")
    cls = MODELS[name]
    return cls(noise, **{key: value for key, value in parameters.items() if key in cls.parameters})


__all__ = ['MODELS', 'MeasurementModel', 'REASONS', 'make_model', 'wrap_angle',
           'Position', 'RangeAzimuthElevation', 'LineOfSight', 'Range', 'RangeRate',
           'DockingCamera', 'RelativeGPS']
