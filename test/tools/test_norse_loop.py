"""Norse (GitHub master; a simulator we did not write) runs the exported synchronous network, built
only from the .nir file, in the closed rendezvous loop (issue 40, part 4). Runs where norse is
importable; under CI the missing extra is exempt (test/conftest.py, docs/decisions.md, 71)."""

import numpy as np
import pytest

pytest.importorskip('norse.torch')
torch = pytest.importorskip('torch')
nir = pytest.importorskip('nir')

from snn_tools.neuromorphic.nir_export import constant_gain_estimator  # noqa: E402
from snn_tools.neuromorphic.norse_loop import (  # noqa: E402
    NorseBatch,
    build_module,
    compare,
    initial_state,
    step_sample,
)
from snn_tools.neuromorphic.reader_loop import (  # noqa: E402
    GOAL_RATIO,
    KIND,
    export_runs,
    scenario,
    synchronous_config,
)
from snn_tools.neuromorphic.tick_reader import gate_inputs  # noqa: E402

torch.set_num_threads(1)
# norse_loop writes its section through tables, which imports brian2 (pyparsing names it deprecates)
pytestmark = [pytest.mark.filterwarnings('ignore::DeprecationWarning:brian2'),
              pytest.mark.filterwarnings('ignore::DeprecationWarning:pyparsing')]
SEEDS = (4, 5)
SAMPLES = 15


@pytest.fixture(scope='module')
def files(tmp_path_factory):
    sc = scenario()
    return sc, export_runs(sc, KIND, SEEDS, tmp_path_factory.mktemp('norse'), 'comparator')


def test_norse_built_from_the_file_is_the_package_network_spike_for_spike(files):
    """Fed the same measurements and controls, Norse's network fires as the package's in every
    sample and decodes the same estimate (the leak and the tick's order written into the file; to
    ~1e-6 m: Norse rounds the file's arrays to float32)."""
    sc, paths = files
    batch = NorseBatch(paths)
    estimators = [constant_gain_estimator(KIND, synchronous_config(sc).replace(seed=s), sc.model) for s in SEEDS]
    rng = np.random.default_rng(0)
    total = 0
    for k in range(SAMPLES):
        z = np.array([sc.x0[:3] + rng.normal(0.0, 1.0, 3) for _ in SEEDS])
        u = rng.normal(0.0, 1e-3, (len(SEEDS), 3))
        before = batch.spikes.copy()
        x_norse = batch.sample(z, u)
        for b, estimator in enumerate(estimators):
            estimator.step(z[b], u[b], sc.dt)
            assert batch.spikes[b] - before[b] == estimator.spikes.sum(), f'run {b}, sample {k}'
            np.testing.assert_allclose(x_norse[b], estimator.x_hat, rtol=0, atol=1e-5)  # Norse's float32 arrays
            total += int(estimator.spikes.sum())
    assert total > 20 * SAMPLES * len(SEEDS)


def test_the_runs_on_one_batch_axis_are_each_files_own_norse_module(files):
    """The stacked Linear layers change nothing: each run as Norse builds it from its file alone."""
    sc, paths = files
    batch = NorseBatch(paths)
    graphs = [nir.read(path) for path in paths]
    singles = [build_module(graph) for graph in graphs]
    states = [initial_state(module, [graph]) for module, graph in zip(singles, graphs)]
    gate = torch.as_tensor(gate_inputs(graphs[0]))
    x_hats = [batch.x_hat[b:b + 1].copy() for b in range(len(paths))]
    spikes = [np.zeros(1, dtype=np.int64) for _ in paths]
    rng = np.random.default_rng(1)
    for _ in range(5):
        z, u = sc.x0[:3] + rng.normal(0.0, 1.0, (len(paths), 3)), np.zeros((len(paths), 3))
        together = batch.sample(z, u)
        for b, (module, state) in enumerate(zip(singles, states)):
            held = np.concatenate([z[b:b + 1], u[b:b + 1], x_hats[b]], axis=1)
            x_hats[b] = step_sample(module, state, gate, held, spikes[b])
            np.testing.assert_allclose(together[b], x_hats[b][0], rtol=1e-12, atol=1e-9)
            assert batch.spikes[b] == spikes[b][0]


def test_norse_closes_the_loop_within_the_goal_of_the_packages_rmse_over_20_runs(tmp_path):
    """The issue's goal on a short horizon (10 s, the last 3.3 s measured: the dispersed start's
    approach, where the tick's semantics matter most; a reader that ticks the slow loop or
    resets without the overshoot is ~3x here), 20 runs, median against the package's median."""
    data = compare(runs=20, seed=0, duration=10.0, folder=tmp_path)
    assert data['package']['diverged'] == 0
    assert data['median_ratio'] <= GOAL_RATIO, data['ratio_per_run']
    assert np.all(np.isfinite(data['norse']['rmse_position_m']))
