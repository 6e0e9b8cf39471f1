"""The live view over Foxglove's WebSocket protocol, with the Foxglove SDK (no rclpy here).

:class:`FoxgloveView` starts the SDK's server and, on the public port, the
:class:`~scenario_nodes.foxglove_gateway.SubprotocolGateway` in front of it, so clients of both
subprotocols (``foxglove.sdk.v1``: the Foxglove app, Lichtblick 1.22+; ``foxglove.websocket.v1``:
older Lichtblick and Studio, anything built on ``@foxglove/ws-protocol``) connect to
``ws://localhost:8765``. It logs, per :class:`scenario_nodes.scene.Frame`:

* ``/scene``: foxglove.SceneUpdate (protobuf), one entity per part of the scene;
* ``/plots``: JSON (schema ``snn_rendezvous.LivePlots``), :func:`scene.plot_record`'s values:
  error and +-3 sigma per state, ranges, spikes per step, NEES;
* ``/spike_raster``: foxglove.RawImage (mono8), neurons down, the last steps across.

Time: every message of a frame is logged at the frame's time on the real epoch
(:class:`~scenario_nodes.scene.LogClock`: the run's start plus simulated time), so log times
never go backwards within a channel nor across channels, and the server broadcasts that time
(capability ``time``): a viewer's clock and timeline then run on simulated time. Inside the
messages each part keeps its own stamp on the same epoch. The raster is sent at most
``raster_rate`` times per wall-clock second (it is most of the bytes). The SDK queues at most
``backlog`` messages per client and drops the oldest when a client does not keep up: logging
never blocks.
"""

from __future__ import annotations

import json
import time

import numpy as np

from .foxglove_gateway import SubprotocolGateway
from .scene import STATES, Frame, LogClock, Scene, plot_record, raster_image

SCENE_TOPIC, PLOTS_TOPIC, RASTER_TOPIC = '/scene', '/plots', '/spike_raster'
PLOTS_SCHEMA_NAME = 'snn_rendezvous.LivePlots'


def _per_state(description: str) -> dict:
    return {'type': 'object', 'description': description,
            'properties': {s: {'type': 'number'} for s in STATES}}


#: JSON schema of the /plots channel (what Foxglove's Plot panel offers as paths).
PLOTS_SCHEMA = {
    'type': 'object',
    'properties': {
        'timestamp': {'type': 'object', 'properties': {'sec': {'type': 'integer'}, 'nsec': {'type': 'integer'}}},
        'time': {'type': 'number', 'description': 'simulated time of the estimate, s'},
        'estimate': _per_state('x_hat, m and m/s'),
        'error': _per_state('x_hat - x, m and m/s'),
        'three_sigma': _per_state('+covariance_sigma * sqrt(diag P), m and m/s'),
        'minus_three_sigma': _per_state('-covariance_sigma * sqrt(diag P), m and m/s'),
        'range_true': {'type': 'number', 'description': '|r|, m'},
        'range_estimated': {'type': 'number', 'description': '|r_hat|, m'},
        'spikes': {'type': 'integer', 'description': 'spikes in the step'},
        'nees': {'type': 'number', 'description': 'e^T P^-1 e (block-diagonal P; 6 expected)'},
    },
}


def arrow_pose(start, end) -> tuple[tuple, tuple, float]:
    """(position, orientation x y z w, length) of an arrow from ``start`` to ``end``: the rotation
    that takes +x onto the arrow (Foxglove's ArrowPrimitive points along +x)."""
    start, end = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
    d = end - start
    length = float(np.linalg.norm(d))
    if length == 0.0:
        return tuple(start), (0.0, 0.0, 0.0, 1.0), 0.0
    d /= length
    x = np.array([1.0, 0.0, 0.0])
    axis = np.cross(x, d)
    w = 1.0 + float(x @ d)
    if w < 1e-12:  # pointing along -x: half a turn about z
        return tuple(start), (0.0, 0.0, 1.0, 0.0), length
    q = np.array([*axis, w])
    q /= np.linalg.norm(q)
    return tuple(start), tuple(float(v) for v in q), length


#: Static meshes' points, converted once: id of the mesh -> (the mesh, its Point3 list).
_STATIC: dict[int, tuple] = {}


def _timestamp(stamp_ns: int):
    from foxglove.messages import Timestamp
    return Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)


def scene_update(scene: Scene, epoch_ns: int = 0):
    """The foxglove.SceneUpdate of a scene: one entity per primitive, named as in the scene,
    stamped with the scene's time on the epoch ``epoch_ns``."""
    from foxglove.messages import (
        ArrowPrimitive,
        Color,
        LinePrimitive,
        LinePrimitiveLineType,
        Point3,
        Pose,
        Quaternion,
        SceneEntity,
        SceneUpdate,
        SpherePrimitive,
        TriangleListPrimitive,
        Vector3,
    )

    def color(c):
        return Color(r=c[0], g=c[1], b=c[2], a=c[3])

    def pose(position, orientation=(0.0, 0.0, 0.0, 1.0)):
        return Pose(position=Vector3(x=position[0], y=position[1], z=position[2]),
                    orientation=Quaternion(x=orientation[0], y=orientation[1], z=orientation[2], w=orientation[3]))

    def points(array):
        return [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in array]

    def static_points(array):  # the corridor: one mesh, converted once
        key = id(array)
        if key not in _STATIC or _STATIC[key][0] is not array:
            _STATIC[key] = (array, points(array))
        return _STATIC[key][1]

    stamp = _timestamp(epoch_ns + scene.stamp_ns)

    def entity(name, **primitives):
        return SceneEntity(timestamp=stamp, frame_id=scene.frame_id, id=name, **primitives)

    entities = []
    for s in scene.spheres:
        size = Vector3(x=2 * s.radii[0], y=2 * s.radii[1], z=2 * s.radii[2])
        entities.append(entity(s.name, spheres=[SpherePrimitive(pose=pose(s.center, s.orientation), size=size,
                                                                color=color(s.color))]))
    for a in scene.arrows:
        position, orientation, length = arrow_pose(a.start, a.end)
        head = min(0.25 * length, 2.0)
        entities.append(entity(a.name, arrows=[ArrowPrimitive(
            pose=pose(position, orientation), shaft_length=length - head, shaft_diameter=0.3,
            head_length=head, head_diameter=0.8, color=color(a.color))]))
    for line in scene.lines:
        entities.append(entity(line.name, lines=[LinePrimitive(
            type=LinePrimitiveLineType.LineStrip, pose=pose((0.0, 0.0, 0.0)), thickness=line.width,
            scale_invariant=False, points=points(line.points), color=color(line.color))]))
    for t in scene.triangles:
        entities.append(entity(t.name, triangles=[TriangleListPrimitive(
            pose=pose((0.0, 0.0, 0.0)), points=static_points(t.points), color=color(t.color))]))
    return SceneUpdate(entities=entities)


def raster_message(raster: np.ndarray, stamp_ns: int, frame_id: str):
    """foxglove.RawImage (mono8) of a (neurons, steps) raster, stamped ``stamp_ns`` (ns since the
    Unix epoch)."""
    from foxglove.messages import RawImage
    image = raster_image(raster)
    return RawImage(timestamp=_timestamp(stamp_ns), frame_id=frame_id,
                    width=image.shape[1], height=image.shape[0], encoding='mono8', step=image.shape[1],
                    data=image.tobytes())


class Throttle:
    """At most ``rate`` yeses per second of ``clock`` (0: never); calls that come at a higher
    rate keep it on average (the next slot follows the last one's due time, not its call)."""

    def __init__(self, rate: float, clock=time.monotonic):
        if rate < 0:
            raise ValueError(f'raster_rate = {rate!r}: must be >= 0 (per wall-clock s; 0: no raster)')
        self._period = 1.0 / rate if rate > 0 else None
        self._clock = clock
        self._due = None

    def __call__(self) -> bool:
        if self._period is None:
            return False
        now = self._clock()
        if self._due is not None and now < self._due:
            return False
        late = self._due is None or now - self._due > self._period
        self._due = (now if late else self._due) + self._period
        return True


class FoxgloveView:
    """The SDK's WebSocket server, the gateway for ``foxglove.websocket.v1`` clients in front of
    it (``legacy``; False: the SDK serves ``port`` itself, ``foxglove.sdk.v1`` only) and the three
    channels (its own foxglove.Context, so several views, e.g. in tests, never share channels).
    ``epoch_ns``: the log times' epoch (None: the run's start, see LogClock)."""

    def __init__(self, host: str = '127.0.0.1', port: int = 8765, backlog: int = 64,
                 name: str = 'snn_rendezvous live view', legacy: bool = True, epoch_ns: int | None = None,
                 raster_rate: float = 5.0):
        try:
            import foxglove
            from foxglove.channels import RawImageChannel, SceneUpdateChannel
            from foxglove.websocket import Capability
        except ImportError as error:
            raise ValueError(f'the live view needs foxglove-sdk ({error}): pip install '
                             "'snn_rendezvous[live]', or set foxglove:=false (markers only)") from None
        self._clock = LogClock(epoch_ns)
        self._raster_due = Throttle(raster_rate)
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(
                name=name, host='127.0.0.1' if legacy else host, port=0 if legacy else port,
                context=self._context, message_backlog_size=backlog, capabilities=[Capability.Time])
        except RuntimeError as error:  # the port is taken, or the host is not an address of this machine
            raise ValueError(f'cannot serve the live view on {host}:{port} ({error}): choose another '
                             "'port' (0: any free port) or 'host'") from None
        self._gateway = None
        if legacy:
            try:
                self._gateway = SubprotocolGateway(host, port, self._server.port)
            except OSError as error:
                self._server.stop()
                raise ValueError(f'cannot serve the live view on {host}:{port} ({error}): choose another '
                                 "'port' (0: any free port) or 'host'") from None
        self._scene = SceneUpdateChannel(SCENE_TOPIC, context=self._context)
        schema = foxglove.Schema(name=PLOTS_SCHEMA_NAME, encoding='jsonschema',
                                 data=json.dumps(PLOTS_SCHEMA).encode())
        self._plots = foxglove.Channel(PLOTS_TOPIC, schema=schema, message_encoding='json', context=self._context)
        self._raster = RawImageChannel(RASTER_TOPIC, context=self._context)
        self.host = host
        self.sent = 0

    @property
    def port(self) -> int:
        return self._gateway.port if self._gateway is not None else self._server.port

    @property
    def url(self) -> str:
        return f'ws://{"localhost" if self.host in ("127.0.0.1", "::1") else self.host}:{self.port}'

    @property
    def epoch_ns(self) -> int | None:
        """The log times' epoch, ns since the Unix epoch (None until the first frame anchors it)."""
        return self._clock.epoch_ns

    @property
    def watched(self) -> bool:
        """Whether a client subscribes to any channel (nothing is built for nobody)."""
        return self._scene.has_sinks() or self._plots.has_sinks() or self._raster.has_sinks()

    def publish(self, frame: Frame) -> None:
        """Log one frame at its time (any part may be None: not available yet), each channel
        only while a client subscribes to it, the raster at most ``raster_rate`` times a second."""
        log_time = self._clock(frame.stamp_ns)
        epoch = self._clock.epoch_ns
        self._server.broadcast_time(log_time)
        scene, sample, raster = frame.scene, frame.sample, frame.raster
        if scene is not None and self._scene.has_sinks():
            self._scene.log(scene_update(scene, epoch), log_time=log_time)
        if sample is not None and self._plots.has_sinks():
            self._plots.log(json.dumps(plot_record(sample, epoch)).encode(), log_time=log_time)
        if raster is not None and scene is not None and self._raster.has_sinks() and self._raster_due():
            self._raster.log(raster_message(raster, epoch + scene.stamp_ns, scene.frame_id), log_time=log_time)
        self.sent += 1

    def close(self) -> None:
        self._server.stop()  # first: it closes its clients' connections, through the gateway too
        if self._gateway is not None:
            self._gateway.close()
