"""The core objects a node's parameter values describe: the estimator's configuration, the CW
model, a measurement model, the Basilisk orbit, the silenced neurons."""

from __future__ import annotations

from snn_estimator import schema
from snn_estimator.config import EstimatorConfig, silenced_neurons

from .parameter_tables import SENSOR_GEOMETRY


def estimator_config(values: dict) -> EstimatorConfig:
    """The core configuration from the estimator node's parameter values (every schema field;
    silenced_neurons with silenced_fraction added)."""
    silenced = tuple(silenced_set(values, values['neuron_count'], values['seed']))
    return EstimatorConfig(**dict(schema.config_values(values), silenced_neurons=silenced))


def silenced_set(values: dict, neurons: int, seed: int) -> list[int]:
    """silenced_neurons plus a seeded random silenced_fraction of the N neurons
    (snn_estimator.config.silenced_neurons)."""
    return silenced_neurons(neurons, seed, values.get('silenced_fraction') or 0.0,
                            values.get('silenced_neurons') or ())


def orbit_settings(values: dict):
    """The Basilisk target orbit the basilisk_plant parameters describe (angles in deg)."""
    import math

    from snn_estimator.plant.basilisk_truth import OrbitSettings
    return OrbitSettings(
        semi_major_axis=values['orbit_radius'], eccentricity=values['eccentricity'],
        inclination=math.radians(values['inclination']), raan=math.radians(values['raan']),
        argument_of_perigee=math.radians(values['argument_of_perigee']),
        true_anomaly=math.radians(values['true_anomaly']), mu=values['gravitational_parameter'],
        j2=values['j2'])


def cw_model(values: dict, form: str = 'standard', measured_axes=(0, 1, 2)):
    """The CW model the parameters describe."""
    from snn_estimator import ClohessyWiltshire
    return ClohessyWiltshire(orbit_radius=values['orbit_radius'], mu=values['gravitational_parameter'],
                             form=form, measured_axes=tuple(measured_axes))


def filter_model(values: dict, measured_axes=(0, 1, 2)):
    """The estimator's model: ``dynamics_model`` cw (the ``cw_model`` form), nonlinear_circular or
    ss_j2 (at its default inclination, models.SchweighartSedwick)."""
    if values['dynamics_model'] == 'cw':
        return cw_model(values, form=values['cw_model'], measured_axes=measured_axes)
    from snn_estimator.models import relative_motion
    return relative_motion(values['dynamics_model'], orbit_radius=values['orbit_radius'],
                           mu=values['gravitational_parameter'], measured_axes=tuple(measured_axes))


def measurement_model(values: dict, noise, **limits):
    """The measurement model the parameters describe (snn_estimator.measurements): ``model`` with
    R ``noise`` in its units, the sensor geometry, and ``limits`` (field of view, range) where
    the caller has them."""
    from snn_estimator.measurements import make_model
    geometry = {spec.name: values[spec.name] for spec in SENSOR_GEOMETRY if spec.name != 'sensor_frame_id'}
    return make_model(values['model'], noise, measured_axes=tuple(int(a) for a in values['measured_axes']),
                      **geometry, **limits)


def approach_guidance(values: dict):
    """The approach guidance (snn_estimator.sim.approach's holds, legs, corridor and speeds) for
    the target orbit the parameters describe, with their observability manoeuvre."""
    from snn_estimator.sim.approach import approach_guidance as guidance
    return guidance(cw_model(values).mean_motion, manoeuvre=observability_manoeuvre(values))


def observability_manoeuvre(values: dict):
    """The core's ObservabilityManoeuvre the observability_* parameters describe (None: none);
    the core checks its size and delay, the guidance its hold."""
    if values['observability_manoeuvre'] == 'none':
        return None
    from snn_estimator.plant.approach import ObservabilityManoeuvre
    return ObservabilityManoeuvre(values['observability_hold'], values['observability_hop_size'],
                                  values['observability_hop_delay'])
