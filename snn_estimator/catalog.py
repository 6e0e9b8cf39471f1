"""The names the layers share, without the code behind them: the filter kinds (declared by
their gain laws, snn_estimator.gains, numpy only) and the estimator's start modes. The ROS
parameter tables import these (a recorder or a sensor need not load numba to know the valid
``filter_type`` values); the filters live in estimators.py."""

from __future__ import annotations

from typing import NamedTuple

from . import gains


class FilterKind(NamedTuple):
    """What a filter kind is made of."""

    gain: str            # the gain law: a module of snn_estimator.gains
    spiking: bool        # the state lives in a spiking network (Eq. 10-15)
    covariance: str      # riccati (Eq. 6) | gain (the covariance of the gain used) | none
    twin: str | None     # the non-spiking filter a spiking one implements
    label: str           # as tables and figures name it
    summary: str


def _filter_kinds() -> dict:
    """The kinds each gain law declares (snn_estimator.gains, ``KINDS``: its direct filter, then
    the spiking twin): the direct filters in the laws' order, then their spiking twins."""
    direct, spiking = {}, {}
    for name, law in gains.laws().items():
        if not law.KINDS:
            continue
        (kind, (label, summary)), (twin, (twin_label, twin_summary)) = law.KINDS.items()
        direct[kind] = FilterKind(name, False, law.COVARIANCE, None, label, summary)
        spiking[twin] = FilterKind(name, True, law.COVARIANCE, kind, twin_label, twin_summary)
    return {**direct, **spiking}


#: The filter kinds, in the order tables list them.
FILTER_KINDS = _filter_kinds()
#: The non-spiking filter each spiking filter implements.
TWIN_OF = {kind: spec.twin for kind, spec in FILTER_KINDS.items() if spec.twin}
#: Kinds whose every run converges from a dispersed start on the rendezvous (final range below
#: 0.1 m); the literal (S)EMSIF/ESIF gains have zero velocity rows with position-only
#: measurements and do not (results/rendezvous_dispersed.json).
CONVERGES_FROM_DISPERSION = ('ekf', 'emsif_weighted', 'snn_ekf', 'snn_emsif_weighted')
#: The spiking filter the estimator node runs unless told otherwise: the one that converges from
#: a dispersed start in the Monte Carlo of results/rendezvous_dispersed.json (docs/decisions.md, 17).
DEFAULT_FILTER = 'snn_ekf'
#: Filters of the paper (the others are this package's remedies).
PAPER_KINDS = ('ekf', 'emsif', 'esif', 'snn_ekf', 'snn_emsif', 'snn_emsif_star')

def kinds_table() -> str:
    """:data:`FILTER_KINDS` as a reST table (the estimators module docstring)."""
    rows = [(f'``{kind}``', spec.label, spec.gain, spec.covariance,
             'spiking network (Eq. 10-15)' if spec.spiking else 'direct (Eq. 3)', spec.summary)
            for kind, spec in FILTER_KINDS.items()]
    head = ('kind', 'label', 'gain law', 'covariance', 'state integration', 'what it is')
    widths = [max(len(row[i]) for row in rows + [head]) for i in range(len(head))]
    rule = '  '.join('=' * w for w in widths)
    line = lambda row: '  '.join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip()  # noqa: E731
    return '\n'.join([rule, line(head), rule, *map(line, rows), rule])


#: Start-up strategies of :meth:`snn_estimator.runners.filter_runner.FilterRunner.start` (``initialization``).
START_MODES = ('auto', 'parameters', 'last_estimate', 'history')
#: How measurement stamps relate to the filter's steps (``measurement_timing``; the rule in
#: :mod:`snn_estimator.runners.filter_runner`, docs/decisions.md, 31).
MEASUREMENT_TIMINGS = ('grid', 'any')
