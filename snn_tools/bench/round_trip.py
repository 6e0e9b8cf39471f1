"""The ROS loop's transport floor: one rclpy round trip between two processes, as the pipeline does it.

A ``ping`` process publishes an estimate (nav_msgs/Odometry as CDR bytes, the estimator's
message) and a ``pong`` process decodes it and answers with a control (geometry_msgs/
AccelStamped as CDR bytes, the controller's message): the exchange that paces a lockstep step
(estimate k -> control k -> estimate k+1, docs/performance.md). Both use the pipeline's executor
(:func:`scenario_nodes.runtime.make_executor`), QoS (reliable transient-local publishers,
best-effort subscriptions) and raw CDR, and start with the demo's CPU plan and scheduling for
the loop pair (both on the loop's CPU, SCHED_BATCH). The ping times each round trip on
CLOCK_MONOTONIC (``time.perf_counter_ns``) from just before ``publish`` to the answer's callback,
so the figure includes both processes' callback overhead, as a step does.

``measure_round_trip()`` runs the pair and returns the RTT; ``snn_loop_bench`` divides the
step (dt) by it: ``dt / RTT`` is the real-time factor a lockstep loop of one round trip per step
could reach, and ``fraction_of_floor`` is the demo's factor as a part of it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: Topics of the pair (not the pipeline's: a bench beside a running demo does not disturb it).
PING, PONG = 'rtt_ping', 'rtt_pong'
#: Round trips thrown away at the start (discovery, first-call allocation, caches).
WARM_UP = 200
#: A round trip lost on the best-effort link is restarted after this long (seconds).
RESEND_AFTER = 0.2


def percentiles(samples_us) -> dict:
    """median / p90 / p99 / max of round-trip samples in microseconds."""
    data = np.asarray(samples_us, dtype=float)
    if data.size == 0:
        raise ValueError('no round-trip samples')
    return {'median_us': float(np.median(data)), 'p90_us': float(np.percentile(data, 90)),
            'p99_us': float(np.percentile(data, 99)), 'max_us': float(data.max()),
            'samples': int(data.size)}


def _pair_node(role: str, samples: int, out: Path | None):
    from geometry_msgs.msg import AccelStamped
    from nav_msgs.msg import Odometry
    from rclpy.node import Node

    from scenario_nodes import qos
    from scenario_nodes.codec import decode_accel, decode_odometry, encode_accel, encode_odometry
    from scenario_nodes.runtime import ProcessHooks

    class PairNode(ProcessHooks, Node):
        def __init__(self):
            super().__init__(f'rtt_{role}')
            events = qos.QosEvents(self)
            state, covariance = np.arange(6.0), np.eye(6)
            if role == 'pong':
                self._out = qos.publisher(self, events, AccelStamped, PONG)
                qos.subscription(self, events, Odometry, PING, self._on_ping, qos.INPUT_QOS)
                self._u = np.zeros(3)
                self._decode, self._encode = decode_odometry, encode_accel
            else:
                self._out = qos.publisher(self, events, Odometry, PING)
                qos.subscription(self, events, AccelStamped, PONG, self._on_pong, qos.INPUT_QOS)
                self._message = lambda k: encode_odometry(state, covariance, k, 'lvlh', 'chaser')
                self._decode = decode_accel
                self._rtt_ns: list[int] = []
                self._k = 0
                self._sent_at = 0
                self._timer = self.create_timer(0.02, self._on_timer)

        def _on_ping(self, data: bytes) -> None:
            record = self._decode(data)
            self._out.publish(self._encode(self._u, record.stamp_ns, 'lvlh'))

        def _send(self) -> None:
            self._k += 1
            self._sent_at = time.perf_counter_ns()
            self._out.publish(self._message(self._k))

        def _on_timer(self) -> None:
            # start once the pong is matched both ways; restart a round trip lost on the way
            if self._sent_at == 0:
                if self._out.get_subscription_count() and self.count_publishers(PONG):
                    self._send()
            elif time.perf_counter_ns() - self._sent_at > RESEND_AFTER * 1e9:
                self._send()

        def _on_pong(self, data: bytes) -> None:
            now = time.perf_counter_ns()
            if self._decode(data).stamp_ns != self._k:
                return  # the answer to a round trip already given up
            self._rtt_ns.append(now - self._sent_at)
            if len(self._rtt_ns) >= WARM_UP + samples:
                out.write_text(json.dumps([ns / 1e3 for ns in self._rtt_ns[WARM_UP:]]))
                self.done = True
                return
            self._send()

    return PairNode


def measure_round_trip(samples: int = 2000, domain_id: int | None = None, pin_cpus: bool = True,
                       scheduling: str = 'batch', timeout: float = 120.0) -> dict:
    """Run a ping and a pong process; return :func:`percentiles` of the round trips (us).
    Raises RuntimeError when the pair does not finish within ``timeout`` seconds."""
    from snn_tools.run.demo import LOOP_PAIR, _child_setup, cpu_plan, pipeline_env
    if samples < 1:
        raise ValueError(f'samples must be >= 1 (got {samples})')
    env = pipeline_env(domain_id)
    cpus = cpu_plan().get(LOOP_PAIR[0]) if pin_cpus else None
    with tempfile.TemporaryDirectory(prefix='snn_rtt_') as folder:
        out = Path(folder) / 'rtt.json'
        processes = [subprocess.Popen(
            [sys.executable, '-m', 'snn_tools.bench.round_trip', '--role', role, '--samples', str(samples),
             '--out', str(out)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            preexec_fn=_child_setup(cpus, False, scheduling == 'batch')) for role in ('pong', 'ping')]
        pong, ping = processes
        try:
            ping.wait(timeout)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f'the round-trip pair did not finish within {timeout:.0f} s') from None
        finally:
            for process in processes:
                if process.poll() is None:
                    process.terminate()
                    try:
                        process.wait(5.0)
                    except subprocess.TimeoutExpired:
                        process.kill()
                        process.wait()
        if ping.returncode != 0 or not out.exists():
            raise RuntimeError(f'the ping process failed ({ping.returncode}): '
                               f'{ping.stderr.read().decode()[-1000:]}')
        return percentiles(json.loads(out.read_text()))


def floor_factor(dt: float, rtt_us: float) -> float:
    """The real-time factor of a lockstep loop that costs one round trip per step: dt / RTT."""
    if dt <= 0 or rtt_us <= 0:
        raise ValueError(f'dt and RTT must be positive (dt {dt} s, RTT {rtt_us} us)')
    return dt / (rtt_us * 1e-6)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='snn_tools.bench.round_trip', description=__doc__.split('\n\n')[0])
    parser.add_argument('--role', choices=('ping', 'pong'), help='(internal) run one side of the pair')
    parser.add_argument('--samples', type=int, default=2000, help='round trips timed (default 2000)')
    parser.add_argument('--out', type=Path, help='ping: where to write the samples (us, JSON)')
    parser.add_argument('--domain-id', type=int, help='ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or random)')
    args = parser.parse_args(argv)
    if args.samples < 1:
        parser.error('--samples must be >= 1')
    if args.role:
        from scenario_nodes.runtime import run_node
        if args.role == 'ping' and args.out is None:
            parser.error('--role ping needs --out')
        return run_node(_pair_node(args.role, args.samples, args.out), None, f'rtt_{args.role}')
    figures = measure_round_trip(args.samples, args.domain_id)
    print(f"round trip between two rclpy processes: median {figures['median_us']:.0f} us, "
          f"p90 {figures['p90_us']:.0f}, p99 {figures['p99_us']:.0f}, max {figures['max_us']:.0f} "
          f"over {figures['samples']}")
    print(f'floor for dt = 0.1 s: real-time factor {floor_factor(0.1, figures["median_us"]):.0f} '
          '(one round trip per step)')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
