"""The exported synchronous network rewritten for a reader that steps LIF neurons by explicit Euler
at one tick, emits a spike as 1 in its tick, and resets a neuron to 0 (Norse's ``from_nir``, GitHub
master; docs/decisions.md, 60 and 71). ``nir`` (the neuromorphic extra) and numpy only: it takes only the ``.nir`` file
:mod:`.nir_export` writes (``spike_rule: synchronous``) and writes another NIR graph.

What such a reader does with a LIF (``tau``, ``v_threshold``; ``r`` and ``v_reset`` ignored)::

    v <- v + dt/tau (-v + I);   s = [v > v_threshold];   v <- 0 where s

and with a LI: ``x <- x + dt/tau (-x + I)``. So every current is written as ``I = tau a`` for a
rate a (v' += a) and ``I = (tau/dt) J`` for a jump J per tick; a spike reaches the LI of the
spike trains through ``diag(tau/dt)``. An edge that closes a cycle carries the previous tick's
output, so the fast connections of a tick's spikes act at the next tick: the synchronous rule.

The slow connections (Omega_s + Omega_k, Eq. 17-23) act in the package with r at the start of
the sample, held over its T ticks: the sample's drive is Eq. 14's, computed once from x_hat_k. A
reader that ticks the recurrent edge trains -> neurons instead lets them act within the sample, a
continuous-time network around a gain designed for the sampled filter; it follows the
measurements more slowly (Norse: 3x the package's position RMSE at 10 s over 20 runs, with the
same spike counts; docs/decisions.md, 71). NIR has no sample-and-hold, so the host holds it: the
graph takes the decoded estimate of the sample before as an input, through (Omega_s + Omega_k)
(S D)^+ (exact: those rows lie in the row space of D).

The graph has one Input, ``[z (m), u (nu), x_hat_k (n), gate (N)]``: z, u and x_hat_k held over
the sample, the gate fed per tick by :func:`gate_inputs` (neuron i may fire only in the ticks
with (t + i) mod K = 0; NIR has no field for it). Every threshold is 1 (each neuron's rows
divided by its widened threshold), so the neurons of all runs have the same parameters and differ
only in Linear weights.

Two forms (``form``):

* ``comparator`` (default, exact): the potential is a LI node (``potential``, tau = 1/lambda)
  that nothing resets; it receives the full Omega_f of Eq. 18, its diagonal (the reset by
  subtraction of ||D_i||^2) included, and the gate. The LIF has tau = one tick and one input, so
  Euler makes it memoryless (v = its input each tick) and the reader computes it after the
  potential of the same tick: it compares the potential with 1, and its reset to 0 loses
  nothing. Two compartments per neuron, as a chip's multi-compartment neuron.
* ``diagonal`` (one compartment): the LIF holds the potential; after its reset to 0 the fast
  diagonal adds the rest of the subtraction, -(||D_i||^2 - threshold_i). The overshoot above
  threshold at the spike (up to K ticks of drive while the neuron waits for its slot) is lost.
"""

from __future__ import annotations

import nir
import numpy as np

from .nir_export import network_arrays

FORMS = ('comparator', 'diagonal')
#: How far below its threshold the gate holds a neuron outside its firing slots (in thresholds).
GATE_DEPTH = 1.0e3
INPUT, NEURONS, TRAINS, POTENTIAL, OUTPUT = 'input', 'neurons', 'trains', 'potential', 'output'


def reset_to_zero_graph(graph, form: str = 'comparator'):
    """The NIR graph a reset-to-zero, one-tick Euler reader runs as the synchronous rule of ``graph``
    (a graph written by nir_export.network_graph with spike_rule synchronous). ValueError naming
    the fix for any other graph, a refractory period, or an unknown ``form``."""
    if form not in FORMS:
        raise ValueError(f"form must be one of {', '.join(FORMS)}; got {form!r}")
    net = network_arrays(graph)
    meta = net.metadata
    if meta.get('spike_rule') != 'synchronous':
        raise ValueError(f"the graph's spike_rule is {meta.get('spike_rule')!r}: export the network with "
                         'spike_rule synchronous (the tick is what a one-tick reader steps)')
    if int(meta['refractory_ticks']) != 0:
        raise ValueError('refractory_ticks > 0 has no field in a NIR LIF and no reader here counts it: '
                         'export with refractory_ticks 0')
    tick = float(meta['tick_s'])
    neurons, m, nu = net.threshold.size, net.measurement.shape[1], net.control.shape[1]
    n = net.decoder.shape[0]
    threshold = net.threshold
    # time constants whose Euler step at the tick leaks exactly as the package's tick does,
    # (1 - lambda dt)^(1/T) (1 - tick/tau to first order); a tick's spikes reach the potential
    # at the next tick, after its leak, where the package subtracts them before it: times keep
    ticks, sample = int(meta['ticks_per_sample']), float(meta['sample_period'])
    keep_v = np.exp(np.log1p(-sample / net.tau_v) / ticks)
    tau_v = tick / (1.0 - keep_v)
    tau_r = tick / (1.0 - np.exp(np.log1p(-sample / net.tau_r) / ticks))
    unit = 1.0 / threshold[:, None]                 # rows into neuron i in thresholds of i
    omega_f = net.omega_f                           # the jump per spike, reset on the diagonal
    # the slow loop, held over the sample as the package holds it: (Omega_s + Omega_k) r_k =
    # (Omega_s + Omega_k) (S D)^+ x_hat_k, exact because its rows lie in the row space of D
    slow_from_estimate = net.slow @ np.linalg.pinv(net.decoder)
    drive = np.zeros((neurons, m + nu + n + neurons))
    drive[:, :m] = tau_v[:, None] * net.measurement
    drive[:, m:m + nu] = tau_v[:, None] * net.control
    drive[:, m + nu:m + nu + n] = tau_v[:, None] * slow_from_estimate
    drive = unit * drive
    drive[:, m + nu + n:] = np.diag(tau_v / tick)   # the gate, already in thresholds: a jump per tick
    fast_jump = (tau_v / tick * keep_v)[:, None]
    ones, zeros = np.ones(neurons), np.zeros(neurons)
    initial_v = net.initial_v / threshold + gate_offsets(neurons, ticks, int(meta['firing_slots']))[-1]
    nodes = {
        INPUT: nir.Input(input_type={'input': np.array([m + nu + n + neurons])}),
        'drive': nir.Linear(weight=drive),
        'spike_to_train': nir.Linear(weight=np.diag(tau_r / tick * net.train_jump)),
        TRAINS: nir.LI(tau=tau_r.copy(), r=ones.copy(), v_leak=zeros.copy(),
                       metadata={'initial_state': net.initial_r, 'equation': "r' = -lambda r + s (Eq. 11)"}),
        'decoder': nir.Linear(weight=net.decoder.copy(), metadata={'equation': 'x_hat = S D r (Eq. 12)'}),
        OUTPUT: nir.Output(output_type={'output': np.array([n])}),
    }
    edges = [(INPUT, 'drive'), (NEURONS, 'spike_to_train'), ('spike_to_train', TRAINS), (TRAINS, 'decoder'),
             ('decoder', OUTPUT)]
    if form == 'comparator':
        # the potential (in thresholds, the gate's offset in it) integrates and is never reset; the
        # LIF only compares: tau = tick makes Euler's v equal to its one input every tick, and
        # with one input the reader computes it after the potential of the same tick
        nodes.update({
            POTENTIAL: nir.LI(tau=tau_v.copy(), r=ones.copy(), v_leak=zeros.copy(), metadata={
                'initial_state': initial_v, 'equation': "v' = -lambda v + I (Eq. 15) / threshold, never reset"}),
            'fast': nir.Linear(weight=unit * fast_jump * omega_f,
                               metadata={'equation': 'Omega_f (Eq. 18), its reset diagonal included'}),
            'compare': nir.Linear(weight=np.eye(neurons)),
            NEURONS: nir.LIF(tau=np.full(neurons, tick), r=ones.copy(), v_leak=zeros.copy(), v_threshold=ones.copy(),
                             v_reset=zeros.copy(), metadata={'initial_v': zeros.copy(),
                                                             'meaning': 'comparator: v = its input each tick'}),
        })
        edges += [('drive', POTENTIAL), (NEURONS, 'fast'), ('fast', POTENTIAL), (POTENTIAL, 'compare'),
                  ('compare', NEURONS)]
    else:
        diagonal_rest = omega_f + np.diag(threshold)   # the reset to 0 already took threshold_i off
        nodes.update({
            NEURONS: nir.LIF(tau=tau_v.copy(), r=ones.copy(), v_leak=zeros.copy(), v_threshold=ones.copy(),
                             v_reset=zeros.copy(), metadata={'initial_v': initial_v}),
            'fast': nir.Linear(weight=unit * fast_jump * diagonal_rest),
        })
        edges += [('drive', NEURONS), (NEURONS, 'fast'), ('fast', NEURONS)]
    metadata = dict(meta)
    metadata.update({
        'reader_profile': f'reset_to_zero/{form}',
        'reader': ('explicit Euler at dt = tick_s (LIF and LI, r = 1), a spike is 1 in its tick, a LIF resets '
                   'to 0 and fires when v > v_threshold = 1; edges closing a cycle carry the previous tick'),
        'input_layout': (f'one Input of {m + nu + n + neurons}: z ({m}), u ({nu}) and the decoded estimate '
                         f'x_hat ({n}) of the sample before, held over the sample; gate ({neurons}) per tick '
                         '(gate_inputs)'),
        'gate_depth': GATE_DEPTH,
    })
    return nir.NIRGraph(nodes=nodes, edges=edges, metadata=metadata)


def gate_offsets(neurons: int, ticks: int, slots: int) -> np.ndarray:
    """(ticks, N): 0 in neuron i's firing slots ((t + i) mod K = 0), -GATE_DEPTH (thresholds) elsewhere."""
    t, i = np.arange(ticks)[:, None], np.arange(neurons)[None, :]
    return np.where((t + i) % slots == 0, 0.0, -GATE_DEPTH)


def gate_inputs(graph) -> np.ndarray:
    """(ticks_per_sample, N): the gate part of the Input, tick by tick, for a graph written by
    :func:`reset_to_zero_graph`. The potential (the comparator's LI, the diagonal form's LIF) holds
    the offset, so it is fed as a jump per tick: this tick's offset minus what the leak left of the
    last one (tick 0 follows the last tick of the previous sample; the initial state holds it)."""
    meta = graph.metadata
    ticks, slots, tick = int(meta['ticks_per_sample']), int(meta['firing_slots']), float(meta['tick_s'])
    holder = graph.nodes[POTENTIAL if POTENTIAL in graph.nodes else NEURONS]
    offsets = gate_offsets(int(meta['neurons']), ticks, slots)
    keep = 1.0 - tick / np.asarray(holder.tau, dtype=float)
    return offsets - keep * np.roll(offsets, 1, axis=0)
