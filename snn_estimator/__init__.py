"""snn_estimator: the ROS-free core of snn_rendezvous.

Models (Clohessy-Wiltshire, Van der Pol), the EKF / EMSIF filters and their spiking-network
implementations (SNN-EKF, SNN-EMSIF, SNN-EMSIF*), LQR design and the offline closed loop.
Nothing here imports rclpy.
"""

from .config import EstimatorConfig, SPIKE_RULES
from .estimators import FILTER_KINDS, TWIN_OF, Estimator, make_estimator
from .models import ClohessyWiltshire, StateSpaceModel, VanDerPol
from .simulation import (Plant, PositionSensor, Scenario, lqr_control, lqr_gain,
                         rendezvous_scenario, simulate, van_der_pol_scenario)

__all__ = [
    'ClohessyWiltshire', 'Estimator', 'EstimatorConfig', 'FILTER_KINDS', 'Plant', 'PositionSensor',
    'SPIKE_RULES', 'Scenario', 'StateSpaceModel', 'TWIN_OF', 'VanDerPol', 'lqr_control', 'lqr_gain',
    'make_estimator', 'rendezvous_scenario', 'simulate', 'van_der_pol_scenario',
]
