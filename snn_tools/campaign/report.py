"""summary.md and figures of a campaign, from its rows (one dict per finished cell).

Figures, under DIR/figures/ (matplotlib's object API: no pyplot, so no GUI backend): a heatmap
of the RMSE of the first position and the first velocity state over the first two swept
settings, one panel per filter (and per value of a third swept setting); the RMSE against the
setting when only one is swept; the spike fraction against N when neuron_count is swept.
Settings not on an axis are held at their first value.
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from snn_estimator.filters.estimators import FILTER_KINDS
from snn_tools.campaign.cells import APPROACH, SCENARIOS
from snn_tools.campaign.page import write_campaign_page  # the interactive page of the same rows
from snn_tools.campaign.spec import identity_columns, reading_columns, state_names, swept
from snn_tools.figures import UNITS, colour_of, label_of

#: Rows per filter listed in summary.md (all of them are in results.parquet).
SUMMARY_ROWS = 100
#: Panels across a heatmap figure (values of a third swept setting) and lines in a spike plot.
MAX_COLUMNS = 6
MAX_LINES = 8


def _text(value) -> str:
    """A setting value as a label."""
    return json.dumps(value) if isinstance(value, (list, dict)) else str(value)


def _same(a, b) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def _number(value) -> str:
    return '-' if value is None or math.isnan(value) else f'{value:.3g}'


def _pick(rows: list[dict], kind: str, fixed: dict) -> list[dict]:
    return [r for r in rows if r['filter'] == kind and all(_same(r.get(k), v) for k, v in fixed.items())]


def _save(fig: Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


def _held(spec, names: list[str]) -> dict:
    """The first value of every swept setting not in ``names`` (what a figure holds fixed)."""
    return {n: spec.grid[n][0] for n in swept(spec) if n not in names}


def _held_text(held: dict) -> str:
    return ('; held at ' + ', '.join(f'{k} = {_text(v)}' for k, v in held.items())) if held else ''


def heatmap(spec, rows: list[dict], state: str, path: Path) -> Path | None:
    """RMSE of ``state`` over the first two swept settings, a row of panels per filter, a column
    per value of the third (up to MAX_COLUMNS); one log colour scale for all panels."""
    axes_names = swept(spec)
    if len(axes_names) < 2:
        return None
    y_name, x_name = axes_names[:2]
    columns = spec.grid[axes_names[2]][:MAX_COLUMNS] if len(axes_names) > 2 else [None]
    held = _held(spec, axes_names[:3])
    ys, xs = spec.grid[y_name], spec.grid[x_name]
    grids = {}
    for kind, column in itertools.product(spec.filters, columns):
        fixed = dict(held, **({axes_names[2]: column} if column is not None else {}))
        grid = np.full((len(ys), len(xs)), np.nan)
        for row in _pick(rows, kind, fixed):
            i = next(i for i, v in enumerate(ys) if _same(v, row[y_name]))
            j = next(j for j, v in enumerate(xs) if _same(v, row[x_name]))
            grid[i, j] = row[f'rmse_{state}']
        grids[kind, _text(column)] = grid
    values = np.concatenate([g[np.isfinite(g) & (g > 0)] for g in grids.values()])
    if not values.size:
        return None
    norm = LogNorm(values.min(), max(values.max(), values.min() * 1.0001))
    fig = Figure(figsize=(1.8 + 0.9 * len(xs) * len(columns), 0.9 + 0.5 * len(ys) * len(spec.filters)),
                 layout='constrained')
    panels = fig.subplots(len(spec.filters), len(columns), squeeze=False, sharex=True, sharey=True)
    for (r, kind), (c, column) in itertools.product(enumerate(spec.filters), enumerate(columns)):
        ax, grid = panels[r, c], grids[kind, _text(column)]
        image = ax.imshow(grid, norm=norm, cmap='viridis_r', aspect='auto')
        for i, j in itertools.product(range(len(ys)), range(len(xs))):
            dark = np.isfinite(grid[i, j]) and norm(grid[i, j]) > 0.6  # viridis_r: large is dark
            ax.text(j, i, _number(grid[i, j]), ha='center', va='center', fontsize=7,
                    color='white' if dark else 'black')
        ax.set_xticks(range(len(xs)), [_text(v) for v in xs], fontsize=7)
        ax.set_yticks(range(len(ys)), [_text(v) for v in ys], fontsize=7)
        if r == len(spec.filters) - 1:
            ax.set_xlabel(x_name, fontsize=8)
        if c == 0:
            ax.set_ylabel(f'{label_of(kind)}\n{y_name}', fontsize=8)
        if r == 0 and column is not None:
            ax.set_title(f'{axes_names[2]} = {_text(column)}', fontsize=8)
    unit = UNITS.get(state, '')
    fig.colorbar(image, ax=panels, label=f'RMSE {state} [{unit}]')
    fig.suptitle(f'RMSE of {state}, last {_window(spec)} s, {spec.runs} runs per cell{_held_text(held)}',
                 fontsize=9)
    return _save(fig, path)


def _window(spec) -> str:
    """The metric window as the spec sets it, or the scenario's default."""
    if 'metric_window' in spec.grid:
        return 'metric_window (per cell)'
    return _text(spec.settings.get('metric_window', SCENARIOS[spec.scenario]().metric_window))


def line_plot(spec, rows: list[dict], state: str, path: Path) -> Path | None:
    """RMSE of ``state`` against the only swept setting, one line per filter."""
    axes_names = swept(spec)
    if len(axes_names) != 1:
        return None
    name = axes_names[0]
    values = spec.grid[name]
    fig = Figure(figsize=(7, 4), layout='constrained')
    ax = fig.subplots()
    for kind in spec.filters:
        points = {_text(r[name]): r[f'rmse_{state}'] for r in _pick(rows, kind, {})}
        ax.plot(range(len(values)), [points.get(_text(v), np.nan) for v in values], marker='o',
                color=colour_of(kind), label=label_of(kind))
    ax.set_xticks(range(len(values)), [_text(v) for v in values])
    ax.set_xlabel(name)
    ax.set_yscale('log')
    ax.set_ylabel(f'RMSE {state} [{UNITS.get(state, "")}]')
    ax.grid(alpha=0.3, which='both')
    ax.legend(fontsize=8)
    ax.set_title(f'RMSE of {state}, {spec.runs} runs per cell', fontsize=9)
    return _save(fig, path)


def spike_plot(spec, rows: list[dict], path: Path) -> Path | None:
    """Spike fraction against neuron_count for each spiking filter: one line per combination
    of the other swept settings (up to MAX_LINES; beyond that they are held at their first value)."""
    spiking = [k for k in spec.filters if FILTER_KINDS[k][1]]
    if 'neuron_count' not in swept(spec) or not spiking:
        return None
    others = [n for n in swept(spec) if n != 'neuron_count']
    combos = list(itertools.product(*(spec.grid[n] for n in others)))
    if len(combos) * len(spiking) > MAX_LINES:
        combos = [tuple(spec.grid[n][0] for n in others)]
    counts = spec.grid['neuron_count']
    fig = Figure(figsize=(7, 4), layout='constrained')
    ax = fig.subplots()
    for (index, kind), combo in itertools.product(enumerate(spiking), combos):
        fixed = dict(zip(others, combo))
        points = {r['neuron_count']: r['spike_fraction'] for r in _pick(rows, kind, fixed)}
        label = label_of(kind) + ''.join(f', {k} {_text(v)}' for k, v in fixed.items())
        ax.plot(counts, [100 * points[n] if n in points else np.nan for n in counts],
                marker='os^vD'[index % 5], linestyle=('-', '--', ':')[index % 3], fillstyle='none',
                color=colour_of(kind) if len(combos) == 1 else None, label=label)
    ax.set_xlabel('neurons N')
    ax.set_ylabel('spikes [% of N x steps]')
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(f'spike fraction, {spec.runs} runs per cell', fontsize=9)
    return _save(fig, path)


def figures(out: Path, spec, rows: list[dict]) -> list[Path]:
    """Every figure that the grid allows (see the module docstring)."""
    states = state_names(rows)
    if not states:
        return []
    shown = [states[0], states[len(states) // 2]] if len(states) > 1 else states
    drawn = []
    for state in dict.fromkeys(shown):
        drawn.append(heatmap(spec, rows, state, out / 'figures' / f'heatmap_rmse_{state}.png'))
        drawn.append(line_plot(spec, rows, state, out / 'figures' / f'rmse_{state}.png'))
    drawn.append(spike_plot(spec, rows, out / 'figures' / 'spike_fraction_vs_N.png'))
    return [path for path in drawn if path is not None]


def _filter_table(spec, rows: list[dict], kind: str, states: list[str]) -> list[str]:
    """Markdown table of one filter's rows: scenario, dynamics model and grid settings, then RMSE
    per state, spikes, range, or for the approach its safety figures (approach_cells.TABLE_COLUMNS)."""
    mine = [r for r in rows if r['filter'] == kind]
    names, readings = identity_columns(spec), reading_columns(spec, mine, states)
    head = [*names, *readings]
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for row in mine[:SUMMARY_ROWS]:
        cells = [_text(row.get(k, '-')) for k in names]
        cells += [_number(row.get(c)) for c in readings]
        lines.append('| ' + ' | '.join(cells) + ' |')
    if len(mine) > SUMMARY_ROWS:
        lines.append(f'\n(first {SUMMARY_ROWS} of {len(mine)} rows; all in results.parquet)')
    return lines


def _readings_text(spec) -> str:
    """What the readings of the rows are."""
    common = ('Common random numbers: every cell runs seeds seed .. seed + runs - 1 (the same plant, '
              'sensor and decoder noise), so cells differ only by their settings. ')
    if spec.scenario == APPROACH:
        return common + ('Each cell flies its runs to contact, abort or no-go (snn_estimator.sim.approach); '
                         'its row is summarize() of the flights, flattened: `contact_rate` (contacts / runs), '
                         '`success`, closing speed (m/s) and lateral offset (m) at contact, '
                         '`corridor_violation_runs`, `keep_out_entry_before_go`, `outcomes_abort` / '
                         '`outcomes_no_go`, delta-v (m/s per run), the mean NEES, the hold-point error (m) at '
                         "each hold's decision (go or no-go), spikes per run (all of summarize()'s figures in "
                         'results.parquet).')
    return common + (f'Readings over the final {_window(spec)} s: `rmse_<state>`, the ordinary RMSE over runs '
                     'and time; `mean_error_<state>` (in results.parquet), the time average of |mean over '
                     'runs of the error|.')


def write_report(out: Path, spec, rows: list[dict], total_cells: int) -> Path:
    """summary.md: what ran, how far it got, a table per filter, and the figures."""
    states = state_names(rows)
    status = 'complete' if len(rows) == total_cells else f'INCOMPLETE: {len(rows)} of {total_cells} cells'
    versions = sorted({v for r in rows for v in r['code_version'].split()})
    lines = [
        f'# Campaign {out.name}', '',
        *([spec.description.strip(), ''] if spec.description.strip() else []),
        (f'Scenario {spec.scenario}, {spec.runs} runs per cell, seed {spec.seed}; '
         f'{total_cells // len(spec.filters)} grid points x {len(spec.filters)} filters = '
         f'{total_cells} cells, {status}.'), '',
        _readings_text(spec), '',
        (f'Fixed settings: {spec.settings or "none (scenario defaults)"}. Spec sha256 '
         f'`{spec.digest()[:16]}`; code {", ".join(versions) or "-"}; worker time '
         f'{sum(r["wall_time_s"] for r in rows):.0f} s.'), '',
    ]
    if len(versions) > 1:
        lines += [('**Warning**: the rows were computed by different code versions (a campaign '
                   'resumed across commits).'), '']
    for kind in spec.filters:
        lines += [f'## {label_of(kind)} (`{kind}`)', '', *_filter_table(spec, rows, kind, states), '']
    drawn = figures(out, spec, rows)
    if drawn:
        lines += ['## Figures', '', *(f'![{p.stem}](figures/{p.name})' for p in drawn), '']
    if write_campaign_page(out, spec, rows, total_cells):
        lines += ['Interactive page (heatmaps, filter comparison, table by cell; opens offline): '
                  '[campaign.html](campaign.html)', '']
    path = out / 'summary.md'
    path.write_text('\n'.join(lines))
    return path
