"""The Foxglove layout of the live view (config/foxglove_layout.json), built with the SDK's
``foxglove.layouts`` from the channel names of :mod:`scenario_nodes.foxglove_view`.

``python -m snn_tools.live.layout --write`` regenerates the file (a test keeps it in step). In
Foxglove: Layouts -> Import from file, then Open connection -> Foxglove WebSocket ->
ws://localhost:8765 (README, "Watch it fly").

Panels: the 3D scene (frame lvlh) beside plots in tabs (position and velocity errors with
their +-3 sigma bounds, range, spikes per step, NEES) and the spike raster image. The plots'
x axis is the messages' own simulated time (``/plots.time``, s), every message kept: the 360 s
of the approach at any real-time factor (a timestamp x axis would show the viewer's receive
time).
"""

from __future__ import annotations

import argparse
import json

from scenario_nodes.foxglove_view import PLOTS_TOPIC, RASTER_TOPIC, SCENE_TOPIC
from snn_tools.paths import SOURCE_ROOT

ROOT = SOURCE_ROOT
LAYOUT_FILE = ROOT / 'config' / 'foxglove_layout.json'
COLORS = {'error': '#4e79a7', 'bound': '#e15759'}
#: The plots' x axis: simulated s of each /plots message.
TIME_PATH = f'{PLOTS_TOPIC}.time'


def _plot_config(fl, paths, unit: str):
    return fl.PlotConfig(paths=paths, show_legend=True, y_axis_label=unit, x_axis_val='custom',
                         x_axis_path=fl.PlotXAxisPath(value=TIME_PATH, enabled=True), time_range='all',
                         x_axis_label='simulated time [s]')


def _error_plot(fl, state: str, unit: str):
    paths = [fl.PlotSeries(value=f'{PLOTS_TOPIC}.error.{state}', label=f'error {state}', color=COLORS['error']),
             fl.PlotSeries(value=f'{PLOTS_TOPIC}.three_sigma.{state}', label='+3 sigma', color=COLORS['bound'],
                           line_style='dashed'),
             fl.PlotSeries(value=f'{PLOTS_TOPIC}.minus_three_sigma.{state}', label='-3 sigma',
                           color=COLORS['bound'], line_style='dashed')]
    return fl.PlotPanel(title=f'estimation error {state} [{unit}]', config=_plot_config(fl, paths, unit))


def _plot(fl, title: str, series: dict, unit: str):
    paths = [fl.PlotSeries(value=f'{PLOTS_TOPIC}.{path}', label=label) for path, label in series.items()]
    return fl.PlotPanel(title=title, config=_plot_config(fl, paths, unit))


def _column(fl, panels):
    return fl.SplitContainer(direction='column', items=[fl.SplitItem(content=p) for p in panels])


def layout():
    """The layout object (foxglove.layouts.Layout)."""
    import foxglove.layouts as fl
    scene = fl.ThreeDeePanel(title='rendezvous scene (lvlh)', config=fl.ThreeDeeConfig(
        follow_tf='lvlh', topics={SCENE_TOPIC: fl.BaseRendererSceneUpdateTopicSettings(visible=True)},
        camera_state=fl.ThreeDeeCameraState(distance=160.0, perspective=True, phi=55.0,
                                            target=(35.0, 15.0, 0.0), theta_offset=200.0)))
    errors = fl.TabContainer(tabs=[
        fl.TabItem(title='position error', content=_column(fl, [_error_plot(fl, s, 'm') for s in ('x', 'y', 'z')])),
        fl.TabItem(title='velocity error', content=_column(fl, [_error_plot(fl, s, 'm/s')
                                                                for s in ('vx', 'vy', 'vz')])),
        fl.TabItem(title='range, spikes, NEES', content=_column(fl, [
            _plot(fl, 'range [m]', {'range_true': 'true', 'range_estimated': 'estimated'}, 'm'),
            _plot(fl, 'spikes per step', {'spikes': 'spikes'}, 'spikes'),
            _plot(fl, 'NEES (6 expected)', {'nees': 'NEES'}, '')])),
    ])
    raster = fl.ImagePanel(title='spike raster (neurons x last steps)',
                           config=fl.ImageConfig(image_mode=fl.ImageModeConfig(image_topic=RASTER_TOPIC)))
    right = fl.SplitContainer(direction='column', items=[fl.SplitItem(proportion=3, content=errors),
                                                         fl.SplitItem(proportion=1, content=raster)])
    return fl.Layout(content=fl.SplitContainer(direction='row', items=[
        fl.SplitItem(proportion=3, content=scene), fl.SplitItem(proportion=2, content=right)]))


def layout_json() -> str:
    """The file's text: the SDK's JSON, indented."""
    return json.dumps(json.loads(layout().to_json()), indent=2) + '\n'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_live_layout', description=__doc__.split('\n\n')[0])
    parser.add_argument('--write', action='store_true', help=f'write {LAYOUT_FILE.relative_to(ROOT)}')
    args = parser.parse_args(argv)
    if args.write:
        LAYOUT_FILE.write_text(layout_json())
        print(f'wrote {LAYOUT_FILE}')
    else:
        print(layout_json(), end='')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
