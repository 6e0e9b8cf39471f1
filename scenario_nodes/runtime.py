"""Process entry points shared by the nodes: init, spin, clean shutdown, exit codes.

Signals: rclpy's own SIGTERM handling ends ``spin`` in several ways, so the nodes install
their own SIGINT/SIGTERM handlers that ask the spin loop to stop; the node then finishes its
work (a recorder closes its bag) while the context is still valid, and the process exits 0.
A configuration error exits with code 2 and a message that says what to fix.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from typing import Callable

import rclpy
from rclpy.clock import JumpThreshold
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from .conversions import seconds_to_ns

EXIT_OK = 0
EXIT_CONFIG = 2
EXIT_FAILURE = 1
#: Callbacks run between two checks of rclpy.ok() (a stop request is checked after each one).
SPIN_BURST = 100


class StopFlag:
    """Set by SIGINT/SIGTERM; the spin loop polls it."""

    def __init__(self):
        self.requested = False
        self.signal = None

    def __call__(self, signum, frame):
        self.requested = True
        self.signal = signum

    def install(self):
        signal.signal(signal.SIGINT, self)
        signal.signal(signal.SIGTERM, self)


def flush(node, timeout: float = 5.0) -> None:
    """Wait until every subscriber acknowledged what the node published: a reliable sample
    still unacknowledged when the process exits would be lost (e.g. to a lagging recorder).

    The timeout outlasts Fast DDS's 3 s heartbeat period: when a lagging reader's shared-memory
    queue was full, the dropped samples are repaired from the writer's history, but the last
    ones of a sparse topic (nothing newer shows the gap) only after the next heartbeat. With
    2 s, a hot-swap test once lost the plant's final 22 diagnostics to a lagging recorder."""
    deadline = time.monotonic() + timeout
    for publisher in node.publishers:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            break
        publisher.wait_for_all_acked(Duration(nanoseconds=int(remaining * 1e9)))


def clock_ns(node) -> int:
    """The node's clock in nanoseconds: ``node.get_clock().now().nanoseconds`` without building
    a Time object (it is read once per message in the loop's hot paths)."""
    clock = node.get_clock()
    with clock.handle:
        return clock.handle.get_now().nanoseconds


def time_base_restarted(node, stamp_ns: int, last_ns: int, threshold_s: float) -> bool:
    """Without a running clock (it reads 0), an input stamped more than ``threshold_s`` before
    the last one means the time base restarted (a restarted plant, a bag loop). With a clock,
    old stamps are only late inputs: its jump callback (:func:`on_clock_jump_back`) reports a
    restart. The clock is read only for a stamp that far back (this runs for every input)."""
    return stamp_ns < last_ns - seconds_to_ns(threshold_s) and clock_ns(node) <= 0


def seconds_ahead_of_clock(now_ns: int, stamp_ns: int, values: dict) -> float:
    """How far ``stamp_ns`` lies ahead of the clock reading ``now_ns`` when that is more than
    ``max_input_age`` plus two ``time_step`` (an estimate is stamped one step ahead, and /clock
    may arrive after the message it precedes); 0 when it is not, or without a clock (0).
    Accepted, such an input would make every real one look old."""
    lead = seconds_to_ns(values['max_input_age'] + 2 * values['time_step'])
    return (stamp_ns - now_ns) * 1e-9 if now_ns > 0 and stamp_ns > now_ns + lead else 0.0


def on_clock_jump_back(node, callback: Callable[[float], None]):
    """Call ``callback(seconds)`` after the node's clock jumped back (a restarted plant, a bag
    played in a loop). Keep the returned handle as long as the node: dropping it unregisters."""
    def after_jump(jump) -> None:
        if jump.delta.nanoseconds < 0:
            callback(-jump.delta.nanoseconds * 1e-9)
    return node.get_clock().create_jump_callback(
        JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1), on_clock_change=False),
        post_callback=after_jump)


def make_executor():
    """rclpy's EventsExecutor (C++, several times less overhead per callback) when this rclpy
    has it and SNN_EXECUTOR is not 'single'; the SingleThreadedExecutor otherwise."""
    if os.environ.get('SNN_EXECUTOR', 'events') != 'single':
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor()
        except ImportError:
            pass
    return SingleThreadedExecutor()


def run_node(factory: Callable, args=None, name: str = 'node') -> int:
    """Create the node with ``factory()`` and spin it until a signal, shutdown or ``node.done``.

    ``node.done`` (optional attribute) lets a node end the process itself (the plant after its
    last step); ``node.drain(executor)`` (optional) may keep spinning after a stop request (the
    recorder empties its queues); ``node.close()`` (optional) runs before the node is destroyed,
    even when draining failed. An unexpected exception propagates (traceback, exit code 1).
    """
    stop = StopFlag()
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as error:  # bad --ros-args: rclpy raises its own types
        print(f'[{name}] cannot initialise ROS: {error}', file=sys.stderr)
        return EXIT_CONFIG
    stop.install()
    node = executor = None
    code = EXIT_OK
    try:
        node = factory()
        executor = make_executor()
        executor.add_node(node)
        spin_once = executor.spin_once
        while rclpy.ok() and not stop.requested and not getattr(node, 'done', False):
            # checked per callback, rclpy.ok() took 13 % of the recorder's main thread (py-spy);
            # spin_once raises ExternalShutdownException on shutdown anyway
            for _ in range(SPIN_BURST):
                spin_once(timeout_sec=0.05)
                if stop.requested or getattr(node, 'done', False):
                    break
        code = getattr(node, 'exit_code', EXIT_OK)
    except (KeyboardInterrupt, ExternalShutdownException):
        code = EXIT_OK
    except (ValueError, ParameterException) as error:  # invalid parameters: say what to fix
        print(f'[{name}] invalid configuration: {error}', file=sys.stderr)
        code = EXIT_CONFIG
    finally:
        try:
            if node is not None:
                _finish(node, executor)
        finally:
            rclpy.try_shutdown()
    return code


def _finish(node, executor) -> None:
    """Drain, close, flush and destroy ``node``. A failing step does not skip the later ones
    (a bag left unclosed has no metadata.yaml and cannot be read); its exception propagates."""
    try:
        drain = getattr(node, 'drain', None)
        if drain is not None and executor is not None and rclpy.ok():
            drain(executor)
    finally:
        try:
            close = getattr(node, 'close', None)
            if close is not None:
                close()
        finally:
            if rclpy.ok():
                flush(node)
            node.destroy_node()
