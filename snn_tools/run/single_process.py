"""Every node of the pipeline in one process and one executor (``snn_demo --single-process``).

The same nodes as the multi-process demo and the launch file, from the same pipeline
description (scenario_nodes.registry: classes, start order, subscriber counts; the live view
stays a process of its own), with the same parameters (the ``--params-file`` arguments apply to
every node; their ``/**/<name>`` entries pick each node's own) and topics; messages still
travel through the middleware (rclpy has no intra-process transport), but there is one process
to wake instead of five and one executor that runs every callback. The separate processes stay
the default: a crash or a hot swap takes one node there, and the CPU plan spreads them over the
cores.

The process ends when the plant is done (``exit_when_done``) or on SIGINT/SIGTERM; the nodes
then stop as the demo stops them: the others first, the plant, and the recorder last, after it
drained its queues, so the bag is complete (:func:`finish`: the shared executor is shut down
first, never spun again). Exit code as :func:`scenario_nodes.runtime.run_node`.
"""

from __future__ import annotations

import argparse
import sys
import time

from scenario_nodes import registry

#: Seconds the others keep spinning after the plant's last step (the last estimate and control).
SETTLE = 0.3


def build_nodes(plant: str = 'cw', optional=('recorder',), sensor: str = 'position', listeners=None, **options):
    """Yield (name, node) for every node of the run that shares the process, in start order: the
    nodes of scenario_nodes.registry.pipeline(``plant``, ``optional``, ``sensor``), each of its
    registered class, with the subscriber counts of the run as parameter overrides (they win
    over the parameter files, as the launch file's do; ``listeners``: subscribers outside the
    pipeline, topic -> count) and, for a suite's sensor, its own name and topic. ``options`` go
    to every node (e.g. ``context``)."""
    import importlib

    from rclpy.parameter import Parameter

    started = registry.pipeline(plant, optional, sensor)
    counts = registry.subscriber_counts(started, listeners)
    for node in started:
        if node.entry.own_process:
            continue
        cls = getattr(importlib.import_module(node.entry.module), node.entry.node_class)
        overrides = [Parameter(name, value=value) for name, value in counts.get(node.name, {}).items()]
        arguments = {}
        if node.name != node.entry.name or node.remaps:
            rules = [f'__node:={node.name}', *node.remaps]
            arguments['cli_args'] = ['--ros-args', *(part for rule in rules for part in ('-r', rule))]
        yield node.name, cls(parameter_overrides=overrides, **arguments, **options)


def run(args=None, plant: str = 'cw', optional=('recorder',), sensor: str = 'position', listeners=None) -> int:
    """Build the nodes of the run (:func:`build_nodes`) in one executor and spin it until the
    plant is done or a signal comes."""
    import rclpy
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    from scenario_nodes.runtime import EXIT_CONFIG, EXIT_OK, SPIN_BURST, StopFlag, make_executor, tune_process

    plant_name = registry.plant_node(plant)
    stop = StopFlag()
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as error:  # bad --ros-args
        print(f'[single_process] cannot initialise ROS: {error}', file=sys.stderr)
        return EXIT_CONFIG
    stop.install()
    nodes: dict = {}
    executor = spin_once = None
    code = EXIT_OK
    try:
        executor = make_executor()
        for name, node in build_nodes(plant, optional, sensor, listeners):
            nodes[name] = node
            executor.add_node(node)
        for node in nodes.values():
            node.start()
        tune_process(nodes.values())
        the_plant = nodes[plant_name]
        spin_once = executor.spin_once
        while rclpy.ok() and not stop.requested and not the_plant.done:
            for _ in range(SPIN_BURST):
                spin_once(timeout_sec=0.05)
                if stop.requested or the_plant.done:
                    break
        if the_plant.done:  # the estimator's last step and the controller's answer
            settle = time.monotonic() + SETTLE
            while time.monotonic() < settle and rclpy.ok() and not stop.requested:
                spin_once(timeout_sec=0.05)
        code = max((node.exit_code for node in nodes.values()), default=EXIT_OK)
    except (KeyboardInterrupt, ExternalShutdownException):
        code = EXIT_OK
    except (ValueError, ParameterException) as error:
        print(f'[single_process] invalid configuration: {error}', file=sys.stderr)
        code = EXIT_CONFIG
    finally:
        try:
            finish(nodes, executor)
        finally:
            executor = spin_once = None  # freed here, while the context is valid (see finish)
            rclpy.try_shutdown()
    return code


def finish(nodes: dict, executor) -> None:
    """Stop the shared executor, then finish every node without spinning it again: the others
    (final diagnostics, flushed, destroyed), the plant after them, and the recorder last, which
    drains its queues on an executor of its own.

    Why not remove each node from the shared executor and let the recorder spin it (as before,
    which crashed with SIGSEGV in the recorder's drain in 2 of 6 runs): rclpy's EventsExecutor
    (Jazzy, 7.1.6) queues every event of a QoS event handler (a Waitable) with a reference that
    enters the waitable as a context manager. When the waitable is removed from the executor
    while such an event is still queued, the executor later drops the event on its spinning
    thread, which does not hold the GIL, and the last reference's ``__exit__`` runs Python code
    without it. Here the event is the estimator's liveliness monitor seeing the `estimate`
    writer go away as the estimator is destroyed (gdb on the core: ``__exit__`` called from the
    executor's queue with no thread state; a 30-line reproduction crashed in 8 of 12 runs, with
    this teardown in none of 12; upstream, by its title, rclpy issue #1644). ``shutdown()`` clears
    every callback while holding the GIL and never runs the queue again; what is still queued is
    freed with the executor, in Python, with the GIL held."""
    from rclpy.executors import SingleThreadedExecutor

    from scenario_nodes.runtime import finish_node

    try:
        if executor is not None:
            executor.shutdown()
    finally:
        recorder = nodes.get('recorder')
        try:
            for node in nodes.values():  # the plant after the others: it is last in start order
                if node is not recorder:
                    finish_node(node, None)
        finally:
            if recorder is not None:
                drain = SingleThreadedExecutor(context=recorder.context)
                drain.add_node(recorder)
                try:
                    finish_node(recorder, drain)
                finally:
                    drain.shutdown()


def main(argv=None) -> int:
    """``python -m snn_tools.run.single_process [--plant cw|basilisk] [--sensor S] [--no-record]
    [--live-view] [--listener TOPIC ...] --ros-args ...``"""
    argv = list(sys.argv[1:] if argv is None else argv)
    ros = argv[argv.index('--ros-args'):] if '--ros-args' in argv else []
    parser = argparse.ArgumentParser(prog='single_process', description=__doc__.split('\n\n')[0])
    parser.add_argument('--plant', default='cw', choices=tuple(registry.plants()))
    parser.add_argument('--sensor', default='position', choices=tuple(registry.SENSOR_NODES),
                        help='position, or a sensor suite: its sensor nodes each on their own topic')
    parser.add_argument('--no-record', action='store_true', help='without the recorder')
    parser.add_argument('--live-view', action='store_true',
                        help='a live view runs beside, in a process of its own (snn_demo starts it): the '
                             'nodes count it among the subscribers they wait for')
    parser.add_argument('--listener', action='append', default=[], metavar='TOPIC',
                        help='one more subscriber of TOPIC outside the pipeline (a probe), counted likewise')
    own = parser.parse_args(argv[:len(argv) - len(ros)])
    optional = [name for name, asked in (('recorder', not own.no_record), ('live_view', own.live_view)) if asked]
    listeners = {topic: own.listener.count(topic) for topic in own.listener}
    return run(['single_process', *ros], own.plant, optional, own.sensor, listeners)


if __name__ == '__main__':
    raise SystemExit(main())
