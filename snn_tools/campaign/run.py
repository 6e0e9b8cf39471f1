"""Monte-Carlo campaigns on Dask: a grid of settings x filters, one table, resumable.

``snn_campaign --spec SPEC.yaml [--workers N | --scheduler tcp://HOST:PORT] [--out DIR]``

A spec (see config/campaigns/example.yaml) names the scenario, the runs per cell, the filters,
a ``grid`` of settings (every combination is a grid point) and optional fixed ``settings``;
the allowed setting names are campaign_cells.SETTINGS. One *cell* is one filter at one grid
point. ``scenario: approach`` (config/campaigns/approach.yaml) flies each cell's runs from 5 km
to contact and gives their safety figures (campaign.approach_cells) instead of RMSE. Everything
is checked before anything runs: unknown keys, bad values (every cell is built and stepped
once), empty grids.

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
import json
import os
import signal
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import yaml

from snn_tools.campaign.cells import (
    SETTINGS,
    cell_row,
    chunk_bounds,
    run_chunk,
)
from snn_tools.campaign.report import write_report
from snn_tools.campaign.spec import (
    RETRIES,
    CampaignSpec,
    Cell,
    CellFailed,
    SpecError,
    canonical,
    cell_path,
    load_spec,
    prepare_directory,
    read_rows,
    validate,
    write_atomic,
)
from snn_tools.progress import Progress


def write_table(out: Path, spec: CampaignSpec, rows: list[dict]) -> Path:
    """results.parquet from the rows; settings with list values (e.g. a per-axis
    boundary_layer) become JSON text columns. The spec rides along as schema metadata."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    listed = {name for row in rows for name in (*spec.grid, *spec.settings)
              if isinstance(row.get(name), (list, dict))}
    rows = [{k: (canonical(v) if k in listed else v) for k, v in row.items()} for row in rows]
    table = pa.Table.from_pylist(rows).replace_schema_metadata(
        {'spec_sha256': spec.digest(), 'spec': yaml.safe_dump(spec.as_dict(), sort_keys=False)})
    path = out / 'results.parquet'
    temporary = out / f'.results.parquet.{os.getpid()}.tmp'
    pq.write_table(table, temporary)
    os.replace(temporary, path)
    return path


def write_outputs(out: Path, spec: CampaignSpec) -> list[dict]:
    """Table, summary and figures of whatever cells are finished; returns the rows."""
    cells = spec.cells()
    rows = read_rows(out, cells, spec.scenario)
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
            row = cell_row(spec.scenario, cell.filter, cell.settings, spec.runs, spec.seed,
                           [done[i] for i in range(batches)])
            write_atomic(cell_path(out, cell), json.dumps(row) + '\n')
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
