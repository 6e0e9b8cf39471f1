"""The names the layers share, without the code behind them: the filter kinds and the
estimator's start modes. The ROS parameter tables import these (a recorder or a sensor need not
load numba to know the valid ``filter_type`` values); the filters live in estimators.py."""

from __future__ import annotations

from typing import NamedTuple


class FilterKind(NamedTuple):
    """What a filter kind is made of."""

    gain: str            # kalman | msif | sif | msif_hybrid
    spiking: bool        # the state lives in a spiking network (Eq. 10-15)
    covariance: str      # riccati (Eq. 6) | gain (the covariance of the gain used) | none
    twin: str | None     # the non-spiking filter a spiking one implements
    label: str           # as tables and figures name it
    summary: str


#: The filter kinds, in the order tables list them.
FILTER_KINDS = {
    'ekf': FilterKind('kalman', False, 'riccati', None, 'EKF', 'extended Kalman filter (Eq. 3-6)'),
    'emsif': FilterKind('msif', False, 'riccati', None, 'EMSIF',
                        'extended modified sliding innovation filter as printed (Eq. 8-9)'),
    'esif': FilterKind('sif', False, 'none', None, 'ESIF', 'extended sliding innovation filter (Eq. 7)'),
    'emsif_hybrid': FilterKind('msif_hybrid', False, 'gain', None, 'EMSIF-H',
                               'EMSIF on the measured states, Kalman gain on the unmeasured ones'),
    'emsif_weighted': FilterKind('msif_weighted', False, 'gain', None, 'EMSIF-W',
                                 'EMSIF with the covariance-weighted inverse P C^T (C P C^T)^-1 for C^+'),
    'snn_ekf': FilterKind('kalman', True, 'riccati', 'ekf', 'SNN-EKF', 'SNN-EKF (Eq. 14-20)'),
    'snn_emsif': FilterKind('msif', True, 'riccati', 'emsif', 'SNN-EMSIF', 'SNN-EMSIF (Eq. 21-22)'),
    'snn_emsif_star': FilterKind('sif', True, 'none', 'esif', 'SNN-EMSIF*', 'SNN-EMSIF* (Eq. 23-24)'),
    'snn_emsif_hybrid': FilterKind('msif_hybrid', True, 'gain', 'emsif_hybrid', 'SNN-EMSIF-H',
                                   'spiking twin of emsif_hybrid'),
    'snn_emsif_weighted': FilterKind('msif_weighted', True, 'gain', 'emsif_weighted', 'SNN-EMSIF-W',
                                     'spiking twin of emsif_weighted'),
}
#: The non-spiking filter each spiking filter implements.
TWIN_OF = {kind: spec.twin for kind, spec in FILTER_KINDS.items() if spec.twin}
#: Kinds whose every run converges from a dispersed start on the rendezvous (final range below
#: 0.1 m); the literal (S)EMSIF/ESIF gains have zero velocity rows with position-only
#: measurements and do not, and the hybrid corrects the velocity too slowly
#: (results/rendezvous_dispersed.json).
CONVERGES_FROM_DISPERSION = ('ekf', 'emsif_weighted', 'snn_ekf', 'snn_emsif_weighted')
#: The spiking filter the estimator node runs unless told otherwise: the one that converges from
#: a dispersed start in the Monte Carlo of results/rendezvous_dispersed.json (docs/decisions.md, 17).
DEFAULT_FILTER = 'snn_ekf'
#: Filters of the paper (the others are this package's remedies).
PAPER_KINDS = ('ekf', 'emsif', 'esif', 'snn_ekf', 'snn_emsif', 'snn_emsif_star')

#: Start-up strategies of :meth:`snn_estimator.runner.FilterRunner.start` (``initialization``).
START_MODES = ('auto', 'parameters', 'last_estimate', 'history')
