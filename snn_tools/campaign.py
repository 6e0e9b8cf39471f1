"""Monte-Carlo campaigns on Dask: a grid of settings x filters, one table, resumable.

``snn_campaign --spec SPEC.yaml [--workers N | --scheduler tcp://HOST:PORT] [--out DIR]``

A spec (see config/campaigns/example.yaml) names the scenario, the runs per cell, the filters,
a ``grid`` of settings (every combination is a grid point) and optional fixed ``settings``;
the allowed setting names are campaign_cells.SETTINGS. One *cell* is one filter at one grid
point. Everything is checked before anything runs: unknown keys, bad values (every cell is built
and stepped once), empty grids.

DIR receives ``spec.yaml`` and ``spec.sha256`` (the normalised spec and its hash), one JSON file
per finished cell under ``cells/`` (written atomically), then ``results.parquet`` (one row per
cell, in spec order), ``summary.md`` and ``figures/``. Running the same spec into the same DIR
again computes only the missing cells; another spec is refused. Ctrl-C, or a failed cell,
still writes the table of the finished cells.

Seeding (common random numbers): every cell uses the spec's ``seed``; run b draws from seed + b
(plant, sensor and decoder streams of the core), and a silenced fraction is drawn from the seed
too. So cells differ only by their settings, and a cell's numbers are the same whatever the
workers, the cluster or the order the cells run in (bit for bit on machines with the same CPU
type and libraries; another CPU may round the last digits of a BLAS product differently).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import itertools
import json
import os
import re
import signal
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from snn_estimator.filters.estimators import FILTER_KINDS

from .campaign_cells import (
    RUNS_PER_TASK,
    SCENARIOS,
    SETTINGS,
    cell_row,
    check_cell,
    check_setting,
    chunk_bounds,
    run_chunk,
)
from .paths import config_file
from .progress import Progress

#: Top-level keys of a spec: required ones, then optional ones with their defaults.
REQUIRED_KEYS = ('scenario', 'runs', 'filters', 'grid')
OPTIONAL_KEYS = {'settings': {}, 'seed': 0, 'runs_per_task': RUNS_PER_TASK, 'description': ''}
#: Times Dask re-runs a task that raised (a worker that dies is handled by the scheduler, which
#: moves its tasks to other workers up to distributed.scheduler.allowed-failures times).
RETRIES = 2


class SpecError(ValueError):
    """A campaign spec that cannot run; the message names the key and what to change."""


class CellFailed(RuntimeError):
    """A cell whose task still failed after its retries; the finished cells are kept."""


# ---------------------------------------------------------------- spec
class _SpecLoader(yaml.SafeLoader):
    """YAML as users write numbers: PyYAML reads 1e-3 (no dot) as a string, this loader as 0.001."""


_SpecLoader.add_implicit_resolver(
    'tag:yaml.org,2002:float',
    re.compile(r'^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$'),
    list('-+0123456789'))


def _canonical(value) -> str:
    """A stable text form of a value, for hashing and comparing settings."""
    return json.dumps(value, sort_keys=True, separators=(',', ':'))


@dataclass(frozen=True)
class Cell:
    """One filter at one grid point; ``settings`` holds the grid values, then the fixed ones."""

    filter: str
    settings: dict

    @property
    def name(self) -> str:
        """File stem under cells/: readable, and unique within a spec."""
        digest = hashlib.sha256(_canonical([self.filter, self.settings]).encode()).hexdigest()
        return f'{self.filter}-{digest[:12]}'


@dataclass(frozen=True)
class CampaignSpec:
    """A parsed, type-checked spec (values are checked against the core by :func:`validate`)."""

    scenario: str
    runs: int
    filters: tuple
    grid: dict
    settings: dict = field(default_factory=dict)
    seed: int = 0
    runs_per_task: int = RUNS_PER_TASK
    description: str = ''

    def as_dict(self) -> dict:
        """The spec as YAML would hold it."""
        return {'description': self.description, 'scenario': self.scenario, 'runs': self.runs,
                'seed': self.seed, 'runs_per_task': self.runs_per_task, 'filters': list(self.filters),
                'grid': self.grid, 'settings': self.settings}

    def digest(self) -> str:
        """sha256 of everything that decides the numbers or the rows (not the description)."""
        identity = {k: v for k, v in self.as_dict().items() if k != 'description'}
        return hashlib.sha256(_canonical(identity).encode()).hexdigest()

    def cells(self) -> list[Cell]:
        """Every (grid point, filter), grid points in the spec's order, filters inner, so the
        first cells to finish compare all filters."""
        keys = list(self.grid)
        points = itertools.product(*(self.grid[k] for k in keys))
        pairs = ((point, kind) for point in points for kind in self.filters)
        return [Cell(kind, {**dict(zip(keys, point)), **self.settings}) for point, kind in pairs]


def _integer(data: dict, key: str, low: int) -> int:
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise SpecError(f'{key} must be an integer >= {low}, got {value!r}')
    return value


def _filters(value) -> tuple:
    if not isinstance(value, list) or not value:
        raise SpecError(f'filters must be a non-empty list of {", ".join(FILTER_KINDS)}; got {value!r}')
    unknown = [k for k in value if not isinstance(k, str) or k not in FILTER_KINDS]
    if unknown:
        raise SpecError(f'filters: unknown filter {unknown[0]!r}; choose from {", ".join(FILTER_KINDS)}')
    if len(set(value)) != len(value):
        raise SpecError(f'filters: each filter once, got {value}')
    return tuple(value)


def _plain(where: str, value) -> str:
    """The canonical text of a setting value; SpecError for what JSON cannot hold (a YAML date)."""
    try:
        return _canonical(value)
    except TypeError:
        raise SpecError(f'{where}: a value is a number, text, true/false or a list of them; '
                        f'got {value!r}') from None


def _setting_names(section: str, mapping, scenario: str) -> None:
    """Every key of ``mapping`` must be in the settings table and apply to the scenario."""
    if not isinstance(mapping, dict):
        raise SpecError(f'{section} must be a mapping of setting: value, got {mapping!r}')
    for name in mapping:
        try:
            check_setting(name, scenario)
        except ValueError as error:
            raise SpecError(f'{section}.{name}: {error}') from None


def _grid(value, scenario: str) -> dict:
    if not isinstance(value, dict) or not value:
        raise SpecError('grid must map at least one setting to a list of values, e.g. '
                        'grid: {neuron_count: [100, 200]}; got ' + repr(value))
    _setting_names('grid', value, scenario)
    for name, values in value.items():
        if not isinstance(values, list) or not values:
            raise SpecError(f'grid.{name} must be a non-empty list of values (a single value '
                            f'belongs under settings), got {values!r}')
        if len({_plain(f'grid.{name}', v) for v in values}) != len(values):
            raise SpecError(f'grid.{name} lists a value twice: {values}')
    return dict(value)


def parse_spec(data) -> CampaignSpec:
    """Check a spec's structure and types; SpecError names the key."""
    if not isinstance(data, dict):
        raise SpecError(f'a spec is a mapping with keys {", ".join(REQUIRED_KEYS)}; got {type(data).__name__}')
    unknown = [k for k in data if k not in REQUIRED_KEYS and k not in OPTIONAL_KEYS]
    if unknown:
        raise SpecError(f'unknown spec key {unknown[0]!r}; a spec has '
                        f'{", ".join((*REQUIRED_KEYS, *OPTIONAL_KEYS))} (settings go under grid or settings)')
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise SpecError(f'the spec lacks {missing[0]!r} (required: {", ".join(REQUIRED_KEYS)})')
    data = {**OPTIONAL_KEYS, **data}
    if not isinstance(data['scenario'], str) or data['scenario'] not in SCENARIOS:
        raise SpecError(f'scenario must be one of {", ".join(SCENARIOS)}; got {data["scenario"]!r}')
    scenario = data['scenario']
    grid = _grid(data['grid'], scenario)
    settings = data['settings'] if data['settings'] is not None else {}
    _setting_names('settings', settings, scenario)
    for name, value in settings.items():
        _plain(f'settings.{name}', value)
    both = sorted(set(grid) & set(settings))
    if both:
        raise SpecError(f'{both[0]!r} is under both grid and settings; keep it in one')
    if not isinstance(data['description'], str):
        raise SpecError(f'description must be text, got {data["description"]!r}')
    return CampaignSpec(
        scenario=scenario, runs=_integer(data, 'runs', 1), filters=_filters(data['filters']),
        grid=grid, settings=dict(settings), seed=_integer(data, 'seed', 0),
        runs_per_task=_integer(data, 'runs_per_task', 1), description=data['description'])


def load_spec(path) -> CampaignSpec:
    """Read and parse a spec file (a path, or a name under the package's config/)."""
    try:
        resolved = config_file(str(path))
    except FileNotFoundError as error:
        raise SpecError(f'spec file not found: {error}') from None
    try:
        data = yaml.load(resolved.read_text(), Loader=_SpecLoader)
    except yaml.YAMLError as error:
        raise SpecError(f'{resolved} is not valid YAML: {error}') from None
    return parse_spec(data)


def _check(where: str, scenario: str, kind: str, settings: dict, seed: int) -> None:
    """check_cell, with the core's error turned into a SpecError that says where it came from."""
    try:
        check_cell(scenario, kind, settings, seed)
    except (ValueError, TypeError) as error:
        raise SpecError(f'{where} (filter {kind}): {error}') from None


def validate(spec: CampaignSpec) -> None:
    """Build and step every cell once before anything runs. First the cell of every setting's
    first value, then each value varied alone from it (so an error names the key and value at
    fault), then every combination (some values fail only together)."""
    first = {name: values[0] for name, values in spec.grid.items()}
    checked = set()  # a cell checked in the first two passes is not built again in the third

    def check(where: str, kind: str, settings: dict) -> None:
        key = _canonical([kind, settings])
        if key not in checked:
            _check(where, spec.scenario, kind, settings, spec.seed)
            checked.add(key)

    for kind in spec.filters:
        check(f'grid cell {first} with settings {spec.settings}', kind, {**first, **spec.settings})
        for name, values in spec.grid.items():
            for value in values[1:]:
                check(f'grid.{name} = {value!r}', kind, {**first, name: value, **spec.settings})
    for cell in spec.cells():
        check(f'grid cell {cell.settings}', cell.filter, cell.settings)


# ---------------------------------------------------------------- campaign directory
def prepare_directory(out: Path, spec: CampaignSpec) -> None:
    """Create DIR with the spec and its hash, or check that DIR holds this very spec."""
    out.mkdir(parents=True, exist_ok=True)
    (out / 'cells').mkdir(exist_ok=True)
    digest_file = out / 'spec.sha256'
    if digest_file.exists():
        stored = digest_file.read_text().strip()
        if stored != spec.digest():
            raise SpecError(f'{out} holds a campaign of another spec ({_spec_changes(out, spec)}); '
                            'give another --out, or delete the directory to start over')
        return
    _write_atomic(out / 'spec.yaml', yaml.safe_dump(spec.as_dict(), sort_keys=False))
    _write_atomic(digest_file, spec.digest() + '\n')


def _spec_changes(out: Path, spec: CampaignSpec) -> str:
    """Which top-level keys differ from the spec stored in DIR."""
    stored = yaml.load((out / 'spec.yaml').read_text(), Loader=_SpecLoader) or {}
    changed = [k for k, v in spec.as_dict().items()
               if k != 'description' and _canonical(stored.get(k)) != _canonical(v)]
    return 'changed: ' + ', '.join(changed) if changed else 'spec.yaml edited by hand'


def _write_atomic(path: Path, text: str) -> None:
    """Write to a temporary file beside ``path``, then rename: a reader sees all or nothing."""
    temporary = path.with_name(f'.{path.name}.{os.getpid()}.tmp')
    with open(temporary, 'w') as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)


def cell_path(out: Path, cell: Cell) -> Path:
    return out / 'cells' / f'{cell.name}.json'


def read_rows(out: Path, cells: list[Cell]) -> list[dict]:
    """The rows of the finished cells, in spec order (a cell file is complete or absent)."""
    rows = []
    for cell in cells:
        path = cell_path(out, cell)
        if path.exists():
            rows.append(json.loads(path.read_text()))
    return rows


def write_table(out: Path, spec: CampaignSpec, rows: list[dict]) -> Path:
    """results.parquet from the rows; settings with list values (e.g. a per-axis
    boundary_layer) become JSON text columns. The spec rides along as schema metadata."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    listed = {name for row in rows for name in (*spec.grid, *spec.settings)
              if isinstance(row.get(name), (list, dict))}
    rows = [{k: (_canonical(v) if k in listed else v) for k, v in row.items()} for row in rows]
    table = pa.Table.from_pylist(rows).replace_schema_metadata(
        {'spec_sha256': spec.digest(), 'spec': yaml.safe_dump(spec.as_dict(), sort_keys=False)})
    path = out / 'results.parquet'
    temporary = out / f'.results.parquet.{os.getpid()}.tmp'
    pq.write_table(table, temporary)
    os.replace(temporary, path)
    return path


def write_outputs(out: Path, spec: CampaignSpec) -> list[dict]:
    """Table, summary and figures of whatever cells are finished; returns the rows."""
    from .campaign_report import write_report
    cells = spec.cells()
    rows = read_rows(out, cells)
    write_table(out, spec, rows)
    write_report(out, spec, rows, total_cells=len(cells))
    return rows


# ---------------------------------------------------------------- progress
class CampaignProgress:
    """Cells and runs done, runs/s and ETA on stderr through :class:`snn_tools.progress.Progress`:
    one redrawn line on a terminal, nothing in a log. ``say`` lines (what runs, the dashboard)
    are printed unless ``quiet``."""

    def __init__(self, quiet: bool = False, stream=sys.stderr):
        self.quiet = quiet
        self.stream = stream
        self.bar = Progress(0, 'runs', stream=stream, enabled=False if quiet else None)
        self.cells_total = self.cells_done = 0

    def start(self, cells_total: int, cells_skipped: int, runs_total: int) -> None:
        self.cells_total, self.cells_done = cells_total, cells_skipped
        self.bar.restart(runs_total)
        self.bar.open()
        if cells_skipped:
            self.say(f'{cells_skipped} of {cells_total} cells already done, skipped')
        self._note()

    def say(self, text: str) -> None:
        if self.quiet:
            return
        if self.bar.enabled:
            self.bar.say(text)
        else:
            self.stream.write(text + '\n')
            self.stream.flush()

    def runs_finished(self, runs: int) -> None:
        self.bar.advance(runs)

    def cell_finished(self) -> None:
        self.cells_done += 1
        self._note()

    def _note(self) -> None:
        self.bar.note = f'cells {self.cells_done}/{self.cells_total}'
        self.bar.draw(force=True)

    def line(self) -> str:
        return self.bar.line()

    def close(self) -> None:
        self.bar.close()


# ---------------------------------------------------------------- running
@dataclass
class Outcome:
    """What a call of :func:`run_campaign` did."""

    cells: int
    skipped: int
    computed: int
    rows: list


def _submit(client, spec: CampaignSpec, cells: list[Cell]) -> dict:
    """One task per batch of runs, earlier cells first; future -> (cell, batch index)."""
    tasks = [(cell, index, first, count) for cell in cells
             for index, (first, count) in enumerate(chunk_bounds(spec.runs, spec.runs_per_task))]
    futures, prefix = {}, f'snn-campaign-{spec.digest()[:10]}'
    for order, (cell, index, first, count) in enumerate(tasks):
        future = client.submit(
            run_chunk, spec.scenario, cell.filter, cell.settings, spec.seed, first, count,
            key=f'{prefix}-{cell.name}-{index}', retries=RETRIES, priority=len(tasks) - order)
        futures[future] = (cell, index)
    return futures


def _compute(client, spec: CampaignSpec, cells: list[Cell], out: Path,
             progress: CampaignProgress) -> None:
    """Run the cells' tasks; write each cell's row as soon as its last batch is in."""
    from dask.distributed import as_completed
    batches = len(chunk_bounds(spec.runs, spec.runs_per_task))
    partials: dict[str, dict[int, dict]] = {cell.name: {} for cell in cells}
    futures = _submit(client, spec, cells)
    for future in as_completed(futures):
        cell, index = futures.pop(future)
        try:
            partial = future.result()
        except Exception as error:  # any failure of the task (after its retries) stops the campaign
            raise CellFailed(f'cell {cell.filter} {cell.settings} failed after {RETRIES} retries: '
                             f'{type(error).__name__}: {error}') from error
        progress.runs_finished(partial['runs'])
        done = partials[cell.name]
        done[index] = partial
        if len(done) == batches:
            row = cell_row(cell.filter, cell.settings, spec.runs, spec.seed,
                           [done[i] for i in range(batches)])
            _write_atomic(cell_path(out, cell), json.dumps(row) + '\n')
            del partials[cell.name]
            progress.cell_finished()


def run_campaign(spec: CampaignSpec, out: Path, client, progress: CampaignProgress | None = None) -> Outcome:
    """Compute the cells of ``spec`` missing from ``out`` on the Dask ``client``, then write the
    table, summary and figures; on Ctrl-C or a failed cell, write those of the finished cells
    and re-raise. Call :func:`validate` first."""
    progress = progress or CampaignProgress(quiet=True)
    out = Path(out)
    prepare_directory(out, spec)
    cells = spec.cells()
    pending = [cell for cell in cells if not cell_path(out, cell).exists()]
    progress.start(len(cells), len(cells) - len(pending), len(pending) * spec.runs)
    try:
        if pending:
            _compute(client, spec, pending, out, progress)
    finally:
        progress.close()
        rows = write_outputs(out, spec)
    return Outcome(cells=len(cells), skipped=len(cells) - len(pending), computed=len(pending), rows=rows)


@contextlib.contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None) -> Iterator:
    """A client of the scheduler at ``scheduler``, or of a LocalCluster of ``workers``
    single-threaded worker processes (numba kernels hold the GIL: processes, not threads)."""
    from dask.distributed import Client, LocalCluster
    if scheduler:
        with Client(scheduler, timeout='30s') as client:
            yield client
        return
    with _sigint_ignored():
        cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1,
                               processes=True)
    with cluster, Client(cluster) as client:
        yield client


@contextlib.contextmanager
def _sigint_ignored() -> Iterator:
    """Ignore SIGINT while local workers are spawned: they inherit it, so a Ctrl-C in the
    terminal reaches only this process, which then closes them, instead of every worker
    dying with its own KeyboardInterrupt traceback."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def dashboard(client) -> str | None:
    """The dashboard address when the scheduler serves one (it needs bokeh)."""
    services = client.scheduler_info().get('services', {})
    return client.dashboard_link if 'dashboard' in services else None


# ---------------------------------------------------------------- command line
def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='snn_campaign', description='Run a Monte-Carlo campaign (a grid of settings x filters) '
        'on Dask; write results.parquet, summary.md and figures to --out. Running it again with '
        'the same spec and --out computes only the missing cells.')
    parser.add_argument('--spec', help='campaign spec (YAML): a path, or a name under config/, '
                                       'e.g. campaigns/example.yaml')
    where = parser.add_mutually_exclusive_group()
    where.add_argument('--workers', type=int, help='local worker processes (default: one per core)')
    where.add_argument('--scheduler', help='address of a running `dask scheduler`, e.g. tcp://host:8786')
    parser.add_argument('--out', type=Path, help='campaign directory (default: runs/campaigns/<spec name>)')
    parser.add_argument('--check', action='store_true', help='validate the spec, count the cells, run nothing')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')
    parser.add_argument('--list-settings', action='store_true',
                        help='print the settings a grid may sweep, and where each goes')
    return parser


def settings_table() -> str:
    """The allowed settings, one a line: name, where it goes, scenarios, meaning."""
    return '\n'.join(f'{name:<26} {s.target:<10} {",".join(s.scenarios):<23} {s.help}'
                     for name, s in SETTINGS.items())


def main(argv=None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.list_settings:
        print(settings_table())
        return 0
    if not args.spec:
        parser.error('--spec is required')
    if args.workers is not None and args.workers < 1:
        parser.error('--workers must be >= 1')
    out = args.out or Path('runs/campaigns') / Path(args.spec).stem
    progress = CampaignProgress(quiet=args.quiet)
    try:
        spec = load_spec(args.spec)
        validate(spec)
        cells = spec.cells()
        print(f'{len(cells)} cells ({len(cells) // len(spec.filters)} grid points x '
              f'{len(spec.filters)} filters) x {spec.runs} runs, spec {spec.digest()[:12]}', file=sys.stderr)
        if args.check:
            return 0
        prepare_directory(out, spec)
    except SpecError as error:
        print(f'snn_campaign: error: {error}', file=sys.stderr)
        return 2
    try:
        with contextlib.ExitStack() as stack:
            try:
                client = stack.enter_context(dask_client(args.workers, args.scheduler))
            except OSError as error:  # nothing at --scheduler, or no local ports/processes
                print(f'snn_campaign: error: cannot reach the Dask cluster: {error}', file=sys.stderr)
                return 1
            link = dashboard(client)
            if link:
                progress.say(f'dask dashboard: {link}')
            outcome = run_campaign(spec, out, client, progress)
    except KeyboardInterrupt:
        done = len(read_rows(out, spec.cells()))
        print(f'\ninterrupted: {done} of {len(spec.cells())} cells in {out / "results.parquet"}; '
              'the same command finishes the rest', file=sys.stderr)
        return 130
    except CellFailed as error:
        print(f'snn_campaign: {error}\nfinished cells are in {out / "results.parquet"}; '
              'the same command retries the rest', file=sys.stderr)
        return 1
    print(f'{outcome.computed} cells computed, {outcome.skipped} already done: '
          f'{out / "results.parquet"}, {out / "summary.md"}' +
          (f', {out / "campaign.html"}' if (out / 'campaign.html').exists() else ''))
    return 0


if __name__ == '__main__':
    sys.exit(main())
