"""``snn_export``: a spiking filter's network as a NIR graph (Neuromorphic Intermediate
Representation, the ``nir`` package), and the reader that takes it back to arrays.

The exported network has a constant gain (``gain_schedule: steady_state``, the gain at the fixed
point of Eq. 6: see estimators.steady_state_gain), so every weight is constant, which is what a
neuromorphic chip holds. Weights are those of ``Estimator.weights`` (Eq. 16-24) in the
state-scaled units the package runs the network on (x~ = S^-1 x).

Graph (NIR is continuous-time; a spike is a unit impulse)::

    z (m) --> measurement_weights: Linear F_k = D^T S^-1 K  (Eq. 20/22/24) --+
    u (nu) -> control_weights:     Linear F   = D^T S^-1 B_d (Eq. 16) -------+
                                                                             v
    +------------------------------------------------------------> neurons: LIF (N)
    |  fast: Linear, Omega_f = -D^T D off its diagonal (Eq. 18) <------ spikes |
    |                                                                          |
    |  slow_dynamics:   Linear Omega_s = D^T (S^-1 A_d S + lambda I) D (17) <--+-- trains: LI (N)
    +- slow_correction: Linear Omega_k = -D^T S^-1 K C S D (19/21/23)    <-----+      |
                                                                                      v
                                  x_hat (n) <-- decoder: Linear S D (Eq. 12) <---- trains

* ``neurons``: LIF with tau = 1/lambda and r = 1/lambda, so tau v' = -v + r I reads
  v' = -lambda v + I (Eq. 10 and 15, v_leak = 0); v_threshold = T_i = ||D_i||^2 / 2.
* The reset is the diagonal of Omega_f: a spike of i lowers v_i by ||D_i||^2 = 2 T_i (Eq. 18).
  NIR's LIF resets to v_reset, so the diagonal is written as v_reset = v_threshold - 2 T_i =
  -T_i and the ``fast`` Linear holds only the off-diagonal part: at a crossing v_i = T_i
  (continuous time) resetting to -T_i and subtracting 2 T_i are the same. A simulator that
  steps in time, where v_i overshoots T_i (the package's 0.1 s steps, in which one neuron may
  fire many times), must subtract v_threshold - v_reset instead, as the package does; the
  LIF's metadata says so.
* ``trains``: LI with tau = r = 1/lambda: r' = -lambda r + s (Eq. 11), the filtered spike
  trains; ``slow_*`` feed them back, ``decoder`` reads the estimate x_hat = S D r (Eq. 12) in
  m and m/s.
* ``spike_rule: synchronous`` (docs/decisions.md, 58-60): v_threshold is the widened threshold
  (1 + w) T_i and v_reset = v_threshold - ||D_i||^2; the tick (``ticks_per_sample``, ``tick_s``),
  the firing slots and the refractory ticks are graph metadata, and ``spike_rule_meaning`` states
  the reading a simulator must take.
* What NIR has no field for is node and graph metadata (nir 1.0.8 stores it in the file): the
  sample period and its discretisation, the spike rule, S, the gain K, the filter kind and
  gain law, seed, units, and the initial state (v and r after encoding x_hat0).

A NIR Linear's weight is (out, in): ``fast.weight[j, i]`` is what a spike of i adds to v_j.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from snn_estimator.filters.estimators import FILTER_KINDS, Estimator, make_estimator, steady_state_gain
from snn_estimator.models import StateSpaceModel
from snn_estimator.sim.scenarios import rendezvous_scenario
from snn_estimator.spiking import chip

#: The kinds with a spiking network, in FILTER_KINDS order.
SPIKING_KINDS = tuple(kind for kind, spec in FILTER_KINDS.items() if spec.spiking)
#: Sections of a ROS parameter file the exporter reads (PyYAML; no rclpy).
PARAMETER_SECTIONS = ('/**', '/**/estimator')
LIF, TRAINS, OUTPUT = 'neurons', 'trains', 'x_hat'

RESET_SEMANTICS = (
    'v_reset = v_threshold - ||D_i||^2 carries the self term of Omega_f (Eq. 18): subtract '
    'v_threshold - v_reset at each spike. Equal to resetting to v_reset only when v crosses '
    'exactly at v_threshold (continuous time)')
#: What each spike rule means to a reader of the graph (metadata ``spike_rule_meaning``).
SPIKE_RULES = {
    'greedy': ('per sample period, integrate the drive, then while some neuron has v_i > T_i the one '
               'with the largest v_i - T_i fires alone and its fast connections act before the next is chosen'),
    'one_per_step': 'per sample period, integrate the drive, then the neuron with the largest v_i - T_i > 0 fires',
    'all_above': ('per sample period, integrate the drive, then every neuron with v_i > T_i fires once, all '
                  'together; the fast connections act after'),
    'synchronous': (
        'explicit Euler at tick_s = sample_period / ticks_per_sample, the inputs held over the sample and fed '
        'at every tick, and so is the slow input (slow_dynamics + slow_correction): computed once per sample '
        'from r at its start, not ticked (snn_tools/neuromorphic/tick_reader.py writes it for a reader that '
        'ticks every edge); each tick v and r decay by (1 - leak_rate sample_period)^(1/ticks_per_sample) and '
        'v integrates 1/ticks_per_sample of the sample\'s input; then every neuron i fires whose v_i exceeds '
        'its own v_threshold (already widened: (1 + threshold_widening) ||D_i||^2 / 2), if (t + i) mod '
        'firing_slots = 0 for the tick t = 0..ticks_per_sample-1 of the sample and it has not fired in the '
        'last refractory_ticks ticks; all that fire in a tick fire together (a spike is 1 in that tick, no '
        'neuron is compared with another), and their fast connections and reset act after the tick '
        '(the previous tick\'s spikes reach the next tick); r_i += 1 per spike'),
}


def constant_gain_estimator(kind: str, config, model: StateSpaceModel) -> Estimator:
    """The single-run ``kind`` filter with its gain held at steady state (constant weights).
    ValueError (naming the fix) for a non-spiking kind, a nonlinear model or silenced neurons."""
    if kind not in SPIKING_KINDS:
        raise ValueError(f'filter {kind!r} has no spiking network to export; choose one of '
                         f'{", ".join(SPIKING_KINDS)}')
    if not model.is_linear:
        raise ValueError(f'{type(model).__name__} is nonlinear: its network weights follow the '
                         'Jacobian at the estimate (Eq. 17) and change every step, so there is no '
                         'constant network to export; use a linear model (e.g. ClohessyWiltshire)')
    if config.silenced_neurons:
        raise ValueError('silenced_neurons is set: export the intact network (silenced_neurons '
                         '[] and silenced_fraction 0.0)')
    return make_estimator(kind, config.replace(gain_schedule='steady_state'), model)


def network_graph(estimator: Estimator, dt: float, weight_set: int = 0):
    """The NIR graph of a constant-gain spiking ``estimator`` (weights at sample period ``dt``,
    s); its current v and r become the initial state in the metadata. For a chip network
    (precision loihi or gain_schedule switched: snn_estimator.spiking.chip) the weights are those its
    quantized factors compute, of set ``weight_set`` (NIR has no switch: one graph per set,
    :func:`export_schedule`)."""
    import nir

    network = estimator.chip
    if not (estimator.spiking and (estimator.constant_gain or network is not None) and estimator.runs == 1):
        raise ValueError('network_graph needs a single-run spiking estimator with gain_schedule '
                         'steady_state or switched (see constant_gain_estimator)')
    if estimator.coding != 'state':
        raise ValueError('network_graph exports the network of network_coding state: with deviation '
                         'the prediction x_pred runs off the network, which a NIR graph does not hold')
    s = estimator.settings
    if network is None:
        w = estimator.weights(dt=dt)
        gain, leak = steady_state_gain(estimator.gain_law, estimator.model, s, dt), s.leak_rate
        initial_v, initial_r = estimator.potentials.copy(), estimator.rates.copy()
    else:
        network.prepare(dt)
        w = chip.effective_weights(network, weight_set)
        gain, leak = w['gain'], w['leak_rate']
        initial_v, initial_r = network.potentials[0].copy(), network.initial_rates(0)
    neurons = w['neurons']
    model = estimator.model
    # a leak the chip's 12-bit decay rounds to 0 is written as a time constant of 1e12 s
    tau = np.full(neurons, 1.0 / max(leak, 1e-12))
    synchronous = s.spike_rule == 'synchronous'
    # the synchronous rule fires above the widened threshold; the reset still subtracts ||D_i||^2
    thresholds = w['thresholds'] * (1.0 + s.threshold_widening) if synchronous else w['thresholds']
    reset = thresholds - 2.0 * w['thresholds']
    fast = w['Omega_f'] - np.diag(np.diag(w['Omega_f']))
    scaled_decoder = s.state_scale[:, None] * w['decoder']
    nodes = {
        'z': nir.Input(input_type={'input': np.array([model.n_meas])},
                       metadata={'meaning': 'measurement z_k held over the sample period', 'unit': 'm'}),
        'u': nir.Input(input_type={'input': np.array([model.n_input])},
                       metadata={'meaning': 'control u_k held over the sample period', 'unit': 'm/s^2'}),
        'measurement_weights': nir.Linear(weight=w['F_k'], metadata={
            'equation': 'F_k = D^T S^-1 K (Eq. 20/22/24)', 'unit': '1/(m s)'}),
        'control_weights': nir.Linear(weight=w['F'], metadata={
            'equation': 'F = D^T S^-1 B_d (Eq. 16)', 'unit': 's/m'}),
        LIF: nir.LIF(tau=tau, r=tau.copy(), v_leak=np.zeros(neurons), v_threshold=thresholds,
                     v_reset=reset, metadata={
                         'equation': 'v\' = -lambda v + I (Eq. 10, 15); T_i = ||D_i||^2 / 2',
                         'reset': RESET_SEMANTICS, 'initial_v': initial_v,
                         'unit': 'v in state-scaled units, tau in s'}),
        'fast': nir.Linear(weight=fast, metadata={
            'equation': 'Omega_f = -D^T D off the diagonal (Eq. 18); the diagonal is the reset',
            'unit': 'jump of v per spike'}),
        TRAINS: nir.LI(tau=tau.copy(), r=tau.copy(), v_leak=np.zeros(neurons), metadata={
            'equation': "r' = -lambda r + s (Eq. 11)", 'initial_state': initial_r,
            'unit': 'filtered spike count'}),
        'slow_dynamics': nir.Linear(weight=w['Omega_s'], metadata={
            'equation': 'Omega_s = D^T (S^-1 A_d S + lambda I) D (Eq. 17)', 'unit': '1/s'}),
        'slow_correction': nir.Linear(weight=w['Omega_k'], metadata={
            'equation': 'Omega_k = -D^T S^-1 K C S D (Eq. 19/21/23)', 'unit': '1/s'}),
        'decoder': nir.Linear(weight=scaled_decoder, metadata={
            'equation': 'x_hat = S D r (Eq. 12)', 'unit': 'm and m/s per unit of r'}),
        OUTPUT: nir.Output(output_type={'output': np.array([model.n_state])}, metadata={
            'meaning': 'state estimate', 'states': ','.join(model.state_names)}),
    }
    edges = [('z', 'measurement_weights'), ('measurement_weights', LIF),
             ('u', 'control_weights'), ('control_weights', LIF),
             (LIF, 'fast'), ('fast', LIF), (LIF, TRAINS),
             (TRAINS, 'slow_dynamics'), ('slow_dynamics', LIF),
             (TRAINS, 'slow_correction'), ('slow_correction', LIF),
             (TRAINS, 'decoder'), ('decoder', OUTPUT)]
    metadata = {
        'generator': 'snn_rendezvous snn_export',
        'filter_kind': estimator.kind, 'gain_law': estimator.gain_law, 'gain_schedule': s.gain_schedule,
        'gain': gain,
        'sample_period': float(dt), 'discretization': s.discretization,
        'sample_semantics': ('inputs held over each sample period; A_d = (Phi - I)/dt and B_d = Gamma/dt '
                             'are the exact zero-order hold at this period (models.linearized_increment)'),
        'spike_rule': s.spike_rule, 'spike_rule_meaning': SPIKE_RULES[s.spike_rule],
        'state_scale': s.state_scale.copy(), 'state_names': ','.join(model.state_names),
        'leak_rate': float(leak), 'decoder_variance': float(s.decoder_variance),
        'seed': int(estimator.seeds[0]), 'neurons': int(neurons),
        'units': 'time s; z m; u m/s^2; x_hat m and m/s; v and weights in state-scaled units (x~ = S^-1 x)',
    }
    if synchronous:  # the tick NIR has no field for (docs/decisions.md, 60)
        metadata.update({
            'ticks_per_sample': int(s.ticks_per_sample), 'tick_s': float(dt) / s.ticks_per_sample,
            'threshold_widening': float(s.threshold_widening), 'firing_slots': int(s.firing_slots),
            'firing_slot_rule': '(t + i) mod firing_slots == 0, t = 0..ticks_per_sample-1 within each sample',
            'refractory_ticks': int(s.refractory_ticks),
            'spike_semantics': ('a spike is 1 in the tick it fires (not a unit impulse): the weights of edges '
                                'out of neurons (fast, and trains through LI) are jumps per spike'),
        })
    if network is not None:
        times = [0.0] + list(chip.schedule_times(estimator.config)) + [float('inf')]
        metadata.update({
            'precision': estimator.config.precision, 'chip_format': repr(network.describe()),
            'weight_set': int(weight_set), 'weight_sets': len(network.gains),
            'active_from_s': times[weight_set], 'active_until_s': times[weight_set + 1],
            'chip_semantics': ('weights are the products of the quantized factors of snn_estimator.spiking.chip '
                               '(D, A, K, B: signed mantissas, one exponent each); the chip runs them '
                               'factored, v = D^T e, and rounds its drive to the readout LSB each sample')})
    return nir.NIRGraph(nodes=nodes, edges=edges, metadata=metadata)


def export_schedule(estimator: Estimator, dt: float, folder: Path) -> list[Path]:
    """One NIR file per weight set of a chip network (``<kind>_set<j>.nir``), each with its
    active interval (active_from_s, active_until_s) in the graph metadata: NIR holds constant
    weights and no switch."""
    import nir

    if estimator.chip is None:
        raise ValueError('export_schedule needs a chip network (gain_schedule switched or precision loihi)')
    estimator.chip.prepare(dt)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for j in range(len(estimator.chip.gains)):
        path = folder / f'{estimator.kind}_set{j}.nir'
        nir.write(path, network_graph(estimator, dt, weight_set=j))
        paths.append(path)
    return paths


@dataclass(frozen=True)
class NetworkArrays:
    """A spike-coding network read back from a NIR graph, as arrays (see :func:`network_arrays`).

    Input scaling is applied: ``measurement``, ``control`` and ``slow`` are the rates they add
    to v' (times the LIF's r / tau), ``fast`` the jump of v per spike, ``train_jump`` the jump
    of r per spike (the LI's r / tau).
    """

    measurement: np.ndarray   # (N, m)
    control: np.ndarray       # (N, nu)
    fast: np.ndarray          # (N, N), [j, i]: added to v_j by a spike of i
    slow: np.ndarray          # (N, N), acting on r
    decoder: np.ndarray       # (n, N), x_hat = decoder @ r (SI units)
    threshold: np.ndarray     # (N,)
    reset_amount: np.ndarray  # (N,), v_threshold - v_reset, subtracted at a spike
    tau_v: np.ndarray         # (N,), s
    tau_r: np.ndarray         # (N,), s
    train_jump: np.ndarray    # (N,)
    initial_v: np.ndarray     # (N,)
    initial_r: np.ndarray     # (N,)
    sample_period: float      # s
    metadata: dict

    @property
    def omega_f(self) -> np.ndarray:
        """The full fast matrix of Eq. 18, the reset put back on its diagonal."""
        return self.fast - np.diag(self.reset_amount)


def network_arrays(graph) -> NetworkArrays:
    """Arrays of a graph written by :func:`network_graph`, found by the graph's wiring (one LIF,
    one LI, Inputs z and u, Linear nodes between them; parallel Linear nodes add up).
    ValueError naming what is missing for any other graph."""
    import nir

    lif = _only(graph, nir.LIF, 'LIF')
    trains = _only(graph, nir.LI, 'LI')
    lif_name, trains_name = _name_of(graph, lif), _name_of(graph, trains)
    if np.any(lif.v_leak != 0.0) or np.any(trains.v_leak != 0.0):
        raise ValueError('v_leak must be 0 in the LIF and LI nodes of a spike-coding network (Eq. 10-11)')
    gain_v = lif.r / lif.tau
    decoder = _through_linear(graph, trains_name, _only_name(graph, nir.Output, 'Output'))
    metadata = dict(graph.metadata)
    if 'sample_period' not in metadata:
        raise ValueError('graph metadata has no sample_period: not a network written by snn_export')
    return NetworkArrays(
        measurement=gain_v[:, None] * _through_linear(graph, 'z', lif_name),
        control=gain_v[:, None] * _through_linear(graph, 'u', lif_name),
        fast=gain_v[:, None] * _through_linear(graph, lif_name, lif_name),
        slow=gain_v[:, None] * _through_linear(graph, trains_name, lif_name),
        decoder=decoder, threshold=np.asarray(lif.v_threshold, dtype=float),
        reset_amount=np.asarray(lif.v_threshold - lif.v_reset, dtype=float),
        tau_v=np.asarray(lif.tau, dtype=float), tau_r=np.asarray(trains.tau, dtype=float),
        train_jump=np.asarray(trains.r / trains.tau, dtype=float),
        initial_v=np.asarray(lif.metadata.get('initial_v', np.zeros(lif.tau.shape)), dtype=float),
        initial_r=np.asarray(trains.metadata.get('initial_state', np.zeros(trains.tau.shape)), dtype=float),
        sample_period=float(metadata['sample_period']), metadata=metadata)


def _only(graph, node_type, label: str):
    found = [node for node in graph.nodes.values() if isinstance(node, node_type)]
    if len(found) != 1:
        raise ValueError(f'a spike-coding network has exactly one {label} node; this graph has {len(found)}')
    return found[0]


def _only_name(graph, node_type, label: str) -> str:
    return _name_of(graph, _only(graph, node_type, label))


def _name_of(graph, node) -> str:
    return next(name for name, other in graph.nodes.items() if other is node)


def _through_linear(graph, source: str, target: str) -> np.ndarray:
    """Sum of the weights of the Linear nodes L with edges source -> L -> target."""
    import nir

    edges = set(map(tuple, graph.edges))
    weights = [node.weight for name, node in graph.nodes.items()
               if isinstance(node, nir.Linear) and (source, name) in edges and (name, target) in edges]
    if not weights:
        raise ValueError(f'no Linear node from {source!r} to {target!r}: not a network written by snn_export')
    return np.sum(weights, axis=0).astype(float)


# ---------------------------------------------------------------- parameters and CLI
def read_parameters(path: Path) -> dict:
    """Estimator parameter values from a ROS parameter YAML (sections ``/**`` and
    ``/**/estimator``) over the estimator node's defaults (scenario_nodes.parameter_tables, read
    without rclpy). ValueError naming an unknown estimator parameter or a bad choice."""
    import yaml

    from scenario_nodes.parameter_tables import ESTIMATOR
    from scenario_nodes.ros_parameters import check_choices

    document = yaml.safe_load(Path(path).read_text(encoding='utf-8')) or {}
    if not any(section in document for section in PARAMETER_SECTIONS):
        raise ValueError(f'{path}: no {" or ".join(PARAMETER_SECTIONS)} section with ros__parameters')
    values = {spec.name: spec.default for spec in ESTIMATOR}
    for section in PARAMETER_SECTIONS:
        given = (document.get(section) or {}).get('ros__parameters') or {}
        unknown = set(given) - set(values) - {'use_sim_time'}
        if unknown and section == '/**/estimator':
            raise ValueError(f'{path}: unknown estimator parameters {sorted(unknown)} in {section}; '
                             'see config/rendezvous.yaml for the names')
        values.update({name: value for name, value in given.items() if name in values})
    check_choices(values, ESTIMATOR)
    return values


def export_setup(kind: str | None, params_file: Path | None):
    """(kind, config, model, dt): from a parameter file (its filter_type unless ``kind`` is
    given) or the rendezvous scenario's defaults."""
    if params_file is None:
        scenario = rendezvous_scenario()
        return kind or 'snn_emsif', scenario.estimator, scenario.model, scenario.dt
    from scenario_nodes.core_objects import cw_model, estimator_config

    values = read_parameters(params_file)
    model = cw_model(values, form=values['cw_model'], measured_axes=values['measured_axes'])
    return kind or values['filter_type'], estimator_config(values), model, float(values['time_step'])


def export(kind: str, config, model: StateSpaceModel, dt: float, out: Path):
    """Build the constant-gain ``kind`` network and write it to ``out`` (NIR, HDF5); returns
    the graph."""
    import nir

    graph = network_graph(constant_gain_estimator(kind, config, model), dt)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    nir.write(out, graph)
    return graph


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_export', description=__doc__.split('\n\n')[0])
    parser.add_argument('--filter', choices=SPIKING_KINDS, default=None,
                        help="spiking filter to export (default: the parameter file's filter_type, "
                             'else snn_emsif)')
    parser.add_argument('--params-file', type=Path, default=None,
                        help='ROS parameter YAML (e.g. config/rendezvous.yaml); default: the '
                             'rendezvous scenario')
    parser.add_argument('--out', type=Path, required=True, help='NIR file to write (HDF5)')
    args = parser.parse_args(argv)
    try:
        kind, config, model, dt = export_setup(args.filter, args.params_file)
        graph = export(kind, config, model, dt, args.out)
    except (ValueError, FileNotFoundError) as error:
        print(f'snn_export: {error}', file=sys.stderr)
        return 2
    arrays = network_arrays(graph)
    print(f'wrote {args.out}: {kind}, N = {arrays.threshold.size} LIF neurons, constant gain '
          f'({graph.metadata["gain_law"]}), sample period {dt} s; nodes: {", ".join(graph.nodes)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
