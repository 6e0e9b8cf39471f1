"""A picture of what a Foxglove client receives from the live view (docs/live_view.png, ``make
docs-screenshots``): a realtime demo runs with the live view while a WebSocket client
(snn_tools.live.client) records everything; the newest SceneUpdate (decoded with the schema
the server advertises), the /plots series and the newest spike raster are drawn with
matplotlib. It is our rendering of the received data, not a screenshot of Foxglove (which
needs its app or app.foxglove.dev).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
from matplotlib.figure import Figure

from snn_tools.live.client import FoxgloveClient, free_port, protobuf_class
from snn_tools.run.demo import run_pipeline


def _rgba(c):
    return (c.r, c.g, c.b, max(c.a, 0.25))


def _rotation(q):
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def draw_scene(ax, entities, zoom_to: str | None = None) -> None:
    """Entities of a foxglove.SceneUpdate on a 3D axes (spheres as wireframes)."""
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 24), np.linspace(0, np.pi, 12))
    unit = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)], axis=-1)
    for entity in entities:
        for s in entity.spheres:
            radii = 0.5 * np.array([s.size.x, s.size.y, s.size.z])
            p = s.pose.position
            points = (unit * radii) @ _rotation(s.pose.orientation).T + [p.x, p.y, p.z]
            ax.plot_wireframe(points[..., 0], points[..., 1], points[..., 2], color=_rgba(s.color), linewidth=0.4)
        for line in entity.lines:
            pts = np.array([[q.x, q.y, q.z] for q in line.points])
            ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], color=_rgba(line.color), linewidth=1.2, label=entity.id)
        for tri in entity.triangles:  # the corridor: its rim and some of its generators
            pts = np.array([[q.x, q.y, q.z] for q in tri.points])
            rim, apex = pts[1::6], pts[0]
            ax.plot(rim[:, 0], rim[:, 1], rim[:, 2], color=_rgba(tri.color), linewidth=0.6)
            for r in rim[::4]:
                ax.plot(*np.stack([apex, r]).T, color=_rgba(tri.color), linewidth=0.5)
        for arrow in entity.arrows:
            p = arrow.pose.position
            d = _rotation(arrow.pose.orientation) @ [arrow.shaft_length + arrow.head_length, 0, 0]
            ax.quiver(p.x, p.y, p.z, *d, color=_rgba(arrow.color), linewidth=1.5)
    ax.set_xlabel('x (V-bar) [m]')
    ax.set_ylabel('y [m]')
    ax.set_zlabel('z (R-bar) [m]')


def render(client: FoxgloveClient, path: Path) -> Path:
    scene_channel, raster_channel = client.topic('/scene'), client.topic('/spike_raster')
    SceneUpdate, RawImage = protobuf_class(scene_channel), protobuf_class(raster_channel)
    plots = [json.loads(payload) for _, payload in client.messages['/plots']]
    newest = SceneUpdate.FromString(client.messages['/scene'][-1][1])
    raster = RawImage.FromString(client.messages['/spike_raster'][-1][1])
    t = np.array([p['time'] for p in plots])
    fig = Figure(figsize=(12, 6.4), layout='constrained')
    grid = fig.add_gridspec(3, 3)
    ax = fig.add_subplot(grid[:2, :2], projection='3d')
    draw_scene(ax, newest.entities)
    ax.set_title(f'/scene (foxglove.SceneUpdate) at t = {t[-1]:.1f} s', fontsize=9)
    ax.view_init(elev=25, azim=-130)
    error = fig.add_subplot(grid[0, 2])
    for state, colour in (('x', 'C0'), ('y', 'C1'), ('z', 'C2')):
        error.plot(t, [p['error'][state] for p in plots], color=colour, linewidth=0.8, label=f'error {state}')
        error.plot(t, [p['three_sigma'][state] for p in plots], color=colour, linewidth=0.6, linestyle='--')
        error.plot(t, [p['minus_three_sigma'][state] for p in plots], color=colour, linewidth=0.6, linestyle='--')
    error.set_title('/plots: position error, +-3 sigma [m]', fontsize=9)
    error.legend(fontsize=7)
    ranges = fig.add_subplot(grid[1, 2])
    ranges.plot(t, [p['range_true'] for p in plots], label='range true')
    ranges.plot(t, [p['range_estimated'] for p in plots], linestyle='--', label='estimated')
    ranges.set_title('/plots: range [m]', fontsize=9)
    ranges.legend(fontsize=7)
    spikes = fig.add_subplot(grid[2, 2])
    spikes.plot(t, [p.get('spikes', np.nan) for p in plots], color='C3', linewidth=0.8, label='spikes per step')
    nees = spikes.twinx()
    nees.semilogy(t, [p.get('nees', np.nan) for p in plots], color='C4', linewidth=0.8, label='NEES')
    spikes.set_title('/plots: spikes per step (red), NEES (purple, log)', fontsize=9)
    spikes.set_xlabel('simulated time [s]')
    image = np.frombuffer(raster.data, np.uint8).reshape(raster.height, raster.width)
    raster_ax = fig.add_subplot(grid[2, :2])
    raster_ax.imshow(image, aspect='auto', cmap='gray_r', interpolation='nearest')
    raster_ax.set_title('/spike_raster (foxglove.RawImage, mono8): neurons x last steps', fontsize=9)
    raster_ax.set_ylabel('neuron')
    fig.suptitle(f'What a Foxglove client receives from live_view (ws://localhost:8765): {len(plots)} plot '
                 f'messages, {len(client.messages["/scene"])} scenes', fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_live_snapshot', description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', type=Path, default=Path('docs/live_view.png'))
    parser.add_argument('--duration', type=float, default=120.0, help='simulated s (realtime, 10x)')
    parser.add_argument('--domain-id', type=int)
    args = parser.parse_args(argv)
    port = free_port()
    client = FoxgloveClient(port)
    client.start()
    with TemporaryDirectory(prefix='snn_live_snapshot_') as folder:
        run_pipeline(Path(folder) / 'run', mode='realtime', real_time_factor=10.0, duration=args.duration,
                     domain_id=args.domain_id, live_view=True, extra={'live_view': {'port': port}})
    client.stop()
    if client.error or not client.messages.get('/plots'):
        print(f'snn_live_snapshot: the client received nothing ({client.error})')
        return 1
    print(f'wrote {render(client, args.out)}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
