"""A campaign's spec (YAML: scenario, runs, filters, a grid of settings), parsed and validated,
its cells, and the rows of the finished ones on disk."""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from snn_estimator.filters.estimators import FILTER_KINDS
from snn_tools.campaign.approach_cells import TABLE_COLUMNS as APPROACH_COLUMNS
from snn_tools.campaign.cells import (
    APPROACH,
    RUNS_PER_TASK,
    SCENARIOS,
    check_cell,
    check_setting,
    row_identity,
)
from snn_tools.paths import config_file

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


def canonical(value) -> str:
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
        digest = hashlib.sha256(canonical([self.filter, self.settings]).encode()).hexdigest()
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
        return hashlib.sha256(canonical(identity).encode()).hexdigest()

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
        return canonical(value)
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
        key = canonical([kind, settings])
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
    write_atomic(out / 'spec.yaml', yaml.safe_dump(spec.as_dict(), sort_keys=False))
    write_atomic(digest_file, spec.digest() + '\n')


def _spec_changes(out: Path, spec: CampaignSpec) -> str:
    """Which top-level keys differ from the spec stored in DIR."""
    stored = yaml.load((out / 'spec.yaml').read_text(), Loader=_SpecLoader) or {}
    changed = [k for k, v in spec.as_dict().items()
               if k != 'description' and canonical(stored.get(k)) != canonical(v)]
    return 'changed: ' + ', '.join(changed) if changed else 'spec.yaml edited by hand'


def write_atomic(path: Path, text: str) -> None:
    """Write to a temporary file beside ``path``, then rename: a reader sees all or nothing."""
    temporary = path.with_name(f'.{path.name}.{os.getpid()}.tmp')
    with open(temporary, 'w') as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)


def cell_path(out: Path, cell: Cell) -> Path:
    return out / 'cells' / f'{cell.name}.json'


def read_rows(out: Path, cells: list[Cell], scenario: str | None = None) -> list[dict]:
    """The rows of the finished cells, in spec order (a cell file is complete or absent). Given
    the ``scenario``, a row written before rows had the scenario and dynamics_model columns
    gets them (cells.row_identity), so a resumed campaign's table has them on every row."""
    rows = []
    for cell in cells:
        path = cell_path(out, cell)
        if path.exists():
            row = json.loads(path.read_text())
            if scenario is not None and 'scenario' not in row:
                row = {'filter': row['filter'], **row_identity(scenario, cell.settings), **row}
            rows.append(row)
    return rows


def state_names(rows: list[dict]) -> list[str]:
    """States in the rows' column order (rmse_<state>)."""
    return [key[len('rmse_'):] for key in rows[0] if key.startswith('rmse_')] if rows else []


def swept(spec) -> list[str]:
    """Grid settings with more than one value: the axes of the figures."""
    return [name for name, values in spec.grid.items() if len(values) > 1]


def identity_columns(spec) -> list[str]:
    """The scenario and the filters' dynamics model, then the grid settings: the columns of the
    summary's and the page's tables that say which cell a row is (dynamics_model once, where
    the grid sweeps it)."""
    return ['scenario', *(['dynamics_model'] if 'dynamics_model' not in spec.grid else []), *spec.grid]


def reading_columns(spec, rows, states, optional=('spike_fraction', 'final_range_median')) -> list[str]:
    """The reading columns of the summary's and the page's tables: the approach's safety figures
    (approach_cells.TABLE_COLUMNS), or the RMSE per state, then those of ``optional`` that some of
    ``rows`` holds as a finite number."""
    if spec.scenario == APPROACH:
        return list(APPROACH_COLUMNS)
    shown = [c for c in optional if any(isinstance(r.get(c), (int, float)) and math.isfinite(r[c]) for r in rows)]
    return [*(f'rmse_{s}' for s in states), *shown]
