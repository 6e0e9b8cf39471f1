"""snn_estimator: the ROS-free core of snn_rendezvous.

Models (Clohessy-Wiltshire, Van der Pol), the EKF / EMSIF filters and their spiking-network
implementations (SNN-EKF, SNN-EMSIF, SNN-EMSIF*, and the weighted EMSIF for partial measurements),
LQR design, the simulated closed loop and the runner that feeds a filter from a message stream.
Nothing here imports rclpy or matplotlib.

Layout (each folder's ``__init__`` says what lives there and what it may import):

* the foundation, importing only each other: ``models`` (dynamics), ``schema`` / ``config`` /
  ``defaults`` / ``validation`` (one parameter schema), ``catalog`` (filter kinds);
* ``gains/`` (one module per gain law), ``measurements/`` (one module per sensor model);
* ``filters/`` (the Estimator, its kernels, the reference forms), ``spiking/`` (networks, the
  chip, the spiking LQR, costs);
* ``plant/`` (the truth, the sensors and the LQR around the estimator), ``runners/`` (what the
  ROS nodes wrap: the filter runner, the plant runner), ``sim/`` (scenarios and simulate()).

The names below load on first use (PEP 562), so ``import snn_estimator`` costs nothing and a
process that needs only the models (a plant node) never compiles the spiking kernels or loads
python-control.
"""

import importlib

_EXPORTS = {
    'EstimatorConfig': 'config', 'SPIKE_RULES': 'config',
    'FILTER_KINDS': 'catalog', 'TWIN_OF': 'catalog', 'Estimator': 'filters.estimators',
    'make_estimator': 'filters.estimators',
    'ClohessyWiltshire': 'models', 'NonlinearCircular': 'models', 'SchweighartSedwick': 'models',
    'StateSpaceModel': 'models', 'VanDerPol': 'models',
    'Plant': 'plant.truth', 'PositionSensor': 'plant.sensors', 'Scenario': 'sim.scenarios',
    'lqr_control': 'plant.control', 'lqr_gain': 'plant.control', 'rendezvous_scenario': 'sim.scenarios',
    'simulate': 'sim.simulate', 'van_der_pol_scenario': 'sim.scenarios',
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    value = getattr(importlib.import_module(f'.{module}', __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
