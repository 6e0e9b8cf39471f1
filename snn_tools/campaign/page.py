"""One self-contained, interactive HTML page of one or more campaigns (plotly, its JavaScript
inlined: no server, no internet at view time).

Per campaign: heatmaps of the RMSE (first position and first velocity state) over the first
two swept settings, a panel per filter (other swept settings held at their first value);
RMSE against the setting when one is swept; a filter comparison (grouped bars: RMSE of a
state per grid point and filter, the state chosen from a menu); and the table of every cell,
filtered by filter and by each grid setting. Every point shows its values on hover; a click
on a heatmap cell or a bar filters the table to that cell. ``page.html#<campaign>:<cell>``
opens with that filter applied (what the browser test uses).

``snn_campaign`` writes ``<out>/campaign.html``; ``snn_experiments`` one page of all its
tables, ``<out>/campaigns/index.html``.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

from snn_tools.campaign.approach_cells import TABLE_COLUMNS as APPROACH_COLUMNS
from snn_tools.campaign.cells import APPROACH
from snn_tools.campaign.spec import identity_columns, load_spec, read_rows, reading_columns, state_names, swept
from snn_tools.figures import UNITS, label_of

#: The page's <title> and heading start with this (the browser test looks for it).
TITLE = 'snn_rendezvous campaigns'


def _text(value) -> str:
    return json.dumps(value, sort_keys=True) if isinstance(value, (list, dict)) else str(value)


#: The optional readings the page's table shows where a row has them (the summary adds no NEES).
NUMBERS_SHOWN = ('spike_fraction', 'final_range_median', 'nees_average')


def _finite(value):
    return value if isinstance(value, (int, float)) and math.isfinite(value) else None


def cell_key(row: dict, grid) -> str:
    """The id of a row's cell: filter and grid values, e.g. ``ekf|leak_rate=0.01|neuron_count=50``."""
    return '|'.join([row['filter'], *(f'{name}={_text(row[name])}' for name in grid)])


def _point_label(row: dict, grid) -> str:
    return ', '.join(f'{name}={_text(row[name])}' for name in grid) or 'all'


def _heatmaps(spec, rows, state: str, key: str):
    """Heatmap figure of ``state`` over the first two swept settings, one panel per filter."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots
    names = swept(spec)
    y_name, x_name = names[:2]
    held = {n: spec.grid[n][0] for n in names[2:]}
    xs, ys = [_text(v) for v in spec.grid[x_name]], [_text(v) for v in spec.grid[y_name]]
    fig = make_subplots(rows=1, cols=len(spec.filters), subplot_titles=[label_of(k) for k in spec.filters],
                        shared_yaxes=True, horizontal_spacing=0.04)
    values = [row[f'rmse_{state}'] for row in rows if _finite(row.get(f'rmse_{state}'))]
    low, high = (math.log10(min(values)), math.log10(max(values))) if values and min(values) > 0 else (0, 1)
    for column, kind in enumerate(spec.filters, start=1):
        z = [[None] * len(xs) for _ in ys]
        custom = [[None] * len(xs) for _ in ys]
        for row in rows:
            if row['filter'] != kind or any(_text(row[n]) != _text(v) for n, v in held.items()):
                continue
            i, j = ys.index(_text(row[y_name])), xs.index(_text(row[x_name]))
            value = _finite(row.get(f'rmse_{state}'))
            z[i][j] = math.log10(value) if value and value > 0 else None
            custom[i][j] = [f'{value:.4g}' if value is not None else '-', _spikes(row), cell_key(row, spec.grid), key]
        fig.add_trace(go.Heatmap(
            z=z, x=xs, y=ys, customdata=custom, zmin=low, zmax=high, coloraxis='coloraxis',
            text=[[c[0] if c else '' for c in line] for line in custom], texttemplate='%{text}',
            textfont={'size': 10},
            hovertemplate=(f'{label_of(kind)}<br>{x_name}=%{{x}}<br>{y_name}=%{{y}}<br>RMSE {state} = '
                           '%{customdata[0]}<br>spikes %{customdata[1]}<extra></extra>')), row=1, col=column)
        fig.update_xaxes(title_text=x_name, type='category', row=1, col=column)
    fig.update_yaxes(title_text=y_name, type='category', row=1, col=1)
    held_text = ('; held at ' + ', '.join(f'{k} = {_text(v)}' for k, v in held.items())) if held else ''
    fig.update_layout(title=f'RMSE of {state} [{UNITS.get(state, "")}], {spec.runs} runs per cell{held_text}',
                      coloraxis={'colorscale': 'Viridis', 'reversescale': True,
                                 'colorbar': {'title': f'log10 RMSE {state}'}},
                      height=380, margin={'t': 80})
    return fig


def _spikes(row) -> str:
    value = _finite(row.get('spike_fraction'))
    return f'{100 * value:.2f} % of N x steps' if value is not None else '-'


def _line(spec, rows, state: str, key: str):
    """RMSE of ``state`` against the only swept setting, a line per filter."""
    import plotly.graph_objects as go
    name = swept(spec)[0]
    fig = go.Figure()
    for kind in spec.filters:
        mine = [r for r in rows if r['filter'] == kind]
        fig.add_trace(go.Scatter(
            x=[_text(r[name]) for r in mine], y=[_finite(r.get(f'rmse_{state}')) for r in mine],
            mode='lines+markers', name=label_of(kind),
            customdata=[[_spikes(r), cell_key(r, spec.grid), key] for r in mine],
            hovertemplate=f'{label_of(kind)}<br>{name}=%{{x}}<br>RMSE {state} = %{{y:.4g}}<br>spikes '
                          '%{customdata[0]}<extra></extra>'))
    fig.update_layout(title=f'RMSE of {state} against {name}', yaxis={'type': 'log', 'title': f'RMSE {state}'},
                      xaxis={'type': 'category', 'title': name}, height=380)
    return fig


def _comparison(spec, rows, states, key: str):
    """Grouped bars: RMSE per grid point (x) and filter (colour); a menu picks the state."""
    import plotly.graph_objects as go
    fig = go.Figure()
    for kind in spec.filters:
        mine = [r for r in rows if r['filter'] == kind]
        fig.add_trace(go.Bar(
            x=[_point_label(r, spec.grid) for r in mine], y=[_finite(r.get(f'rmse_{states[0]}')) for r in mine],
            name=label_of(kind), customdata=[[_spikes(r), cell_key(r, spec.grid), key] for r in mine],
            hovertemplate=f'{label_of(kind)}<br>%{{x}}<br>RMSE = %{{y:.4g}}<br>spikes %{{customdata[0]}}'
                          '<extra></extra>'))
    def log_range(state):  # plotly's log autorange of bars starts at the smallest top: set it
        values = [v for r in rows if (v := _finite(r.get(f'rmse_{state}'))) and v > 0]
        return [math.log10(min(values)) - 0.5, math.log10(max(values)) + 0.1] if values else None

    buttons = [{'label': state, 'method': 'update',
                'args': [{'y': [[_finite(r.get(f'rmse_{state}')) for r in rows if r['filter'] == kind]
                                for kind in spec.filters]},
                         {'yaxis.title.text': f'RMSE {state} [{UNITS.get(state, "")}]',
                          'yaxis.range': log_range(state)}]} for state in states]
    fig.update_layout(barmode='group', title='filters compared: RMSE per grid point (menu: state)',
                      yaxis={'type': 'log', 'title': f'RMSE {states[0]} [{UNITS.get(states[0], "")}]',
                             'range': log_range(states[0])},
                      updatemenus=[{'buttons': buttons, 'x': 1.0, 'y': 1.18, 'xanchor': 'right'}], height=420)
    return fig


def _approach_bars(spec, rows, key: str):
    """Grouped bars of the approach: one safety figure per grid point (x) and filter (colour);
    a menu picks the figure (approach_cells.TABLE_COLUMNS)."""
    import plotly.graph_objects as go
    fig = go.Figure()
    for kind in spec.filters:
        mine = [r for r in rows if r['filter'] == kind]
        fig.add_trace(go.Bar(
            x=[_point_label(r, spec.grid) for r in mine], y=[_finite(r.get(APPROACH_COLUMNS[0])) for r in mine],
            name=label_of(kind), customdata=[[cell_key(r, spec.grid), key] for r in mine],
            hovertemplate=f'{label_of(kind)}<br>%{{x}}<br>%{{y:.4g}}<extra></extra>'))
    buttons = [{'label': column, 'method': 'update',
                'args': [{'y': [[_finite(r.get(column)) for r in rows if r['filter'] == kind]
                                for kind in spec.filters]},
                         {'yaxis.title.text': column}]} for column in APPROACH_COLUMNS]
    fig.update_layout(barmode='group', title='filters compared: safety figures per grid point (menu: figure)',
                      yaxis={'title': APPROACH_COLUMNS[0]}, height=420,
                      updatemenus=[{'buttons': buttons, 'x': 1.0, 'y': 1.18, 'xanchor': 'right'}])
    return fig


def _table(spec, rows, states, key: str) -> str:
    """The cells as an HTML table with one select per filterable column."""
    names = identity_columns(spec)
    columns = ['filter', *names, *reading_columns(spec, rows, states, NUMBERS_SHOWN)]
    selects = []
    for name in ['filter', *spec.grid]:
        values = sorted({_text(r[name]) for r in rows})
        options = ''.join(f'<option>{html.escape(v)}</option>' for v in values)
        selects.append(f'<label>{html.escape(name)} <select data-column="{html.escape(name)}">'
                       f'<option value="">all</option>{options}</select></label>')
    head = ''.join(f'<th>{html.escape(c)}</th>' for c in columns)
    body = []
    for row in rows:
        cells = []
        for c in columns:
            value = row.get(c)
            cells.append(f'<td>{html.escape(_text(value)) if c in ("filter", *names) else _number(value)}</td>')
        data = ' '.join(f'data-{_attr(n)}="{html.escape(_text(row[n]))}"' for n in ['filter', *spec.grid])
        body.append(f'<tr data-cell="{html.escape(cell_key(row, spec.grid))}" {data}>{"".join(cells)}</tr>')
    return (f'<div class="filters" data-table="{key}">{" ".join(selects)} <button>show all</button>'
            f' <span class="shown"></span></div>'
            f'<table id="table-{key}"><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>')


def _attr(name: str) -> str:
    return ''.join(ch if ch.isalnum() else '-' for ch in name.lower())


def _number(value) -> str:
    value = _finite(value)
    return '-' if value is None else f'{value:.4g}'


def section(name: str, spec, rows: list[dict], total_cells: int) -> str:
    """The HTML of one campaign: heading, figures, table."""
    import plotly.io as pio
    key = _attr(name)
    states = state_names(rows)
    status = 'complete' if len(rows) == total_cells else f'incomplete: {len(rows)} of {total_cells} cells'
    parts = [f'<section id="{key}"><h2>{html.escape(name)}</h2>',
             f'<p>{html.escape(spec.description.strip())}</p>' if spec.description.strip() else '',
             f'<p>Scenario {spec.scenario}, {spec.runs} runs per cell, seed {spec.seed}, {status}. '
             + ('Safety figures of the flown approaches (summarize() of each cell\'s flights). '
                if spec.scenario == APPROACH else
                'RMSE over the final window of each run (ordinary RMSE over runs and time). ')
             + 'Hover for values; click a cell or a bar to filter the table.</p>']
    if not rows:
        return ''.join(parts) + '<p>No finished cells yet.</p></section>'
    figures = [_approach_bars(spec, rows, key)] if spec.scenario == APPROACH else []
    shown = list(dict.fromkeys([states[0], states[len(states) // 2]])) if states else []
    axes = swept(spec)
    for state in shown:
        if len(axes) >= 2:
            figures.append(_heatmaps(spec, rows, state, key))
        elif len(axes) == 1:
            figures.append(_line(spec, rows, state, key))
    if states and (len(spec.filters) > 1 or not figures):
        figures.append(_comparison(spec, rows, states, key))
    for index, fig in enumerate(figures):
        parts.append(pio.to_html(fig, include_plotlyjs=False, full_html=False, div_id=f'{key}-figure-{index}',
                                 post_script='snnLink(document.getElementById("{plot_id}"));',
                                 config={'displaylogo': False}))
    parts.append(_table(spec, rows, states, key))
    parts.append('</section>')
    return ''.join(parts)


SCRIPT = """
function snnApply(box) {
  var table = document.getElementById('table-' + box.dataset.table);
  var wanted = {};
  box.querySelectorAll('select').forEach(function (s) { if (s.value) wanted[s.dataset.column] = s.value; });
  var shown = 0;
  table.querySelectorAll('tbody tr').forEach(function (tr) {
    var ok = true;
    for (var column in wanted) {
      var attr = 'data-' + column.toLowerCase().replace(/[^a-z0-9]/g, '-');
      if (tr.getAttribute(attr) !== wanted[column]) ok = false;
    }
    tr.style.display = ok ? '' : 'none';
    if (ok) shown += 1;
  });
  box.querySelector('.shown').textContent = shown + ' of ' + table.tBodies[0].rows.length + ' cells shown';
}
function snnSelectCell(key, cell) {
  var box = document.querySelector('.filters[data-table="' + key + '"]');
  if (!box) return;
  var parts = cell.split('|');
  var values = {filter: parts[0]};
  parts.slice(1).forEach(function (p) { var i = p.indexOf('='); values[p.slice(0, i)] = p.slice(i + 1); });
  box.querySelectorAll('select').forEach(function (s) { s.value = values[s.dataset.column] || ''; });
  snnApply(box);
}
function snnLink(div) {
  div.on('plotly_click', function (event) {
    var data = event.points[0].customdata;
    if (data) snnSelectCell(data[data.length - 1], data[data.length - 2]);
  });
}
document.addEventListener('DOMContentLoaded', function () {
  document.querySelectorAll('.filters').forEach(function (box) {
    box.querySelectorAll('select').forEach(function (s) {
      s.addEventListener('change', function () { snnApply(box); });
    });
    box.querySelector('button').addEventListener('click', function () {
      box.querySelectorAll('select').forEach(function (s) { s.value = ''; }); snnApply(box); });
    snnApply(box);
  });
  var hash = decodeURIComponent(window.location.hash.slice(1));
  var colon = hash.indexOf(':');
  if (colon > 0) snnSelectCell(hash.slice(0, colon), hash.slice(colon + 1));
});
"""

STYLE = """
body { font-family: sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; font-size: 12px; margin-top: 0.5em; }
th, td { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
th { background: #eee; } td:first-child { text-align: left; }
.filters label { margin-right: 1em; } section { margin-bottom: 3em; }
"""


def write_page(path: Path, campaigns: list, title: str = TITLE) -> Path:
    """Write the page of ``campaigns``, a list of (name, spec, rows, total cells)."""
    from plotly.offline import get_plotlyjs
    sections = ''.join(section(*campaign) for campaign in campaigns)
    contents = ''.join(f'<li><a href="#{_attr(c[0])}">{html.escape(c[0])}</a></li>' for c in campaigns)
    page = (f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            f'<style>{STYLE}</style><script>{get_plotlyjs()}</script><script>{SCRIPT}</script></head>'
            f'<body><h1>{html.escape(title)}</h1><ul>{contents}</ul>{sections}</body></html>')
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f'.{path.name}.tmp')
    temporary.write_text(page, encoding='utf-8')
    temporary.replace(path)
    return path


def write_campaign_page(out: Path, spec, rows: list[dict], total_cells: int) -> Path | None:
    """``<out>/campaign.html`` of one campaign; None (with a note) when plotly is not installed."""
    try:
        import plotly  # noqa: F401
    except ImportError:
        print('campaign.html not written: pip install plotly (the campaign extra)')
        return None
    return write_page(Path(out) / 'campaign.html', [(Path(out).name, spec, rows, total_cells)],
                      title=f'{TITLE}: {Path(out).name}')


def write_experiments_page(out: Path, names) -> Path | None:
    """One page of the experiments' campaigns (``<out>/campaigns/<name>/``, as snn_experiments
    leaves them): ``<out>/campaigns/index.html``."""
    campaigns = []
    for name in names:
        folder = Path(out) / 'campaigns' / name
        if (folder / 'spec.yaml').exists():
            spec = load_spec(str(folder / 'spec.yaml'))
            campaigns.append((name, spec, read_rows(folder, spec.cells(), spec.scenario), len(spec.cells())))
    try:
        import plotly  # noqa: F401
    except ImportError:
        print('campaigns/index.html not written: pip install plotly (the campaign extra)')
        return None
    return write_page(Path(out) / 'campaigns' / 'index.html', campaigns, title=f'{TITLE}: the experiments')
