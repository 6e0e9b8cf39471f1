"""Every node of the pipeline in one process and one executor (``snn_demo --single-process``).

The same node classes, parameters (the ``--params-file`` arguments apply to every node; their
``/**/<name>`` entries pick each node's own) and topics as the multi-process demo; messages still
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

import sys
import time

#: (name, module, class) in the demo's start order: consumers first, the plant last.
NODE_CLASSES = (
    ('recorder', 'scenario_nodes.recorder_node', 'RecorderNode'),
    ('lqr_controller', 'scenario_nodes.controller_node', 'ControllerNode'),
    ('estimator', 'scenario_nodes.estimator_node', 'EstimatorNode'),
    ('position_sensor', 'scenario_nodes.sensor_node', 'SensorNode'),
)
PLANT_CLASSES = {'cw': ('cw_plant', 'scenario_nodes.plant_node', 'PlantNode'),
                 'basilisk': ('basilisk_plant', 'scenario_nodes.basilisk_plant_node', 'BasiliskPlantNode')}
#: Seconds the others keep spinning after the plant's last step (the last estimate and control).
SETTLE = 0.3


def node_classes(plant: str = 'cw', record: bool = True) -> list[tuple[str, type]]:
    import importlib
    chosen = [entry for entry in NODE_CLASSES if record or entry[0] != 'recorder'] + [PLANT_CLASSES[plant]]
    return [(name, getattr(importlib.import_module(module), cls)) for name, module, cls in chosen]


def run(args=None, plant: str = 'cw', record: bool = True) -> int:
    import rclpy
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    from scenario_nodes.runtime import EXIT_CONFIG, EXIT_OK, SPIN_BURST, StopFlag, make_executor, tune_process

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
        for name, cls in node_classes(plant, record):
            nodes[name] = cls()
            executor.add_node(nodes[name])
        for node in nodes.values():
            node.start()
        tune_process(nodes.values())
        the_plant = nodes[PLANT_CLASSES[plant][0]]
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
    """``python -m snn_tools.run.single_process [--plant cw|basilisk] [--no-record] --ros-args ...``"""
    argv = list(sys.argv[1:] if argv is None else argv)
    ros = argv[argv.index('--ros-args'):] if '--ros-args' in argv else []
    own = argv[:len(argv) - len(ros)]
    plant = 'cw'
    if '--plant' in own:
        plant = own[own.index('--plant') + 1]
    if plant not in PLANT_CLASSES:
        print(f'[single_process] --plant {plant!r}: expected one of {", ".join(PLANT_CLASSES)}',
              file=sys.stderr)
        return 2
    return run(['single_process', *ros], plant, '--no-record' not in own)


if __name__ == '__main__':
    raise SystemExit(main())
