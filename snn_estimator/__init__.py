"""snn_estimator: the ROS-free core of snn_rendezvous.

Models (Clohessy-Wiltshire, Van der Pol), the EKF / EMSIF filters and their spiking-network
implementations (SNN-EKF, SNN-EMSIF, SNN-EMSIF*, and the hybrids for partial measurements),
LQR design, the offline closed loop and the runner that feeds a filter from a message stream.
Nothing here imports rclpy or matplotlib.

The names below load on first use (PEP 562), so ``import snn_estimator`` costs nothing and a
process that needs only the models (a plant node) never compiles the spiking kernels or loads
python-control.
"""

import importlib

_EXPORTS = {
    'EstimatorConfig': 'config', 'SPIKE_RULES': 'config',
    'FILTER_KINDS': 'catalog', 'TWIN_OF': 'catalog', 'Estimator': 'estimators',
    'make_estimator': 'estimators',
    'ClohessyWiltshire': 'models', 'StateSpaceModel': 'models', 'VanDerPol': 'models',
    'Plant': 'blocks', 'PositionSensor': 'blocks', 'Scenario': 'simulation',
    'lqr_control': 'blocks', 'lqr_gain': 'blocks', 'rendezvous_scenario': 'simulation',
    'simulate': 'simulation', 'van_der_pol_scenario': 'simulation',
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
