"""An independent simulator for the exported networks: Brian2, built from the NIR file.

Brian2 (pure Python with numpy code generation) installs beside the ROS 2 wheels without
conflict (with numpy < 2.3 for brian2 2.9.0). The NIR readers of the deep-learning simulators
(snnTorch, Norse, Spyx, Lava-dl) need torch or jax, several GB, which this environment does not
have. The numpy code-generation target is used: no compiler, no cache directory (cython would
need a C implementation of the greedy spike rule below).

What is simulated is read from the graph alone (nir.read, then nir_export.network_arrays): the
LIF population with its thresholds and reset, one Synapses object carrying the fast weights
(v_post += w_fast, Eq. 18) and the slow ones, the inputs, the decoder. The slow path of the
graph, spikes -> LI (r' = -lambda r + s) -> Linear Omega -> LIF, is simulated as a synaptic
current I_slow = Omega r that jumps by Omega[:, i] at a spike of i and decays with the LI's
tau: the same quantity (every r_i decays alike), event-driven, N^2 products per step fewer.
The inputs are piecewise constant over a sample period, so F_k z_k + F u_k is one TimedArray
of N currents per sample.

Two readings of the graph (``mode``):

* ``sampled`` (the package's network): at each sample instant t_k, v <- (1 - dt/tau) v + dt
  (F_k z_k + F u_k + I_slow) and r, I_slow decay by (1 - dt/tau) (forward Euler at the sample
  period, run_regularly); then ``substeps`` Brian2 steps, without drive, resolve the spikes.
* ``continuous``: v' = -v/tau + F_k z + F u + I_slow with inputs held, integrated by Brian2's
  exponential Euler at dt = period / substeps (its 'exact' solver divides by tau_v - tau_r,
  zero here); spikes fire when v crosses.

and two spike rules (``rule``): ``greedy``, where a vectorised threshold function lets only the
neuron with the largest v - v_threshold fire in a Brian2 step (with ``sampled`` this is the
package's greedy rule, one spike per sub-step, as long as substeps exceeds the spikes of a
sample), and ``all_above``, Brian2's own threshold: every neuron above fires at once.
Resets subtract v_threshold - v_reset (the self term of Omega_f; see nir_export).

Only ``sampled`` with ``greedy`` reproduces the package's network (spike for spike); the other
readings are reported by ``snn_neuromorphic`` to show what a continuous-time or synchronous
reader of the same file gets.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import brian2 as b2
import numpy as np

from snn_tools.neuromorphic.nir_export import NetworkArrays, network_arrays

MODES = ('sampled', 'continuous')
RULES = ('greedy', 'all_above')


@dataclass
class BrianRun:
    """A Brian2 run of an exported network over replayed inputs."""

    estimate: np.ndarray         # (steps + 1, n): decoded x_hat at t_0 .. t_steps, m and m/s
    raster: np.ndarray           # (steps, N): spikes per neuron per sample period
    saturated_steps: int         # sampled greedy: periods whose last sub-step still fired
    wall_time: float             # s in Network.run
    brian_dt: float              # s
    mode: str
    rule: str

    @property
    def spikes_per_step(self) -> np.ndarray:
        return self.raster.sum(axis=1)


@b2.implementation('numpy', discard_units=True)
@b2.check_units(overshoot=1, result=1)
def greedy_winner(overshoot):
    """1 for the neuron with the largest v - v_threshold if it is positive, 0 elsewhere: at
    most one spike per Brian2 step (the spike-coding networks' rule, Boerlin et al. 2013)."""
    fired = np.zeros(np.shape(overshoot))
    best = int(np.argmax(overshoot))
    if overshoot[best] > 0.0:
        fired[best] = 1.0
    return fired


def run_file(path: Path, zs, us, **options) -> BrianRun:
    """Read the NIR file at ``path`` and run it over ``zs`` (steps, m) and ``us`` (steps, nu);
    ``options`` as :func:`run_network`."""
    import nir

    return run_network(network_arrays(nir.read(path)), zs, us, **options)


def run_network(net: NetworkArrays, zs, us, mode: str = 'sampled', rule: str = 'greedy',
                substeps: int = 200, initial_v=None, initial_r=None) -> BrianRun:
    """Simulate ``net`` over the measurements ``zs`` and controls ``us`` of consecutive sample
    periods (the graph's sample_period), starting from its stored initial state or the given
    v and r; decode x_hat = S D r at every sample instant."""
    if mode not in MODES or rule not in RULES:
        raise ValueError(f'mode must be one of {MODES} and rule one of {RULES}; got {mode!r}, {rule!r}')
    zs, us = np.atleast_2d(np.asarray(zs, dtype=float)), np.atleast_2d(np.asarray(us, dtype=float))
    if zs.shape != (len(zs), net.measurement.shape[1]) or us.shape != (len(zs), net.control.shape[1]):
        raise ValueError(f'zs must be (steps, {net.measurement.shape[1]}) and us (steps, '
                         f'{net.control.shape[1]}) with the same steps; got {zs.shape} and {us.shape}')
    if int(substeps) < 1:
        raise ValueError(f'substeps must be a positive integer, got {substeps!r}')
    b2.prefs.codegen.target = 'numpy'
    period = net.sample_period
    brian_dt = period / int(substeps)
    group = _neurons(net, zs, us, mode, rule, brian_dt)
    group.v = net.initial_v if initial_v is None else initial_v
    group.r = net.initial_r if initial_r is None else initial_r
    group.I_slow = net.slow @ np.asarray(group.r[:]) * b2.Hz
    synapses = _synapses(net, group, brian_dt)
    spikes = b2.SpikeMonitor(group)
    rates = b2.StateMonitor(group, 'r', record=True, dt=period * b2.second, when='start', order=-1)
    network = b2.Network(group, synapses, spikes, rates)
    steps = len(zs)
    started = time.perf_counter()
    network.run(steps * period * b2.second, namespace={})
    wall = time.perf_counter() - started
    r = np.vstack([rates.r[:, :steps].T, np.asarray(group.r[:])[None]])
    substep = np.rint(np.asarray(spikes.t[:] / b2.second) / brian_dt).astype(np.int64)
    raster = np.zeros((steps, net.threshold.size), dtype=np.int64)
    np.add.at(raster, (substep // substeps, np.asarray(spikes.i[:])), 1)
    saturated = len(np.unique(substep[substep % substeps == substeps - 1] // substeps)) if mode == 'sampled' else 0
    return BrianRun(estimate=r @ net.decoder.T, raster=raster, saturated_steps=saturated,
                    wall_time=wall, brian_dt=brian_dt, mode=mode, rule=rule)


def _neurons(net: NetworkArrays, zs, us, mode: str, rule: str, brian_dt: float):
    """The LIF population: state v, filtered trains r and slow current I_slow."""
    period = net.sample_period
    drive = b2.TimedArray((zs @ net.measurement.T + us @ net.control.T) * b2.Hz, dt=period * b2.second)
    if mode == 'sampled':
        equations = '''v : 1
                       r : 1
                       I_slow : Hz'''
    else:
        equations = '''dv/dt = -v / tau_v + drive(t, i) + I_slow : 1
                       dr/dt = -r / tau_r : 1
                       dI_slow/dt = -I_slow / tau_r : Hz'''
    equations += '''
                   tau_v : second (constant)
                   tau_r : second (constant)
                   v_threshold : 1 (constant)
                   reset_amount : 1 (constant)
                   train_jump : 1 (constant)'''
    threshold = 'greedy_winner(v - v_threshold) > 0.5' if rule == 'greedy' else 'v > v_threshold'
    group = b2.NeuronGroup(
        net.threshold.size, equations, threshold=threshold, reset='v -= reset_amount\nr += train_jump',
        method='exponential_euler' if mode == 'continuous' else None, dt=brian_dt * b2.second,
        namespace={'drive': drive, 'greedy_winner': greedy_winner, 'period': period * b2.second})
    group.tau_v = net.tau_v * b2.second
    group.tau_r = net.tau_r * b2.second
    group.v_threshold = net.threshold
    group.reset_amount = net.reset_amount
    group.train_jump = net.train_jump
    if mode == 'sampled':  # forward Euler of the graph's ODEs at the sample period
        group.run_regularly('''v = v * (1 - period / tau_v) + period * (drive(t, i) + I_slow)
                               r = r * (1 - period / tau_r)
                               I_slow = I_slow * (1 - period / tau_r)''',
                            dt=period * b2.second, when='start', order=0)
    return group


def _synapses(net: NetworkArrays, group, brian_dt: float):
    """All-to-all synapses: the fast weight adds to v, the slow one to I_slow, at each spike."""
    synapses = b2.Synapses(group, group, 'w_fast : 1 (constant)\nw_slow : Hz (constant)',
                           on_pre='v_post += w_fast\nI_slow_post += w_slow', dt=brian_dt * b2.second)
    synapses.connect()
    pre, post = np.asarray(synapses.i[:]), np.asarray(synapses.j[:])
    synapses.w_fast = net.fast[post, pre]
    synapses.w_slow = net.slow[post, pre] * b2.Hz
    return synapses
