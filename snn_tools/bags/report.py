"""report: figures and report.md from recorded runs (bags), like the paper's Fig. 7 and 9-11.

``report RUN [RUN ...] [--out DIR]`` where RUN is a demo run folder (with ``bag/``) or a bag
directory. Several runs are overlaid in the same figures (e.g. snn_ekf against snn_emsif).
Everything is read from the bags, nothing from a running pipeline.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from snn_tools.bags.data import STATES, RunData, matched_errors, read_bag, summarize
from snn_tools.figures import Track, colour_of, control_figure, label_of, raster_figure, rmse_figure, tracking_figure

RMS_WINDOW = 10.0  # s, moving window of the RMSE-over-time figure


def bag_directory(run: Path) -> Path:
    run = Path(run)
    if (run / 'metadata.yaml').exists():
        return run
    if (run / 'bag' / 'metadata.yaml').exists():
        return run / 'bag'
    raise FileNotFoundError(f'{run} is neither a bag directory nor a run folder with bag/ '
                            '(a bag needs its metadata.yaml; was the recorder stopped cleanly?)')


def moving_rms(times: np.ndarray, errors: np.ndarray, window: float) -> np.ndarray:
    """RMS of the error over the preceding ``window`` seconds at every sample."""
    squared = np.concatenate([np.zeros((1, errors.shape[1])), np.cumsum(errors ** 2, axis=0)])
    start = np.searchsorted(times, times - window + 1e-9)
    count = np.arange(1, times.size + 1) - start
    return np.sqrt((squared[1:] - squared[start]) / count[:, None])


def _label(run: RunData, summary: dict, used: set) -> str:
    label = label_of(summary['estimator'])
    if label in used:
        label = f'{label} ({run.path.parent.name or run.path.name})'
    used.add(label)
    return label


def write_report(runs, out: Path) -> Path:
    """Figures and report.md for ``runs`` into ``out``; returns the report path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    loaded, used = [], set()
    for run in runs:
        data = read_bag(bag_directory(run))
        summary = summarize(data)
        loaded.append((_label(data, summary, used), data, summary))
    tracks, rms_series, controls, colours = [], {}, {}, {}
    for label, data, summary in loaded:
        colour = colour_of(summary['estimator'])
        times, errors = matched_errors(data)
        index = {round(t, 9): i for i, t in enumerate(data.estimate_t)}
        rows = [index[round(t, 9)] for t in times]
        estimate = data.estimate[rows]
        sigma = np.sqrt(np.clip(data.estimate_variance[rows], 0.0, None))
        covariance_known = bool(np.any(sigma > 0))
        tracks.append(Track(label, times, estimate + errors, estimate,
                            sigma if covariance_known else None, colour))
        rms_series[label] = moving_rms(times, errors, RMS_WINDOW) if times.size else np.zeros((0, 6))
        colours[label] = colour
        controls[label] = (data.control_t, data.control)
    figures = []
    if any(t.time.size for t in tracks):
        figures.append(tracking_figure(tracks, STATES, out / 'states_and_errors.png',
                                       'True and estimated state (left), error with +-3 sigma (right)'))
        times = max((t.time for t in tracks), key=len)
        padded = {k: v if len(v) == len(times) else _pad(v, len(times)) for k, v in rms_series.items()}
        figures.append(rmse_figure(padded, times, STATES, out / 'rmse.png',
                                   f'RMSE over the preceding {RMS_WINDOW:.0f} s (Fig. 11)', colours))
    for label, data, summary in loaded:
        if data.spikes.size and data.estimate_t.size:
            name = f"spikes_{summary['estimator']}.png" if len(loaded) > 1 else 'spikes.png'
            # spike arrays carry no stamp: paired with the estimates in order (with two
            # publishers or a restart there are more arrays than estimate stamps)
            rows = min(len(data.spikes), data.estimate_t.size)
            figures.append(raster_figure(data.estimate_t[:rows], data.spikes[:rows], out / name,
                                         f'{label}: spike raster and spikes per step (Fig. 7)'))
    if any(c[1].size for c in controls.values()):
        figures.append(control_figure(controls, out / 'control.png', 'Commanded specific force (LQR)'))
    report = out / 'report.md'
    report.write_text(_markdown(loaded, figures, out))
    (out / 'report_summary.json').write_text(json.dumps(
        {label: summary for label, _, summary in loaded}, indent=2) + '\n')
    return report


def _pad(values: np.ndarray, length: int) -> np.ndarray:
    padded = np.full((length, values.shape[1]), np.nan)
    padded[:len(values)] = values[:length]
    return padded


def _markdown(loaded, figures, out: Path) -> str:
    lines = ['# Rendezvous run report', '',
             'Computed from the recorded bag(s). RMSE over the last 60 s of simulated time; '
             'spike fraction = spikes / (N x recorded estimator steps).', '',
             '| run | steps | sim time [s] | wall [s] | real-time factor | final range [m] | '
             'RMSE x, y, z [m] | RMSE vx, vy, vz [m/s] | spikes | spike fraction | control timeouts | '
             'measurements rejected |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|']
    for label, _, s in loaded:
        r = s['rmse_last_60s']
        lines.append(
            f"| {label} | {s['steps']} | {s['sim_time_s']:.1f} | {s['wall_time_s']:.2f} | "
            f"{s['real_time_factor']:.0f} | {s['final_range_m']:.4f} | "
            f"{r['x']:.3e}, {r['y']:.3e}, {r['z']:.3e} | {r['vx']:.3e}, {r['vy']:.3e}, {r['vz']:.3e} | "
            f"{s['spikes_total']} | {100 * s['spike_fraction']:.2f}% | {s['control_timeouts']} | "
            f"{s['measurements_rejected']} |")
    lines += ['', '## Contact conditions: where the chaser first comes within 1 m (docs/decisions.md, 49)', '',
              '| run | time [s] | closing speed [m/s] | offset from the docking axis (LVLH x) [m] |',
              '|---|---|---|---|']
    for label, _, s in loaded:
        contact = s.get('contact')
        lines.append(f"| {label} | " + ('never within 1 m | - | - |' if not contact else
                                         f"{contact['t_s']:.1f} | {contact['closing_speed_m_s']:.3f} | "
                                         f"{contact['axis_offset_m']:.3f} |"))
    lines += ['', '## Messages recorded / published', '']
    for label, _, s in loaded:
        counts = ', '.join(f"{k} {v['recorded']}/{v['published']}" for k, v in s['messages'].items())
        lines.append(f'- {label}: {counts}' + ('' if s['recording_complete'] else ' (INCOMPLETE)'))
        notes = [f"{node} restarted {n}x" for node, n in s.get('restarts', {}).items() if n]
        if s.get('duplicate_estimates'):
            notes.append(f"{s['duplicate_estimates']} estimate stamps published twice (two estimators)")
        notes += [f"{name} missing {', '.join(f'{a:.1f}-{b:.1f} s' for a, b in runs[:5])}"
                  + (f' and {len(runs) - 5} more gaps' if len(runs) > 5 else '')
                  for name, runs in s.get('gaps', {}).items() if runs]
        if notes:
            lines.append(f"  - {'; '.join(notes)} (completeness judged per stamp)")
    lines += ['', '## Figures', '']
    for figure in figures:
        lines.append(f'![{figure.stem}]({Path(figure).relative_to(out)})')
    return '\n'.join(lines) + '\n'


def default_output(runs: list[Path]) -> Path:
    """Where the report goes unless --out says: into a run folder (it has bag/), beside a bare
    bag as <bag>_report (never inside the bag, which ros2 bag owns), ./report for several."""
    if len(runs) != 1:
        return Path('report')
    run = runs[0].resolve()
    return run if (run / 'bag').exists() else run.parent / f'{run.name}_report'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='report', description=__doc__.split('\n\n')[0])
    parser.add_argument('runs', nargs='+', type=Path, help='run folders (with bag/) or bag directories')
    parser.add_argument('--out', type=Path, help='output folder (default: a run folder itself, '
                        '<bag>_report beside a bare bag, ./report for several)')
    args = parser.parse_args(argv)
    out = args.out or default_output(args.runs)
    try:
        report = write_report(args.runs, out)
    except FileNotFoundError as error:
        print(f'report: {error}', file=sys.stderr)
        return 2
    print(f'report: {report}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
