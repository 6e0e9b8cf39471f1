"""Figures in the style of the paper (Fig. 2-7, 9-11), drawn from plain arrays.

Used by the offline experiments and by the ``report`` tool that reads recorded bags, so both
draw the same plots. Matplotlib runs headless (Agg).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from snn_estimator.filters.estimators import FILTER_KINDS  # noqa: E402

UNITS = {'x': 'm', 'y': 'm', 'z': 'm', 'vx': 'm/s', 'vy': 'm/s', 'vz': 'm/s', 'x1': '-', 'x2': '-'}
COLOURS = {'ekf': 'tab:blue', 'emsif': 'tab:green', 'esif': 'tab:olive', 'snn_ekf': 'tab:orange',
           'snn_emsif': 'tab:red', 'snn_emsif_star': 'tab:purple', 'emsif_weighted': 'tab:brown',
           'snn_emsif_weighted': 'tab:gray'}


@dataclass
class Track:
    """One estimator's trajectory for the tracking plots."""

    label: str
    time: np.ndarray         # (T,) s
    truth: np.ndarray        # (T, n)
    estimate: np.ndarray     # (T, n)
    sigma: np.ndarray | None = None  # (T, n) standard deviations, or None
    colour: str | None = None


def label_of(kind: str) -> str:
    """The filter's name in tables and figures (e.g. SNN-EMSIF*); anything else unchanged."""
    spec = FILTER_KINDS.get(kind)
    return spec.label if spec else kind


def colour_of(kind: str) -> str | None:
    return COLOURS.get(kind)


def _axis_label(state: str) -> str:
    unit = UNITS.get(state, '')
    return f'{state} [{unit}]' if unit and unit != '-' else state


#: Resolution of saved figures (make experiments lowers it for the committed report figures).
DPI = 110


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def tracking_figure(tracks: Sequence[Track], states: Sequence[str], path: Path, title: str) -> Path:
    """Left: true and estimated state (Fig. 2a-b, 9). Right: error with +-3 sigma (Fig. 2c-d, 10)."""
    rows = len(states)
    fig, axes = plt.subplots(rows, 2, figsize=(12, 2.1 * rows + 0.8), sharex=True, squeeze=False)
    for row, state in enumerate(states):
        left, right = axes[row]
        first = tracks[0]
        left.plot(first.time, first.truth[:, row], color='black', linewidth=1.6, label='truth')
        for track in tracks:
            left.plot(track.time, track.estimate[:, row], color=track.colour, linewidth=1.0,
                      linestyle='--', label=track.label)
            error = track.truth[:, row] - track.estimate[:, row]
            line, = right.plot(track.time, error, color=track.colour, linewidth=0.9, label=track.label)
            if track.sigma is not None:
                bound = 3.0 * track.sigma[:, row]
                right.plot(track.time, bound, color=line.get_color(), linewidth=0.7, linestyle=':')
                right.plot(track.time, -bound, color=line.get_color(), linewidth=0.7, linestyle=':')
        left.set_ylabel(_axis_label(state))
        right.set_ylabel(f'error {_axis_label(state)}')
        right.axhline(0.0, color='grey', linewidth=0.5)
        _zoom_error_axis(right, tracks, row)
        left.grid(alpha=0.3)
        right.grid(alpha=0.3)
    axes[0, 0].legend(loc='upper right', fontsize=8)
    axes[0, 1].legend(loc='upper right', fontsize=8, title='dotted: +-3 sigma', title_fontsize=7)
    axes[0, 0].set_title('true and estimated state')
    axes[0, 1].set_title('estimation error')
    for ax in axes[-1]:
        ax.set_xlabel('time [s]')
    fig.suptitle(title)
    return _save(fig, path)


def _zoom_error_axis(ax, tracks, row):
    """Limit the error axis to the settled part so the steady-state error stays readable. The
    settled +-3 sigma bound is kept in view when it is within a few times the error; a larger
    one is written on the panel instead of being cut off silently."""
    errors = np.concatenate([np.abs(t.truth[:, row] - t.estimate[:, row])[len(t.time) // 10:]
                             for t in tracks])
    if not (errors.size and np.all(np.isfinite(errors))):
        return
    top = np.percentile(errors, 99.5) * 1.8
    if top <= 0:
        return
    bounds = [3.0 * np.median(t.sigma[len(t.time) // 2:, row]) for t in tracks if t.sigma is not None]
    bounds = [b for b in bounds if np.isfinite(b) and b > 0]
    if bounds:
        widest = max(bounds)
        if widest <= 4.0 * top:
            top = max(top, 1.15 * widest)
        else:
            ax.text(0.99, 0.04, f'settled +-3 sigma = +-{widest:.2g} (off scale)', transform=ax.transAxes,
                    ha='right', va='bottom', fontsize=7, color='dimgrey')
    ax.set_ylim(-top, top)


def rmse_figure(series: dict, time: np.ndarray, states: Sequence[str], path: Path, title: str,
                colours: dict | None = None) -> Path:
    """RMSE over runs against time for each state (Fig. 3-5, 11). ``series``: label -> (T, n)."""
    rows = len(states)
    fig, axes = plt.subplots(rows, 1, figsize=(10, 1.9 * rows + 0.8), sharex=True, squeeze=False)
    for row, state in enumerate(states):
        ax = axes[row, 0]
        for label, history in series.items():
            ax.semilogy(time, history[:, row], linewidth=1.0, label=label,
                        color=(colours or {}).get(label))
        _zoom_log_axis(ax, [history[:, row] for history in series.values()])
        ax.set_ylabel(f'RMSE {_axis_label(state)}')
        ax.grid(alpha=0.3, which='both')
    axes[0, 0].legend(loc='upper right', fontsize=8, ncol=3)
    axes[-1, 0].set_xlabel('time [s]')
    fig.suptitle(title)
    return _save(fig, path)


def _zoom_log_axis(ax, curves) -> None:
    """Log axis limits from the curves after their first 5% (an exact initial estimate would
    otherwise pull the axis down to 1e-15)."""
    tails = [c[len(c) // 20:] for c in curves if len(c)]
    values = np.concatenate(tails) if tails else np.zeros(0)
    values = values[np.isfinite(values) & (values > 0)]
    if values.size:
        ax.set_ylim(np.percentile(values, 0.5) / 2.0, values.max() * 2.0)


def raster_figure(time: np.ndarray, raster: np.ndarray, path: Path, title: str) -> Path:
    """Spike raster (neurons x time, Fig. 7) above the spikes emitted per step."""
    raster = np.asarray(raster)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(11, 6), sharex=True,
                                      gridspec_kw={'height_ratios': [3, 1]})
    steps, neurons = raster.shape
    step_times = time[:steps]
    top.imshow((raster.T > 0).astype(float), aspect='auto', origin='lower', cmap='viridis',
               interpolation='nearest', extent=(step_times[0], step_times[-1], -0.5, neurons - 0.5))
    top.set_ylabel('neuron')
    per_step = raster.sum(axis=1)
    fraction = per_step.sum() / max(steps * neurons, 1)
    top.set_title(f'{title}\n{int(per_step.sum()):,} spikes = {100 * fraction:.1f}% of '
                  f'{neurons} neurons x {steps} steps (yellow: spike)')
    bottom.plot(step_times, per_step, color='tab:red', linewidth=0.7)
    bottom.set_yscale('symlog', linthresh=10)
    bottom.set_ylabel('spikes / step')
    bottom.set_xlabel('time [s]')
    bottom.grid(alpha=0.3)
    return _save(fig, path)


def control_figure(series: dict, path: Path, title: str) -> Path:
    """Commanded specific force per axis. ``series``: label -> (time (T,), u (T, 3))."""
    names = ('f_x', 'f_y', 'f_z')
    fig, axes = plt.subplots(4, 1, figsize=(10, 8), sharex=True)
    for label, (time, u) in series.items():
        for axis in range(3):
            axes[axis].plot(time, u[:, axis], linewidth=0.9, label=label)
        axes[3].plot(time, np.linalg.norm(u, axis=1), linewidth=0.9, label=label)
    for axis, name in enumerate(names):
        axes[axis].set_ylabel(f'{name} [m/s^2]')
    axes[3].set_ylabel('|u| [m/s^2]')
    axes[3].set_yscale('log')
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel('time [s]')
    fig.suptitle(title)
    return _save(fig, path)


def neuron_sweep_figure(sweep: dict, path: Path, coding: dict | None = None) -> Path:
    """Fig. 6: norm of the per-state RMSE (Eq. 29) over the last 10 s against N, the spike
    fraction, and (``coding``) the RMSE norm of the spiking estimate against its twin's."""
    neurons = sweep['neurons']
    panels = 3 if coding else 2
    fig, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 4.5))
    left, right = axes[0], axes[1]
    styles = {'': '-', 'as_published': ':', 'held_noise': '--', 'as_published,held_noise': '-.'}

    def label_style(key):
        kind, _, labels = key.partition('@')
        return kind, label_of(kind) + (f' @{labels}' if labels else ''), styles.get(labels, '-')

    for key, data in sweep.items():
        if key == 'neurons':
            continue
        kind, label, style = label_style(key)
        left.plot(neurons, data['rmse_norm'], style, marker='o', color=colour_of(kind), label=label)
        left.plot(neurons, data['mean_error_norm'], style, marker='x', color=colour_of(kind), alpha=0.6)
        right.plot(neurons, 100 * np.asarray(data['spike_fraction']), style, marker='o',
                   color=colour_of(kind), label=label)
    left.set_yscale('log')
    left.set_xlabel('neurons N')
    left.set_ylabel('delta_x (Eq. 29)')
    left.set_title('o: ordinary RMSE, x: |mean error| reading')
    right.set_xlabel('neurons N')
    right.set_ylabel('spikes [% of N x steps]')
    right.set_title('spike fraction')
    if coding:
        third = axes[2]
        for key, data in coding.items():
            if key in ('neurons', 'runs'):
                continue
            kind, label, style = label_style(key)
            third.plot(coding['neurons'], data['coding_rmse_norm'], style, marker='o', color=colour_of(kind),
                       label=label)
        third.set_yscale('log')
        third.set_xlabel('neurons N')
        third.set_ylabel('RMSE norm of x_snn - x_twin')
        third.set_title("what the network adds to its twin")
    for ax in axes:
        ax.grid(alpha=0.3, which='both')
        ax.legend(fontsize=7)
    fig.suptitle('Van der Pol: accuracy and activity against network size (Fig. 6)')
    return _save(fig, path)


# ---------------------------------------------------------------- adapters for SimulationResult
def tracking(results: dict, states, path: Path, title: str, run: int = 0) -> Path:
    """Tracking figure for run ``run`` of each spiking filter and its twin."""
    keep = [k for k in ('snn_ekf', 'snn_emsif') if k in results] or list(results)
    tracks = []
    for kind in keep:
        result = results[kind]
        sigma = (np.sqrt(np.clip(result.covariance_diag[run], 0.0, None))
                 if result.covariance_diag is not None else None)
        tracks.append(Track(label_of(kind), result.time, result.truth[run], result.estimate[run],
                            sigma, colour_of(kind)))
    return tracking_figure(tracks, states, path, title)


def rmse_histories(results: dict, states, path: Path, title: str) -> Path:
    any_result = next(iter(results.values()))
    series = {label_of(kind): r.rmse_history() for kind, r in results.items()}
    colours = {label_of(kind): colour_of(kind) for kind in results}
    return rmse_figure(series, any_result.time, states, path, title, colours)


def raster(result, path: Path, title: str) -> Path:
    return raster_figure(result.time, result.raster, path, title)


def neuron_sweep(data: dict, path: Path) -> Path:
    """Fig. 6 from an experiment's JSON (``sweep``, and ``coding_error`` when present)."""
    return neuron_sweep_figure(data['sweep'], path, data.get('coding_error'))


def approach_figure(results: dict, path: Path) -> Path:
    """An approach flown over ROS (snn_tools.experiments.approach.ros_results) in the V-bar/R-bar
    plane: the whole approach with the holds, the approach ellipsoid and the keep-out sphere;
    the last 250 m and the last 20 m with the corridor cone and the estimate's 3-sigma tube
    (R-bar); and the estimation error against its 3-sigma in time, the guidance's events marked."""
    tr = results['trajectory']
    time, truth = np.array(tr['time']), np.array(tr['truth'])
    estimate, sigma = np.array(tr['estimate']), np.array(tr['three_sigma'])
    corridor, keep_out = results['corridor'], results['keep_out_radius']
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    circle = np.linspace(0.0, 2.0 * np.pi, 400)

    def plane(ax, x_low, z_half, tube):
        ax.plot(keep_out * np.cos(circle), keep_out * np.sin(circle), color='tab:red', linewidth=0.9,
                label=f'keep-out sphere ({keep_out:g} m)')
        xs = np.linspace(-corridor['length'], 0.0, 50)
        radius = corridor['apex_radius'] + np.tan(np.radians(corridor['half_angle_deg'])) * -xs
        for sign in (1.0, -1.0):
            ax.plot(xs, sign * radius, color='tab:green', linewidth=0.9,
                    label=f"corridor ({corridor['half_angle_deg']:g} deg)" if sign > 0 else None)
        for i, hold in enumerate(results['holds']):
            if -hold['distance'] >= x_low:
                ax.plot(-hold['distance'], 0.0, marker='v', color='black', markersize=7)
                ax.annotate(hold['name'], (-hold['distance'], 0.0), textcoords='offset points',
                            xytext=(0, 8 if i % 2 == 0 else -16), ha='center', fontsize=8)
        if tube:
            ax.fill_between(estimate[:, 0], estimate[:, 2] - sigma[:, 2], estimate[:, 2] + sigma[:, 2],
                            color='tab:orange', alpha=0.35, linewidth=0, label='estimate +-3 sigma (R-bar)')
            ax.plot(estimate[:, 0], estimate[:, 2], color='tab:orange', linewidth=0.9, linestyle='--',
                    label='estimate')
        ax.plot(truth[:, 0], truth[:, 2], color='black', linewidth=1.1, label='truth')
        ax.plot(0.0, 0.0, marker='o', color='tab:blue', markersize=5, label='docking port')
        ax.set_xlim(x_low, -0.04 * x_low)
        ax.set_ylim(z_half, -z_half)  # R-bar (z, toward Earth) drawn downward
        ax.set_xlabel('x, V-bar [m]')
        ax.set_ylabel('z, R-bar [m]')
        ax.grid(alpha=0.3)

    whole = axes[0, 0]
    a, _, c = results['approach_ellipsoid']
    whole.plot(a * np.cos(circle), c * np.sin(circle), color='tab:purple', linewidth=0.9, linestyle='--',
               label='approach ellipsoid')
    plane(whole, -5400.0, 1200.0, tube=False)
    whole.set_title('5 km to contact: holds, approach ellipsoid, keep-out sphere')
    whole.legend(loc='lower left', fontsize=7)
    plane(axes[0, 1], -270.0, 50.0, tube=True)
    axes[0, 1].set_title('the last 250 m: the corridor inside the keep-out sphere')
    plane(axes[1, 0], -22.0, 0.5, tube=True)
    axes[1, 0].set_title('the last 20 m, R-bar magnified: the 3-sigma tube, the corridor\'s apex')
    axes[1, 0].legend(loc='lower left', fontsize=7)
    errors = axes[1, 1]
    for i, (name, colour) in enumerate(zip(('x', 'y', 'z'), ('tab:blue', 'tab:green', 'tab:orange'))):
        errors.semilogy(time, np.abs(truth[:, i] - estimate[:, i]), color=colour, linewidth=0.8,
                        label=f'|error| {name}')
        errors.semilogy(time, sigma[:, i], color=colour, linewidth=0.8, linestyle=':')
    for event in results['events']:
        errors.axvline(event['time'], color='grey', linewidth=0.5)
        errors.annotate(event['event'], (event['time'], 1.0), rotation=90, fontsize=6, va='top', ha='right',
                        xycoords=('data', 'axes fraction'))
    errors.set_xlabel('time [s]')
    errors.set_ylabel('position error [m]')
    errors.set_title('estimation error (solid) and its 3 sigma (dotted)')
    errors.legend(loc='lower left', fontsize=7)
    errors.grid(alpha=0.3)
    contact = results.get('contact')
    ending = (f"contact at {contact['time']:.0f} s, {contact['closing_speed']:.3f} m/s closing, "
              f"{contact['lateral']:.3f} m lateral" if contact else results['outcome'])
    fig.suptitle(f"Approach over ROS 2, lockstep, {label_of(results.get('estimator', ''))}: {ending}")
    return _save(fig, path)


def approach(results_file: Path, path: Path) -> Path:
    """:func:`approach_figure` from a results file (make approach-figure)."""
    return approach_figure(json.loads(Path(results_file).read_text()), path)


def main(argv=None) -> None:
    """python -m snn_tools.figures --approach results/approach_ros.json --out results/figures/approach_ros.png"""
    parser = argparse.ArgumentParser(description='Draw a figure from a results file.')
    parser.add_argument('--approach', type=Path, required=True, help='an approach results file (snn_demo --results)')
    parser.add_argument('--out', type=Path, required=True)
    args = parser.parse_args(argv)
    print(approach(args.approach, args.out))


if __name__ == '__main__':
    main()
