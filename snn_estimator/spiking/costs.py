"""What one estimate costs: synaptic operations and neuron updates of the spiking network, the
multiply-accumulates of the dense N x N formulation and of the non-spiking filter, and the
energy those operations take on published neuromorphic chips.

Counting model (the constant-weight network that ``snn_export`` writes, run event-driven):

* a spike of neuron i is delivered along its fast connections (Omega_f, Eq. 18: N - 1
  targets, its own term -||D_i||^2 being the reset), its slow connections (Omega_s + Omega_k,
  Eq. 17, 19/21/23: N targets) and the readout (S D, Eq. 12: n targets). The slow path is
  counted event-driven: the filtered trains r feed Omega r, and since every r_i decays with
  the same lambda (Eq. 11), Omega r is itself a synaptic current that jumps by Omega[:, i] at
  a spike of i and decays with lambda; the readout likewise. Applied literally (Omega times
  r every step) the slow path costs N^2 per step, which is what the dense count holds;
* the measurement and the control are graded inputs every step: N (m + nu) operations
  (F_k z + F u, Eq. 16, 20/22/24);
* per tick every neuron advances its membrane and its slow synaptic current, and each of the
  n readout traces decays: 2 N + n state updates (``ticks`` chip time steps per estimate);
* with a time-varying gain the host also refreshes F_k = D^T S^-1 K and
  Omega_k = -F_k C S D every step (N n m + N^2 m MACs) after computing K and P as the
  non-spiking filter does.

The dense count is the paper's algebra evaluated per step as :mod:`snn_estimator.filters.reference`
does: (Omega_s + Omega_k) r as an N x N product, F u, F_k z, the leak of v and r, one Omega_f
column per spike and the decoding S D r. The non-spiking count follows the loops of the
step kernels (snn_estimator.filters.kernels; the laws' ``macs`` in snn_estimator.gains) for n states,
m measurements and nu inputs.

numpy only: the ROS estimator calls :meth:`CostModel.step` every diagnostics period.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np

from snn_estimator import gains

#: Covariance laws of the filters (estimators.FILTER_KINDS): Eq. 6, the covariance of the gain
#: used, or none.
COVARIANCE_LAWS = ('riccati', 'gain', 'none')


class Chip(NamedTuple):
    """Published energy per operation of a neuromorphic chip, picojoules."""

    label: str
    synop_pj: float          # one synaptic operation (a spike delivered to one target)
    neuron_update_pj: float  # one compartment update per tick
    spike_pj: float          # extra per spike emitted (active update, routing)
    source: str
    note: str


#: Per-operation figures; static and leakage power are not per-operation and are left out
#: (except where a figure is all-in, as TrueNorth's, which says so).
CHIPS = {
    'loihi': Chip(
        'Intel Loihi', 23.6, 52.0, (81.0 - 52.0) + 1.7,
        'Davies et al. 2018, "Loihi: A Neuromorphic Manycore Processor with On-Chip Learning", '
        'IEEE Micro 38(1):82-99, Table 2',
        'pre-silicon estimates at 0.75 V: 23.6 pJ per synaptic spike op (min), 52 pJ per '
        'inactive and 81 pJ per active neuron update (a spiking neuron charged the difference), '
        '1.7 pJ per within-tile spike; no static power'),
    'spinnaker2': Chip(
        'SpiNNaker 2 (prototype)', 450.0, 2190.0, 0.0,
        'Hoeppner et al. 2019, "Dynamic Power Management for Neuromorphic Many-Core Systems", '
        'IEEE TCAS-I 66(8):2973-2986, arXiv:1903.08941',
        '450 pJ per synaptic event and 2.19 nJ per neuron update (28 nm test chip, software '
        'neurons on ARM cores); figures from a literature search, not re-read in the paper here'),
    'truenorth': Chip(
        'IBM TrueNorth', 26.0, 0.0, 0.0,
        'Merolla et al. 2014, "A million spiking-neuron integrated circuit with a scalable '
        'communication network and interface", Science 345(6197):668-673',
        'all-in: total chip energy (passive plus active) per synaptic event at one operating '
        'point (20 Hz, 128 active synapses per neuron, 0.775 V); neuron updates and leakage '
        'are inside the 26 pJ, so none are charged separately'),
}


#: One 32-bit floating-point multiply-accumulate, arithmetic only: 3.7 pJ multiply + 0.9 pJ add
#: at 45 nm and 0.9 V. Memory access and control, which dominate on a real CPU, are excluded:
#: a lower bound for the dense and non-spiking MAC counts.
FLOAT32_MAC_PJ = 3.7 + 0.9
FLOAT32_MAC_SOURCE = ('Horowitz 2014, "Computing\'s energy problem (and what we can do about it)", '
                      'IEEE ISSCC 2014, pp. 10-14: 45 nm, 0.9 V, float32 multiply 3.7 pJ, add 0.9 pJ')


class StepCosts(NamedTuple):
    """Operations of one estimate (or arrays of them, one per step)."""

    spikes: float | np.ndarray
    synops: float | np.ndarray            # spiking network, event-driven
    neuron_updates: float | np.ndarray    # compartment/trace updates of the network
    host_macs: float | np.ndarray         # time-varying gain: K, P and the weight refresh
    dense_macs: float | np.ndarray        # the paper's N x N algebra per step
    nonspiking_macs: float | np.ndarray   # the non-spiking twin filter's step


@dataclass(frozen=True)
class CostModel:
    """Operation counts of one spiking filter: N neurons, n states, m measurements, nu inputs,
    its gain law (a module of snn_estimator.gains) and covariance law, and
    whether the gain (and so every weight) is constant. ``ticks``: chip time steps per
    estimate (1: the network is integrated once per sample and its spikes resolved in place,
    as the package's kernel does)."""

    neurons: int
    states: int
    measurements: int
    inputs: int
    gain_law: str = 'kalman'
    covariance_law: str = 'riccati'
    constant_gain: bool = True
    ticks: int = 1

    def __post_init__(self):
        for name in ('neurons', 'states', 'measurements', 'inputs', 'ticks'):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < (0 if name == 'inputs' else 1):
                raise ValueError(f'{name} must be a positive integer (inputs may be 0), got {value!r}')
        if self.gain_law not in gains.laws():
            raise ValueError(f'gain_law {self.gain_law!r} is unknown; choose one of {", ".join(gains.laws())}')
        if self.covariance_law not in COVARIANCE_LAWS:
            raise ValueError(f'covariance_law {self.covariance_law!r} is unknown; choose one of '
                             f'{", ".join(COVARIANCE_LAWS)}')

    @classmethod
    def of(cls, estimator, ticks: int = 1) -> CostModel:
        """The cost model of a spiking ``estimator`` (an ``Estimator``)."""
        if not estimator.spiking:
            raise ValueError(f'{estimator.kind} is not a spiking filter: it has no synaptic operations')
        model = estimator.model
        return cls(estimator.neuron_count, model.n_state, model.n_meas, model.n_input,
                   estimator.gain_law, estimator.covariance_law, estimator.constant_gain, ticks)

    # ------------------------------------------------------------------ spiking network
    @property
    def synops_per_spike(self) -> int:
        """Targets of one spike: N - 1 fast (Eq. 18, the self term is the reset), N slow
        (Eq. 17 + 19/21/23) and n readout (Eq. 12)."""
        return 2 * self.neurons - 1 + self.states

    @property
    def input_synops(self) -> int:
        """Graded inputs every step: F_k z and F u (Eq. 16, 20/22/24)."""
        return self.neurons * (self.measurements + self.inputs)

    @property
    def neuron_updates(self) -> int:
        """State updates per estimate: membrane and slow current of each neuron, readout traces."""
        return self.ticks * (2 * self.neurons + self.states)

    @property
    def weight_refresh_macs(self) -> int:
        """Host MACs per step to rewrite F_k = D^T S^-1 K and Omega_k = -F_k C S D (0 with a
        constant gain)."""
        if self.constant_gain:
            return 0
        n, m, big_n = self.states, self.measurements, self.neurons
        return big_n * n * m + big_n * big_n * m

    # ------------------------------------------------------------------ dense and non-spiking
    @cached_property
    def dense_macs_per_step(self) -> int:
        """The spike-independent part of the literal per-step algebra
        (reference.DenseSpikingFilter with the weights held when constant): (Omega_s + Omega_k) r
        as an N x N product, F u, F_k z, the leak of v and r, decoding S D r; plus K, P and the
        weight refresh when the gain varies. Each spike adds one Omega_f column (N)."""
        big_n, n = self.neurons, self.states
        return big_n * big_n + self.input_synops + 2 * big_n + n * big_n + self.host_macs_per_step

    @cached_property
    def host_macs_per_step(self) -> int:
        """Gain and covariance of a time-varying gain (as the twin computes them) and the
        weight refresh; 0 with a constant gain."""
        if self.constant_gain:
            return 0
        parts = filter_macs(self.states, self.measurements, self.inputs, self.gain_law, self.covariance_law)
        return parts['gain'] + parts['covariance'] + self.weight_refresh_macs

    @cached_property
    def nonspiking_macs(self) -> int:
        """MACs of one step of the non-spiking twin: the time-varying filter of the paper, or,
        with a constant gain, its state update alone (K fixed, no P needed)."""
        parts = filter_macs(self.states, self.measurements, self.inputs, self.gain_law,
                            'none' if self.constant_gain else self.covariance_law,
                            constant_gain=self.constant_gain)
        return sum(parts.values())

    # ------------------------------------------------------------------ per step
    def step(self, spikes) -> StepCosts:
        """Costs of estimates that emitted ``spikes`` spikes: an int (a few integer operations,
        cheap enough for every step of a node), or an array of per-step counts for a run."""
        if np.ndim(spikes):
            spikes = np.asarray(spikes, dtype=np.int64)
            ones = np.ones_like(spikes)
        else:
            spikes, ones = int(spikes), 1
        return StepCosts(spikes, spikes * self.synops_per_spike + self.input_synops,
                         self.neuron_updates * ones, self.host_macs_per_step * ones,
                         self.dense_macs_per_step + self.neurons * spikes, self.nonspiking_macs * ones)


def energy_pj(costs: StepCosts, chip: Chip | str):
    """Energy of the network's operations in ``costs`` on ``chip`` (a :class:`Chip` or a key of
    :data:`CHIPS`), picojoules: synops x synop_pj + updates x neuron_update_pj + spikes x
    spike_pj. Host MACs of a time-varying gain and static power are not included."""
    if isinstance(chip, str):
        if chip not in CHIPS:
            raise ValueError(f'chip {chip!r} is unknown; choose one of {", ".join(CHIPS)}')
        chip = CHIPS[chip]
    return (np.asarray(costs.synops) * chip.synop_pj + np.asarray(costs.neuron_updates) * chip.neuron_update_pj
            + np.asarray(costs.spikes) * chip.spike_pj)


def filter_macs(n: int, m: int, nu: int, gain_law: str, covariance_law: str,
                constant_gain: bool = False) -> dict:
    """MACs of one step of the non-spiking filter (the step kernels), by part:

    innovation z - C x_hat (m n); gain: P C^T (n^2 m) when the law reads P, and for the Kalman
    gain of the sampled step (the law's, or the covariance's with ``riccati``) also C P C^T + R_d
    (its triangle, n m(m+1)/2), its Cholesky factor ((m^3 - m)/6), the solve (n m (m - 1)) and
    (I / dt + A_d) K_d (n^2 m), then the law's own products (its ``macs``) (none with a constant
    gain); state: A_d x_hat + B_d u + K nu and x_hat += dt increment (n^2 + n nu + n m + n);
    covariance (Joseph's form of the sampled step, docs/decisions.md, 43): Phi - G C
    (n^2 (m + 1)), (Phi - G C) P (n^3), its product with (Phi - G C)^T and G R_d G^T (upper
    triangles: n(n+1)/2 (n + m), and G R_d: n m^2), and the guard's Cholesky factor of P
    ((n^3 - n)/6).

    For n = 6, m = 3, nu = 3 the EKF (kalman, riccati) takes 18 + 292 + 78 + 638 = 1026 (the
    forward-Euler step of Eq. 6 it replaced took 537).
    """
    law = gains.law(gain_law)  # ValueError naming the laws
    if covariance_law not in COVARIANCE_LAWS:
        raise ValueError(f'covariance_law {covariance_law!r} is unknown; choose one of {", ".join(COVARIANCE_LAWS)}')
    triangle = n * (n + 1) // 2
    p_terms = n * n * m

    def cholesky(k: int) -> int:
        return (k ** 3 - k) // 6

    kalman = p_terms + n * m * (m + 1) // 2 + cholesky(m) + n * m * (m - 1) + n * n * m
    terms = kalman if law.USES_KALMAN or covariance_law == 'riccati' else p_terms if law.USES_P else 0
    gain = 0 if constant_gain else terms + law.macs(n, m)
    joseph = n * n * (m + 1) + n ** 3 + triangle * (n + m) + n * m * m + cholesky(n)
    covariance = 0 if covariance_law == 'none' else joseph
    return {'innovation': m * n, 'gain': gain, 'state': n * n + n * nu + n * m + n, 'covariance': covariance}
