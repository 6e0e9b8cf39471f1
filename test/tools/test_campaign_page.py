"""The interactive campaign page, rendered in headless Chromium (Debian's chromium, installed by
.ci/run): the plots drew (coloured pixels in a screenshot, plotly's SVG in the DOM), the title
is there, the table holds the rows' numbers and filters to the cell named in the URL."""

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('plotly')

from snn_tools.campaign.page import TITLE, cell_key, write_page  # noqa: E402
from snn_tools.campaign.report import write_report  # noqa: E402
from snn_tools.campaign.spec import parse_spec  # noqa: E402

SPEC = {'scenario': 'rendezvous', 'runs': 3, 'filters': ['snn_ekf', 'ekf'],
        'grid': {'leak_rate': [0.001, 0.01], 'neuron_count': [50, 100, 200]},
        'description': 'A page test: made-up numbers.'}
STATES = ('x', 'y', 'z', 'vx', 'vy', 'vz')


def rows_of(spec) -> list[dict]:
    """Rows as campaign_cells.cell_row gives them, with made-up, distinct numbers."""
    rows = []
    for index, cell in enumerate(spec.cells()):
        row = {'filter': cell.filter, **cell.settings, 'runs': spec.runs, 'seed': 0}
        row.update({f'rmse_{s}': (1 + index) * 10.0 ** (-3 - k) for k, s in enumerate(STATES)})
        row.update({f'mean_error_{s}': 1e-4 for s in STATES})
        row.update(spike_fraction=0.05 + 0.01 * index if cell.filter == 'snn_ekf' else None,
                   final_range_median=0.01 * (index + 1), wall_time_s=1.0, code_version='test')
        rows.append(row)
    return rows


def chromium() -> str:
    path = shutil.which('chromium') or shutil.which('chromium-browser')
    if path is None:
        if os.environ.get('CI'):
            pytest.fail('chromium is missing: .ci/run installs it (apt-get install chromium)')
        pytest.skip('chromium is not installed (apt-get install chromium)')
    return path


def run_chromium(tmp_path: Path, *arguments) -> subprocess.CompletedProcess:
    command = [chromium(), '--headless', '--no-sandbox', '--disable-gpu', '--hide-scrollbars',
               f'--user-data-dir={tmp_path / "profile"}', '--virtual-time-budget=10000', *arguments]
    return subprocess.run(command, capture_output=True, text=True, timeout=180)


@pytest.fixture(scope='module')
def page(tmp_path_factory):
    spec = parse_spec(SPEC)
    rows = rows_of(spec)
    path = write_page(tmp_path_factory.mktemp('page') / 'page.html', [('tiny campaign', spec, rows, len(rows))])
    return spec, rows, path


def test_the_page_needs_nothing_from_the_network(page):
    text = page[2].read_text()
    assert not re.search(r'<script[^>]+src=|<link[^>]+href=\"?http', text)  # plotly.js is inlined
    assert 'Plotly.newPlot' in text or 'newPlot' in text


def test_chromium_renders_the_plots_and_the_table_filters_to_the_cell_in_the_url(page, tmp_path):
    spec, rows, path = page
    chosen = rows[4]
    key = cell_key(chosen, spec.grid)
    result = run_chromium(tmp_path, '--dump-dom', f'{path.as_uri()}#tiny-campaign:{key}')
    dom = result.stdout
    assert result.returncode == 0, result.stderr[-2000:]
    assert f'<title>{TITLE}</title>' in dom and f'>{TITLE}</h1>' in dom
    assert dom.count('class="main-svg"') >= 6  # plotly drew 3 figures (two SVG layers each)
    assert 'RMSE of x [m]' in dom and 'RMSE of vx [m/s]' in dom  # the figures' titles, drawn as SVG text
    table = dom[dom.index('id="table-tiny-campaign"'):]
    visible = re.findall(r'<tr data-cell="([^"]+)"(?![^>]*display: none)[^>]*>(.*?)</tr>', table)
    assert [cell for cell, _ in visible] == [key]
    assert f'<td>{chosen["rmse_x"]:.4g}</td>' in visible[0][1]
    assert '1 of 12 cells shown' in dom


def test_chromium_screenshot_shows_coloured_plots(page, tmp_path):
    from matplotlib.image import imread
    shot = tmp_path / 'shot.png'
    result = run_chromium(tmp_path, '--window-size=1300,1600', f'--screenshot={shot}', page[2].as_uri())
    assert result.returncode == 0 and shot.exists(), result.stderr[-2000:]
    pixels = imread(shot)[..., :3]
    saturation = pixels.max(axis=2) - pixels.min(axis=2)
    # heatmaps and bars: strongly coloured; text, tables and axes: grey (saturation ~0)
    assert (saturation > 0.3).mean() > 0.05
    assert len(np.unique((pixels[saturation > 0.3] * 255).astype(int), axis=0)) > 20  # a colour scale, not one fill


def test_a_campaign_summary_comes_with_its_page(tmp_path):
    spec = parse_spec(SPEC)
    rows = rows_of(spec)
    summary = write_report(tmp_path, spec, rows[:7], total_cells=len(rows)).read_text()
    assert '(campaign.html)' in summary
    text = (tmp_path / 'campaign.html').read_text()
    assert 'incomplete: 7 of 12 cells' in text
    assert text.count('<tr data-cell=') == 7
