"""The live view's scene as visualization_msgs/MarkerArray, for RViz (config/rendezvous.rviz) and
Foxglove over a ROS bridge: the same :class:`scenario_nodes.scene.Scene` the Foxglove channels
draw, one marker per part (namespace = the part's name, id 0), in the scene's frame.

SPHERE markers take diameters as ``scale`` and the ellipsoid's orientation as pose; ARROW
markers the tail and the head as two points (scale: shaft diameter, head diameter, head
length); LINE_STRIP the trail (scale.x: width); TRIANGLE_LIST the corridor.
"""

from __future__ import annotations

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from .scene import Scene


def _color(c) -> ColorRGBA:
    return ColorRGBA(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=float(c[3]))


def _points(array) -> list:
    return [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in array]


#: The corridor's points, built once per mesh (rclpy builds a Point in ~20 us; the mesh does not
#: change): id of the mesh -> (the mesh, kept so the id stays its own, its points).
_STATIC: dict[int, tuple] = {}


def _static_points(array) -> list:
    key = id(array)
    if key not in _STATIC or _STATIC[key][0] is not array:
        _STATIC[key] = (array, _points(array))
    return _STATIC[key][1]


def marker_array(scene: Scene) -> MarkerArray:
    """One ADD marker per part of ``scene``, stamped with its simulated time."""
    stamp = Time(sec=scene.stamp_ns // 1_000_000_000, nanosec=scene.stamp_ns % 1_000_000_000)
    markers = []

    def marker(name: str, kind: int, color) -> Marker:
        m = Marker(ns=name, id=0, type=kind, action=Marker.ADD, color=_color(color), frame_locked=False)
        m.header.stamp = stamp
        m.header.frame_id = scene.frame_id
        m.pose.orientation.w = 1.0
        markers.append(m)
        return m

    for s in scene.spheres:
        m = marker(s.name, Marker.SPHERE, s.color)
        m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(c) for c in s.center)
        o = m.pose.orientation
        o.x, o.y, o.z, o.w = (float(q) for q in s.orientation)
        m.scale.x, m.scale.y, m.scale.z = (2.0 * float(r) for r in s.radii)
    for a in scene.arrows:
        m = marker(a.name, Marker.ARROW, a.color)
        m.points = _points((a.start, a.end))
        m.scale.x, m.scale.y, m.scale.z = 0.3, 0.8, 2.0
    for line in scene.lines:
        m = marker(line.name, Marker.LINE_STRIP, line.color)
        m.points = _points(line.points)
        m.scale.x = float(line.width)
    for t in scene.triangles:
        m = marker(t.name, Marker.TRIANGLE_LIST, t.color)
        m.points = _static_points(t.points)
        m.scale.x = m.scale.y = m.scale.z = 1.0
    return MarkerArray(markers=markers)
