"""Gain laws: one module per law K(P, nu) of Eq. 5-9 / 19-24 (and this package's remedies).

Each module holds everything about its law: its name, formula and paper equation; its
``reference`` form (numpy, written from the paper, used by snn_estimator.filters.reference and the tests);
its compiled ``gain`` piece (plain Python loops that snn_estimator.filters.kernels compiles into one
kernel per law, covariance law and integration); its ``steady_state`` form (the constant gain
at the fixed point of Eq. 6); its ``macs`` (what snn_estimator.spiking.costs counts); and its filter
kinds (``KINDS``: the direct filter and its spiking twin, which snn_estimator.catalog lists).
A module may build on another law (``BASE``: its piece runs after the base's, e.g. the weighted
law rescales MSIF's saturations).

Imports: numpy (scipy inside a function) and other law modules only; never numba (the kernels
compile the pieces), the filters, the models or anything outside the core. A new law is one
module here (found by :func:`laws`, ordered by ``ORDER``), its kinds included.
"""

from __future__ import annotations

import importlib
import pkgutil
from functools import lru_cache
from typing import NamedTuple

import numpy as np

#: The constants a law's compiled ``gain`` piece receives as ``consts``, in this order (the
#: step kernel's, snn_estimator.filters.kernels.CONSTANTS, gives their shapes): H and its
#: pseudo-inverse, the process noise of a step Q_d, a sample's variance R_d, diag(R_hat), delta,
#: the network's state scale, a constant gain, the leak, the spike cap, per measured component
#: the step dt where the boundary layer is variable (0: fixed; msif.py), and the synchronous
#: rule's ticks per sample, threshold widening, refractory ticks and firing slots.
PIECE_CONSTANTS = ('c', 'c_pinv', 'q_step', 'r_sample', 'r_hat_diag', 'delta', 'scale', 'fixed_gain', 'leak',
                   'max_spikes', 'layer_step', 'ticks', 'widening', 'refractory', 'slots')
(C, C_PINV, Q_STEP, R_SAMPLE, R_HAT_DIAG, DELTA, SCALE, FIXED_GAIN, LEAK, MAX_SPIKES, LAYER_STEP, TICKS, WIDENING,
 REFRACTORY, SLOTS) = range(len(PIECE_CONSTANTS))


class SampledStep(NamedTuple):
    """What the Kalman gain of a sampled step needs (docs/decisions.md, 43): Phi over the step,
    the step dt, and R_d, the variance of a sample (the R of Eq. 5-6 over dt)."""

    phi: np.ndarray
    dt: float
    r_sample: np.ndarray


def sampled_kalman(p: np.ndarray, c: np.ndarray, step: SampledStep) -> np.ndarray:
    """The Kalman gain of a sampled step as a rate: Phi P C^T (C P C^T + R_d)^-1 / dt, the
    one-step predictor's gain over dt; P C^T R^-1 (Eq. 5) as dt -> 0."""
    return step.phi @ p @ c.T @ np.linalg.inv(c @ p @ c.T + step.r_sample) / step.dt


class SteadyState(NamedTuple):
    """What the steady-state forms need: P_ss (the fixed point of the sampled step of Eq. 6),
    C, C^+, a sample's variance R_d, R_hat per sample, delta, and the Kalman gain at P_ss (a
    rate, :func:`sampled_kalman`)."""

    p: np.ndarray
    c: np.ndarray
    c_pinv: np.ndarray
    r_sample: np.ndarray
    r_hat: np.ndarray
    delta: np.ndarray
    kalman: np.ndarray


@lru_cache(maxsize=None)
def laws() -> dict:
    """Law name -> module, in ``ORDER`` (the order tables list them)."""
    modules = [importlib.import_module(f'{__name__}.{info.name}') for info in pkgutil.iter_modules(__path__)
               if not info.name.startswith('_')]
    return {module.NAME: module for module in sorted(modules, key=lambda module: module.ORDER)}


def law(name: str):
    """The module of gain law ``name``; ValueError naming the choices otherwise."""
    found = laws().get(name)
    if found is None:
        raise ValueError(f'unknown gain law {name!r}; choose one of {", ".join(laws())}')
    return found


def table() -> str:
    """The laws as a reST table (docs, the estimators module docstring)."""
    rows = [(f'``{name}``', module.FORMULA, module.EQUATION) for name, module in laws().items()]
    widths = [max(len(row[i]) for row in rows + [('law', 'gain K', 'equations')]) for i in range(3)]
    rule = '  '.join('=' * w for w in widths)
    line = lambda row: '  '.join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip()  # noqa: E731
    return '\n'.join([rule, line(('law', 'gain K', 'equations')), rule, *map(line, rows), rule])
