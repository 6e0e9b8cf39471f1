"""The exported synchronous network run by Norse (a simulator we did not write) in the closed
rendezvous loop, against the package's own network on the same seeds (issue 40, part 4).

Per run s: the package exports its constant-gain network (``spike_rule: synchronous``, seed s,
dispersed start) to ``run<s>.nir``; :mod:`.tick_reader` rewrites that file alone into the graph a
reset-to-zero, one-tick reader runs (``run<s>_reader.nir``); ``norse.torch.from_nir`` builds the
network from that file, its state set from the file's initial v and r. The loop is the package's
(truth plant, PositionSensor, LQR: the streams of ``simulate`` with seed s): per 0.1 s sample
``u = -K x_hat``, ``z = C x + v``, T ticks of ``[z, u, x_hat, gate_t]`` into Norse (the estimate of
the sample before held: tick_reader's sample-and-hold of the slow loop), x_hat = its decoder's
output at the last tick. The runs share one module: every neuron parameter is the same in all
runs (thresholds 1, one leak), so only the Linear weights differ; they are stacked into one batched
product per Linear (:class:`StackedLinear`) and the runs step on torch's batch axis: ~1.2 ms per
tick for 20 runs here under load, one run alone ~0.4 ms (torch.vmap over the runs' modules cost
~9 ms per tick for 20 runs, more than running them one by one).

Needs torch and Norse built from GitHub master (norse 1.1.0 on PyPI cannot read the graph;
docs/decisions.md, 71): import this module only where they are installed.

``python -m snn_tools.neuromorphic.norse_loop --out results`` (``make norse-loop``) writes
results/norse_loop.json and its section of results/neuromorphic.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import nir
import norse.torch
import numpy as np
import torch

from snn_estimator.plant.control import lqr_control, lqr_gain
from snn_estimator.plant.sensors import PositionSensor
from snn_estimator.sim.simulate import truth_plant

from . import tables
from .reader_loop import (
    KIND,
    export_runs,
    markdown,
    package_closed_loop,
    scenario,
    synchronous_config,
    window_rmse,
    write_section,
)
from .tick_reader import FORMS, INPUT, NEURONS, POTENTIAL, TRAINS, gate_inputs


class StackedLinear(torch.nn.Module):
    """The Linear layers of several runs' modules as one: run b's input (row b) through run b's
    weight. Stands in for the torch.nn.Linear that nirtorch builds from each file's NIR Linear
    (weights exactly those), so that one Norse module steps every run. The input columns whose
    weights are equal in every run (the gate's diagonal, the spike-to-train diagonal, the identity)
    are one shared product; the others a batched product over the columns some run's input is
    not zero in (a tick's few spikes): the same sums, in another order."""

    def __init__(self, layers):
        super().__init__()
        if any(layer.bias is not None for layer in layers):
            raise ValueError('a NIR Linear has no bias: these layers are not from Linear nodes')
        weights = torch.stack([layer.weight.detach() for layer in layers])          # (runs, out, in)
        same = (weights == weights[:1]).all(dim=1).all(dim=0)                         # (in,)
        self.register_buffer('shared_columns', torch.nonzero(same).flatten())
        self.register_buffer('own_columns', torch.nonzero(~same).flatten())
        shared = weights[0][:, same].contiguous()                                    # (out, shared)
        # a diagonal block (the gate, the spike-to-train jumps, the identity) as a product by element
        self.diagonal = shared.shape[0] == shared.shape[1] and bool(torch.equal(shared, torch.diag(shared.diagonal())))
        self.register_buffer('shared', shared.diagonal().clone() if self.diagonal else shared)
        self.register_buffer('own', weights[:, :, ~same].transpose(1, 2).contiguous())  # (runs, own, out)

    def _shared(self, x):
        return x * self.shared if self.diagonal else torch.nn.functional.linear(x, self.shared)

    def forward(self, x):
        if not self.own_columns.numel():
            return self._shared(x)
        own = x if not self.shared_columns.numel() else x[:, self.own_columns]
        active = torch.nonzero((own != 0).any(dim=0)).flatten()
        if active.numel() < own.shape[1]:
            out = torch.bmm(own[:, active].unsqueeze(1), self.own[:, active]).squeeze(1)
        else:
            out = torch.bmm(own.unsqueeze(1), self.own).squeeze(1)
        if self.shared_columns.numel():
            out = out + self._shared(x[:, self.shared_columns])
        return out


class NorseBatch:
    """The networks of several ``.nir`` files (written by tick_reader) built by Norse and stepped
    together on one batch axis, one sample (T ticks) per :meth:`sample`: the module of the first
    file runs with every Linear layer replaced by the runs' layers stacked (:class:`StackedLinear`);
    Norse's neuron cells and the step nirtorch generated are those of the file, unchanged, and the
    neuron parameters are checked equal in every file."""

    def __init__(self, paths):
        graphs = [nir.read(path) for path in paths]
        first = graphs[0]
        self.tick = float(first.metadata['tick_s'])
        self.ticks = int(first.metadata['ticks_per_sample'])
        for graph in graphs[1:]:
            if sorted(graph.nodes) != sorted(first.nodes) or list(map(tuple, graph.edges)) != list(
                    map(tuple, first.edges)):
                raise ValueError('the files differ in nodes or edges: one module cannot run them')
            for name in (NEURONS, TRAINS, POTENTIAL):
                if name in first.nodes and not _same_neurons(first.nodes[name], graph.nodes[name]):
                    raise ValueError(f'the {name} nodes differ between the files: one module cannot run them '
                                     'on one batch axis')
        modules = [build_module(graph) for graph in graphs]
        self.module = modules[0]
        for name, layer in list(self.module.named_children()):
            if isinstance(layer, torch.nn.Linear):
                setattr(self.module, name, StackedLinear([getattr(m, name) for m in modules]))
        self.gate = torch.as_tensor(gate_inputs(first))                       # (T, N)
        self.n_in = int(first.nodes[INPUT].input_type['input'][0])
        self.runs = len(graphs)
        self.state = initial_state(self.module, graphs)
        decoder = np.stack([g.nodes['decoder'].weight for g in graphs])
        initial_r = np.stack([np.asarray(g.nodes[TRAINS].metadata['initial_state'], dtype=float) for g in graphs])
        self.x_hat = np.einsum('bij,bj->bi', decoder, initial_r)
        self.spikes = np.zeros(self.runs, dtype=np.int64)

    def sample(self, z: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One sample of every run: z (runs, m), u (runs, nu) and the last x_hat held over its T
        ticks; returns x_hat (runs, n), the decoder's output at the last tick."""
        held = np.concatenate([z, u, self.x_hat], axis=1)
        self.x_hat = step_sample(self.module, self.state, self.gate, held, self.spikes)
        return self.x_hat


def build_module(graph):
    """Norse's module of one reader graph, at the graph's tick, computing in float64. from_nir
    rounds the file's arrays to float32 (its ``_to_tensor``), weights and neuron parameters alike:
    the estimate differs from the package's by ~1e-6 m from the first sample on."""
    return norse.torch.from_nir(graph, dt=float(graph.metadata['tick_s']), ignore_warnings=True).to(torch.float64)


def initial_state(module, graphs) -> dict:
    """The state of ``module`` (one row per graph) with the files' initial potentials and trains;
    the fast loop's previous output is zero (no spike before the start)."""
    n_in = int(graphs[0].nodes[INPUT].input_type['input'][0])
    with torch.no_grad():
        _, state = module(torch.zeros(len(graphs), n_in, dtype=torch.float64))
    holder = POTENTIAL if POTENTIAL in graphs[0].nodes else NEURONS
    key = 'initial_state' if holder == POTENTIAL else 'initial_v'
    v0 = torch.as_tensor(np.stack([np.asarray(g.nodes[holder].metadata[key], dtype=float) for g in graphs]))
    r0 = torch.as_tensor(np.stack([np.asarray(g.nodes[TRAINS].metadata['initial_state'], dtype=float)
                                   for g in graphs]))
    state[holder] = type(state[holder])(v=v0)
    if holder == POTENTIAL:
        state[NEURONS] = type(state[NEURONS])(v=torch.zeros_like(v0))
    state[TRAINS] = type(state[TRAINS])(v=r0)
    state['fast_prev_output'] = torch.zeros_like(v0)
    return state


def step_sample(module, state: dict, gate, held: np.ndarray, spikes: np.ndarray) -> np.ndarray:
    """T ticks of ``module`` with the inputs ``held`` (runs, m + nu + n: z, u, the last x_hat) and
    the gate row of each tick;
    ``state`` is updated in place, each run's spikes added to ``spikes``; returns the output at
    the last tick (runs, n)."""
    x = torch.zeros(held.shape[0], held.shape[1] + gate.shape[1], dtype=torch.float64)
    x[:, :held.shape[1]] = torch.as_tensor(held)
    out = None
    with torch.no_grad():
        for t in range(gate.shape[0]):
            x[:, held.shape[1]:] = gate[t]
            out, new = module(x, state)
            state.update(new)
            spikes += new[f'{NEURONS}_prev_output'].sum(axis=1).to(torch.int64).numpy()
    return out.numpy().copy()


def _same_neurons(a, b) -> bool:
    fields = [f for f in ('tau', 'v_threshold', 'v_leak', 'r') if hasattr(a, f)]
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in fields)


def norse_closed_loop(sc, kind: str, seeds, folder: Path, form: str = 'comparator', report=None) -> dict:
    """The closed loop with the Norse networks of ``seeds`` (one batch): per-run position RMSE
    over the metric window, spikes per step, final range."""
    started = time.perf_counter()
    batch = NorseBatch(export_runs(sc, kind, seeds, folder, form))
    plant = truth_plant(sc, seeds)
    sensor = PositionSensor(sc.truth_model or sc.model, sc.measurement_noise, seeds)
    gain = lqr_gain(sc.model, sc.lqr_state_weight, sc.lqr_input_weight)
    window_start = sc.steps + 1 - int(round(sc.metric_window / sc.dt))
    errors = []
    x_hat = batch.x_hat
    for k in range(sc.steps):
        u = lqr_control(gain, x_hat)
        z = sensor.measure(plant.x)
        x_hat = batch.sample(z, u)
        plant.step(u, sc.dt)
        if k + 1 >= window_start:
            errors.append(np.asarray(plant.x) - x_hat)
        if report is not None and (k + 1) % 600 == 0:
            report(f'norse: step {k + 1}/{sc.steps}, {time.perf_counter() - started:.0f} s')
    return {'rmse_position_m': window_rmse(np.stack(errors, axis=1)).tolist(),
            'spikes_per_step': (batch.spikes / sc.steps).tolist(),
            'final_range_m': np.linalg.norm(np.asarray(plant.x)[:, :3], axis=1).tolist(),
            'wall_s': round(time.perf_counter() - started, 1)}


def compare(runs: int = 20, seed: int = 0, duration: float | None = None, form: str = 'comparator',
            kind: str = KIND, folder: Path | None = None, report=None) -> dict:
    """Norse against the package over ``runs`` seeds from ``seed``: per run and median."""
    sc = scenario(duration)
    seeds = list(range(seed, seed + runs))
    with tempfile.TemporaryDirectory() as scratch:
        norse_runs = norse_closed_loop(sc, kind, seeds, Path(folder or scratch), form, report)
    package_runs = package_closed_loop(sc, kind, seeds)
    n_rmse, p_rmse = np.array(norse_runs['rmse_position_m']), np.array(package_runs['rmse_position_m'])
    config = synchronous_config(sc)
    return {
        'kind': kind, 'seeds': seeds, 'form': form, 'duration_s': sc.duration, 'metric_window_s': sc.metric_window,
        'ticks_per_sample': config.ticks_per_sample, 'firing_slots': config.firing_slots,
        'threshold_widening': config.threshold_widening,
        'norse_version': getattr(norse, '__version__', 'unknown'), 'torch_version': torch.__version__,
        'norse': norse_runs, 'package': package_runs,
        'ratio_per_run': (n_rmse / p_rmse).tolist(),
        'median_norse_m': float(np.median(n_rmse)), 'median_package_m': float(np.median(p_rmse)),
        'median_ratio': float(np.median(n_rmse) / np.median(p_rmse)),
        'median_spikes_norse': float(np.median(norse_runs['spikes_per_step'])),
        'median_spikes_package': float(np.median(package_runs['spikes_per_step'])),
    }


def record_section(out: Path, data: dict) -> None:
    """This run's section of neuromorphic.md: kept in neuromorphic.json (``norse_loop``), from which
    ``make neuromorphic`` and ``make spike-rules`` rewrite the page; without that file, the section alone."""
    path = out / 'neuromorphic.json'
    if not path.exists():
        write_section(out / 'neuromorphic.md', markdown(data))
        return
    everything = json.loads(path.read_text(encoding='utf-8'))
    everything['norse_loop'] = data
    path.write_text(json.dumps(everything, indent=2) + '\n', encoding='utf-8')
    (out / 'neuromorphic.md').write_text(tables.markdown(everything), encoding='utf-8')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='norse_loop', description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=20)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--duration', type=float, default=None, help='s (default: the full 360 s rendezvous)')
    parser.add_argument('--form', choices=FORMS, default='comparator')
    parser.add_argument('--out', type=Path, default=Path('results'))
    parser.add_argument('--threads', type=int, default=1, help='torch threads')
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    data = compare(args.runs, args.seed, args.duration, args.form, report=lambda line: print(line, flush=True))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / 'norse_loop.json').write_text(json.dumps(data, indent=1) + '\n', encoding='utf-8')
    record_section(args.out, data)
    print(f"norse median {data['median_norse_m']:.4g} m, package {data['median_package_m']:.4g} m, "
          f"ratio {data['median_ratio']:.3f}")
    return 0


if __name__ == '__main__':
    sys.exit(main())
