"""Decode cost per message: the package's codec against rosbags' own CDR deserializer.

``python -m snn_tools.bench.codec [--repeat 20000] [--out results/codec_bench.json]``

The codec (scenario_nodes.codec) decodes the pipeline's standard types from little-endian CDR
by hand and falls back to rosbags for any other representation; this bench is why it keeps
its own path (docs/performance.md, "Codec"). Both sides decode the same bytes into the
numbers the bag tools use (stamp and values), best of five passes.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from rosbags.typesys import Stores, get_typestore

from scenario_nodes import codec


def _samples() -> dict:
    """type name -> (bytes, our decoder, rosbags reader of the same numbers)."""
    x = np.array([70.0, 30.0, -5.0, -1.7, -0.9, 0.25])
    stamp = 12 * codec.NS + 345
    store = get_typestore(Stores.ROS2_JAZZY)

    def general(type_name, read):
        return lambda data: read(store.deserialize_cdr(data, type_name))

    return {
        'nav_msgs/msg/Odometry': (
            codec.encode_odometry(x, np.eye(6) * 1e-2, stamp, 'lvlh', 'chaser'), codec.decode_odometry,
            general('nav_msgs/msg/Odometry', lambda m: (m.header.stamp.sec, m.pose.pose.position.x,
                                                        m.twist.twist.linear.x, m.pose.covariance))),
        'geometry_msgs/msg/PointStamped': (
            codec.encode_point(x[:3], [0, 1, 2], stamp, 'lvlh'), codec.decode_point,
            general('geometry_msgs/msg/PointStamped', lambda m: (m.header.stamp.sec, m.point.x))),
        'geometry_msgs/msg/AccelStamped': (
            codec.encode_accel(x[3:], stamp, 'lvlh'), codec.decode_accel,
            general('geometry_msgs/msg/AccelStamped', lambda m: (m.header.stamp.sec, m.accel.linear.x))),
        'std_msgs/msg/UInt32': (
            codec.encode_uint32(17), codec.decode_uint32,
            general('std_msgs/msg/UInt32', lambda m: m.data)),
        'std_msgs/msg/UInt32MultiArray': (
            codec.encode_spikes(np.arange(200) % 3), codec.decode_spikes,
            general('std_msgs/msg/UInt32MultiArray', lambda m: m.data)),
    }


def _best_us(decode, data: bytes, repeat: int) -> float:
    best = float('inf')
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(repeat):
            decode(data)
        best = min(best, (time.perf_counter() - start) / repeat)
    return best * 1e6


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='codec_bench', description=__doc__.split('\n\n')[0])
    parser.add_argument('--repeat', type=int, default=20000, help='decodes per pass (best of 5 passes)')
    parser.add_argument('--out', type=Path, help='also write the figures as JSON')
    args = parser.parse_args(argv)
    figures = {}
    print(f'{"type":34s} {"ours us":>8s} {"rosbags us":>11s} {"ratio":>6s}')
    for type_name, (data, ours, rosbags) in _samples().items():
        ours(data), rosbags(data)  # warm both (rosbags compiles its deserializer on first use)
        mine, theirs = _best_us(ours, data, args.repeat), _best_us(rosbags, data, args.repeat)
        figures[type_name] = {'ours_us': round(mine, 2), 'rosbags_us': round(theirs, 2),
                              'rosbags_over_ours': round(theirs / mine, 2)}
        print(f'{type_name:34s} {mine:8.2f} {theirs:11.2f} {theirs / mine:6.2f}')
    if args.out:
        args.out.write_text(json.dumps(figures, indent=2) + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
