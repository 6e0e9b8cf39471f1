"""Process entry points shared by the nodes: init, spin, clean shutdown, exit codes.

Signals: rclpy's own SIGTERM handling ends ``spin`` in several ways, so the nodes install
their own SIGINT/SIGTERM handlers that ask the spin loop to stop; the node then finishes its
work (a recorder closes its bag) while the context is still valid, and the process exits 0.
A configuration error exits with code 2 and a message that says what to fix.
"""

from __future__ import annotations

import os
import re
import signal
import struct
import sys
import time
from typing import Callable

import rclpy
from rclpy.clock import Clock, ClockType, JumpThreshold
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

EXIT_OK = 0
EXIT_CONFIG = 2
EXIT_FAILURE = 1
#: Callbacks run between two checks of rclpy.ok() (a stop request is checked after each one).
SPIN_BURST = 100


class ProcessHooks:
    """What :func:`run_node` asks of a node, with do-nothing defaults (every node inherits it).

    * ``start()``: after the node joined the executor (a managed node configures and activates
      itself here when autostart is set; ValueError means a configuration error, exit 2);
    * ``done``: set true to end the process (the plant after its last step);
    * ``exit_code``: the process's exit code when it ends normally;
    * ``drain(executor)``: after a stop request, may keep spinning (the recorder empties its queues);
    * ``close()``: before the node is destroyed, even when draining failed (final diagnostics).
    """

    done = False
    exit_code = EXIT_OK

    def start(self) -> None:
        """Called once the node is spinning-ready."""

    def drain(self, executor) -> None:
        """Called after a stop request, before close()."""

    def close(self) -> None:
        """Called before the node is destroyed."""


_NUMBERS = re.compile(r'[-+]?\d[\d.e+-]*')


class ThrottledLog:
    """``log(level, message)`` for the core's callbacks: warnings of the same kind (the same
    text but for its numbers: a stale and a misaligned measurement are two kinds) at most once
    per ``period`` wall seconds; info and errors always."""

    def __init__(self, logger, period: float = 5.0):
        self._logger = logger
        self._period = period
        self._last: dict[str, float] = {}

    def __call__(self, level: str, message: str) -> None:
        if level == 'warning':
            key = _NUMBERS.sub('#', message)
            now = time.monotonic()
            if now - self._last.get(key, -self._period) < self._period:
                return
            self._last[key] = now
        # one call site per severity: rclpy's logger keeps a context per call site and refuses
        # a different severity from the same line
        if level == 'error':
            self._logger.error(message)
        elif level == 'warning':
            self._logger.warning(message)
        else:
            self._logger.info(message)


class Answers:
    """The last few messages a node sent, by the stamp of the input they answered: in lockstep
    the plant sends a state again when its control does not come (a sample lost on a
    best-effort link), and every node answers a repeated input with the same answer."""

    def __init__(self, keep: int = 8):
        self._keep = keep
        self._sent: dict[int, bytes] = {}
        self.resent = 0

    def remember(self, stamp_ns: int, data: bytes) -> None:
        self._sent[stamp_ns] = data
        if len(self._sent) > self._keep:
            del self._sent[min(self._sent)]

    def resend(self, stamp_ns: int, publisher) -> bool:
        """Publish again what answered ``stamp_ns``; False if nothing did (or it is forgotten)."""
        data = self._sent.get(stamp_ns)
        if data is None:
            return False
        publisher.publish(data)
        self.resent += 1
        return True

    def clear(self) -> None:
        self._sent.clear()


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


class MatchHold:
    """Do ``then`` once a publisher has matched ``wanted`` subscriptions on its own side, or
    after ``match_wait`` wall seconds with a warning naming the count; at once when ``wanted``
    is 0. DDS matches the two ends of a pair separately, and what a publisher sends before its
    end matched is lost to that subscriber (best effort, volatile). A node of the loop therefore
    subscribes to its input only once its output reaches the nodes after it, so the plant, which
    starts on matched 'truth' subscriptions, starts only once the chain is matched downstream
    (docs/decisions.md, 33 and 41). ``count`` reads the matched subscriptions; ``topic`` and
    ``action`` name them in the log."""

    def __init__(self, node, count: Callable[[], int], wanted: int, match_wait: float, then: Callable[[], None],
                 topic: str, action: str):
        self._node, self._count, self._wanted, self._match_wait = node, count, int(wanted), float(match_wait)
        self._then, self._topic, self._action = then, topic, action
        self._started = time.monotonic()
        self._timer = None
        self.done = False
        if self._wanted <= 0:
            self._finish()
        else:
            self._timer = node.create_timer(0.02, self._check, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _check(self) -> None:
        matched = self._count()
        waited = time.monotonic() - self._started
        if matched < self._wanted and waited < self._match_wait:
            return
        if matched < self._wanted:
            self._node.get_logger().warning(
                f"{self._action} after {waited:.1f} s with {matched} of {self._wanted} subscriptions matched on "
                f"'{self._topic}': they may miss the first samples")
        else:
            self._node.get_logger().info(f"'{self._topic}' matched {matched} subscriptions after {waited:.2f} s: "
                                         f'{self._action}')
        self._finish()

    def _finish(self) -> None:
        self.cancel()
        self.done = True
        self._then()

    def cancel(self) -> None:
        """Stop waiting (``then`` is not done)."""
        if self._timer is not None:
            self._node.destroy_timer(self._timer)
            self._timer = None


def flush(node, timeout: float = 5.0) -> None:
    """Wait until every subscriber acknowledged what the node published: a reliable sample
    still unacknowledged when the process exits would be lost (e.g. to a lagging recorder).

    The timeout outlasts Fast DDS's default 3 s heartbeat period: when a lagging reader's
    shared-memory queue was full, the dropped samples are repaired from the writer's history, but
    the last ones of a sparse topic (nothing newer shows the gap) only after the next heartbeat.
    With 2 s, a hot-swap test once lost the plant's final 22 diagnostics to a lagging recorder.
    The package's Fast DDS profile (config/fastdds.xml) heartbeats every 100 ms, so the wait is
    usually that short (docs/decisions.md, 38)."""
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


#: The kernel's CPU latency QoS request (Documentation/power/pm_qos_interface.rst): while a
#: process holds it open with an s32 written, no CPU enters an idle state slower to leave.
CPU_LATENCY_DEVICE = '/dev/cpu_dma_latency'
_held_requests: list[int] = []  # file descriptors held for the process's lifetime


def hold_cpu_wake_latency(microseconds: int, device: str | None = None) -> str | None:
    """Ask the kernel to keep every CPU able to wake within ``microseconds`` (0: idle CPUs
    poll instead of halting) for as long as this process lives, as real-time Linux set-ups do
    (cyclictest's --latency). On a virtual machine a halted vCPU is woken through the host, which
    is the 1x latency tail of docs/performance.md. Costs: idle CPUs busy-poll (power, the host's
    time). Returns None when held, else why not (no device, no permission: the caller says so)."""
    try:
        descriptor = os.open(device or CPU_LATENCY_DEVICE, os.O_WRONLY)
    except OSError as error:
        return f'cannot open {device or CPU_LATENCY_DEVICE}: {error.strerror}'
    try:
        os.write(descriptor, struct.pack('i', int(microseconds)))
    except OSError as error:
        os.close(descriptor)
        return f'cannot write {device or CPU_LATENCY_DEVICE}: {error.strerror}'
    _held_requests.append(descriptor)  # closing it would withdraw the request
    return None


def tune_process(nodes) -> None:
    """Real-time and measurement switches (snn_tools.bench.latency), off unless set:
    ``SNN_CPU_WAKE_LATENCY_US=<us>`` holds the kernel's CPU latency request at that many
    microseconds (:func:`hold_cpu_wake_latency`; 0 keeps idle CPUs polling);
    the garbage collector (``SNN_GC``): by default (``freeze_startup``) every object made while
    starting (the modules, the filter and its compiled kernels) is moved out of its reach once the
    node has started (gc.freeze; collection goes on over what the run makes), so a full
    collection no longer stalls a node for 30-50 ms (docs/decisions.md, 42); ``freeze`` also turns
    automatic collection off (gc.disable; a measurement switch); ``none`` leaves it as Python sets it;
    ``SNN_LOG_LEVEL=debug|info|warn|error``
    sets the nodes' logger level. A bad value is reported on stderr and ignored."""
    wake = os.environ.get('SNN_CPU_WAKE_LATENCY_US')
    if wake:
        try:
            microseconds = int(wake)
            if microseconds < 0:
                raise ValueError
        except ValueError:
            print(f'SNN_CPU_WAKE_LATENCY_US={wake!r} ignored: expected microseconds, an integer >= 0',
                  file=sys.stderr)
        else:
            why_not = hold_cpu_wake_latency(microseconds)
            if why_not:
                print(f'SNN_CPU_WAKE_LATENCY_US={wake}: not held, {why_not}', file=sys.stderr)
    collector = os.environ.get('SNN_GC') or 'freeze_startup'
    if collector not in ('freeze_startup', 'freeze', 'none'):
        print(f'SNN_GC={collector!r} ignored: expected freeze_startup, freeze or none', file=sys.stderr)
        collector = 'freeze_startup'
    if collector != 'none':
        import gc
        gc.collect()
        gc.freeze()
        if collector == 'freeze':
            gc.disable()
    level = os.environ.get('SNN_LOG_LEVEL')
    if level:
        from rclpy.logging import LoggingSeverity
        severity = {'debug': LoggingSeverity.DEBUG, 'info': LoggingSeverity.INFO,
                    'warn': LoggingSeverity.WARN, 'error': LoggingSeverity.ERROR}.get(level)
        if severity is None:
            print(f'SNN_LOG_LEVEL={level!r} ignored: expected debug, info, warn or error', file=sys.stderr)
            return
        for node in nodes:
            node.get_logger().set_level(severity)


def run_node(factory: Callable, args=None, name: str = 'node') -> int:
    """Create the node with ``factory()``, call its ``start()`` and spin it until a signal,
    shutdown or ``node.done`` (see :class:`ProcessHooks`). A configuration error (ValueError,
    ParameterException) exits with code 2 and a message that says what to fix; an unexpected
    exception propagates (traceback, exit code 1).
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
        node.start()
        tune_process([node])
        spin_once = executor.spin_once
        while rclpy.ok() and not stop.requested and not node.done:
            # checked per callback, rclpy.ok() took 13 % of the recorder's main thread (py-spy);
            # spin_once raises ExternalShutdownException on shutdown anyway
            for _ in range(SPIN_BURST):
                spin_once(timeout_sec=0.05)
                if stop.requested or node.done:
                    break
        code = node.exit_code
    except (KeyboardInterrupt, ExternalShutdownException):
        code = EXIT_OK
    except (ValueError, ParameterException) as error:  # invalid parameters: say what to fix
        print(f'[{name}] invalid configuration: {error}', file=sys.stderr)
        code = EXIT_CONFIG
    finally:
        try:
            if node is not None:
                finish_node(node, executor)
        finally:
            rclpy.try_shutdown()
    return code


def finish_node(node, executor) -> None:
    """Drain, close, flush and destroy ``node``. A failing step does not skip the later ones
    (a bag left unclosed has no metadata.yaml and cannot be read); its exception propagates."""
    try:
        if executor is not None and rclpy.ok():
            node.drain(executor)
    finally:
        try:
            node.close()
        finally:
            if rclpy.ok():
                flush(node)
            node.destroy_node()
